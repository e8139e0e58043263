"""One session: the runner plays one episode per goal on a station, each episode logged as it
ends, and the session's summary written last (SESSION_FILE). Every station runs this one loop:
the fake one (deploy/robot/cli.py), the cell (deploy/robot/drivers/cell.py) and the simulated
one (deploy/sim/station.py); each brings its hardware and its part of every episode."""
from __future__ import annotations

import dataclasses
import os
import time
from typing import Callable

from deploy.robot.episode_log import SESSION_FILE, Episode
from deploy.robot.goals import check_goals
from ttmjx.world.files import write_json


@dataclasses.dataclass(frozen=True)
class StationHooks:
    """A station's part of each episode (Runner.run_episodes' callbacks) and of the summary."""
    armed: Callable[[int], float | None] | None = None
    """Before episode i: start its throw; may return the throw's launch time."""
    complete: Callable[[int, Episode], Episode] | None = None
    """After episode i: the episode completed with what the station saw (its events)."""
    no_ball: Callable[[int], None] | None = None
    """A throw that never came: clean up and go on to the next goal (None: raise)."""
    summary: Callable[[list, float], dict] | None = None
    """(episodes, wall seconds) -> the station's own fields of the summary."""

    def episode_callbacks(self) -> dict:
        """Runner.run_episodes' keyword arguments."""
        return {"on_armed": self.armed, "complete": self.complete, "on_no_ball": self.no_ball}


def run_session(runner, goals, out_dir: str | None, hooks: StationHooks) -> dict:
    """One episode per goal [N, 2] on `runner`'s station (Runner.run_episodes; episodes saved
    under out_dir as they end, so a crash loses none); returns the summary, also written to
    out_dir/SESSION_FILE: what every station reports (episodes, mode, overruns, faults, ends,
    policy hash, rate, wall time) and the station's own fields (hooks.summary)."""
    goals = check_goals(goals)
    if out_dir is not None:
        os.makedirs(out_dir, exist_ok=True)
    wall = time.perf_counter()
    episodes = runner.run_episodes(goals, out_dir, **hooks.episode_callbacks())
    wall_s = time.perf_counter() - wall
    out = {"episodes": len(episodes), "goals": int(len(goals)), "mode": runner.mode.value,
           "overruns": runner.overruns, "skipped": runner.skipped, "faults": dict(runner.fault_counts),
           "ends": [e.meta["end"] for e in episodes], "policy_hash": runner.policy_hash,
           "control_hz": runner.contract.control_hz, "wall_s": wall_s, "out": out_dir}
    if hooks.summary is not None:
        out.update(hooks.summary(episodes, wall_s))
    if out_dir is not None:
        write_json(os.path.join(out_dir, SESSION_FILE), out, indent=1)
    return out
