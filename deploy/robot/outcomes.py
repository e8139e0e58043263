"""What became of a robot episode's throw, on the robot's side: the station's events of one
throw (`ThrowEvents`, from the simulated station or the cell's referee), the runner's episode
completed with them (`complete_episode`), and a session's goal metrics and command latencies.

numpy only (no JAX, no MuJoCo): the cell's drivers and the simulated station both use it.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from deploy.robot.contract import Contract
from deploy.robot.episode_log import Episode
from ttmjx.world import record
from ttmjx.world.goals import goal_metrics


@dataclasses.dataclass
class ThrowEvents:
    """What happened to one throw (times on the clock's time base)."""
    t_launch: float
    launch_pos: np.ndarray
    launch_vel: np.ndarray
    launch_spin: np.ndarray
    aim: np.ndarray
    hit: bool = False
    t_hit: float = math.nan
    bounce_own: bool = False
    net: bool = False
    landed: bool = False
    landing: np.ndarray = dataclasses.field(default_factory=lambda: np.full(2, np.nan))
    t_land: float = math.nan
    on_opponent: bool = False
    fell: bool = False
    done: bool = False
    t_done: float = math.nan

    def take(self, ev, t0: float, dt: float) -> None:
        """Copy in the world's events of this throw (env.Events whose step indices count physics
        steps of dt from time t0)."""
        at = lambda step: t0 + int(step) * dt if int(step) >= 0 else math.nan  # noqa: E731
        self.hit, self.t_hit = bool(ev.hit), at(ev.hit_step)
        self.bounce_own, self.net, self.on_opponent = bool(ev.bounce_own), bool(ev.net), bool(ev.on_opponent)
        self.landed, self.landing = bool(ev.landed), np.asarray(ev.landing, np.float64)
        self.done, self.t_done = bool(ev.done), at(ev.done_step)
        self.fell = self.done and not self.landed
        self.t_land = self.t_done if self.landed else math.nan

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, np.ndarray):
                v = [None if not np.isfinite(x) else float(x) for x in v]
            elif isinstance(v, float):
                v = None if not math.isfinite(v) else v
            out[f.name] = v
        return out


def complete_episode(ep: Episode, ev: ThrowEvents | None, contract: Contract) -> Episode:
    """The runner's episode with the station's events and the true launch filled in."""
    tr = ep.traj
    if ev is None:
        meta = {**ep.meta, "events_detected": False, "station": "sim"}
        return Episode(tr, ep.extras, meta)
    t0, T = float(ep.meta["t0"]), contract.horizon
    hit_step = -1
    if ev.hit:
        hit_step = int(np.clip(math.floor((ev.t_hit - t0) / contract.dt + 1e-9), 0, T - 1))
    landing = ev.landing if (ev.hit and ev.landed) else np.full(2, np.nan)
    traj = record.to_numpy(tr._replace(
        hit=np.array([ev.hit]), hit_step=np.array([hit_step], np.int32),
        landing=np.asarray(landing, np.float32)[None],
        on_opponent=np.array([ev.hit and ev.landed and ev.on_opponent]),
        bounce_own=np.array([ev.bounce_own]), net=np.array([ev.net]),
        launch_pos=ev.launch_pos[None], launch_vel=ev.launch_vel[None],
        launch_spin=ev.launch_spin[None], aim=ev.aim[None]))
    meta = {**ep.meta, "events_detected": True, "events": ev.to_dict(), "station": "sim"}
    return Episode(traj, ep.extras, meta)


def goal_summary(episodes: list[Episode]) -> dict:
    """ttmjx.world.goals.goal_metrics over the episodes' landings, plus the fraction that landed
    on the opponent's half (zeros, mean_dist NaN, without episodes)."""
    if not episodes:
        return {"within_30cm": 0.0, "within_20cm": 0.0, "mean_dist": math.nan, "hit_rate": 0.0,
                "on_table_rate": 0.0, "mean_dist_landed": math.nan, "goals": 0, "on_opponent": 0.0}
    tr = record.concat([e.traj for e in episodes])
    return {**goal_metrics(tr.landing, tr.goal, tr.hit, tr.on_opponent), "on_opponent": float(np.mean(tr.on_opponent))}


def latency_ms(episodes: list[Episode]) -> dict | None:
    """p50, p99 and max of the command latencies (ms) over the episodes (None without any)."""
    lat = np.concatenate([e.extras["latency"] for e in episodes]) if episodes else np.zeros(0)
    lat = lat[np.isfinite(lat)] * 1e3
    if not lat.size:
        return None
    return {"p50": float(np.percentile(lat, 50)), "p99": float(np.percentile(lat, 99)), "max": float(lat.max())}
