"""The robot side's command line, `python -m deploy` (numpy only: no JAX at import), and what
`ttmjx robot run` (ttmjx/cli.py) shares with it: the fake station.

    python -m deploy --fake --goals "0.7,0.3;0.4,-0.5" --repeat 5 --out runs/dry
    python -m deploy --policy DIR --station sim --goals goals.json --out runs/sim
    python -m deploy --policy DIR --station sim --goals five --repeat 5   (the five-goal protocol)

--station sim: the simulated station (deploy/station.py, MuJoCo C physics and the thrower);
--station fake / --fake: fake kinematics (deploy/fakes.py); --station cell: the real cell's
drivers (deploy/drivers/, `pip install -e '.[robot]'`) with `ttmjx robot run --config cell.toml`.
It prints one JSON object (non-finite numbers as null).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

from deploy.contract import Contract
from deploy.episode_log import SESSION_FILE, read_session, session, session_state
from deploy.goals import session_goals
from deploy.hardware import MonotonicClock
from deploy.runner import Runner, RunnerConfig
from ttmjx.world.files import json_safe, sha256_file, write_json

STATIONS = ("sim", "fake", "cell")


# --------------------------------------------------------------------------------------------
# python -m deploy
# --------------------------------------------------------------------------------------------
class OneLineParser(argparse.ArgumentParser):
    """Bad input is one line, `python -m deploy: error: ...`, and exit code 2 (no usage block)."""
    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}; see --help\n")


def parse_args(argv=None) -> argparse.Namespace:
    p = OneLineParser(prog="python -m deploy", description=__doc__,
                      formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--goals", required=True, help="'x,y;x,y', a .json/.npy/.csv/.txt file, 'five' or 'uniform'")
    p.add_argument("--repeat", type=int, default=1, help="episodes per goal (in a row)")
    p.add_argument("--out", default=None, help="directory for the episode logs")
    p.add_argument("--policy", default=None, help="an export directory (deploy/export.py)")
    p.add_argument("--station", choices=STATIONS, default=None, help="sim (MuJoCo), fake, or cell (drivers)")
    p.add_argument("--config", default=None, help="--station cell: the cell config (TOML)")
    p.add_argument("--rate", type=float, default=20.0, help="--fake without --policy: control rate, Hz")
    p.add_argument("--frame-stack", type=int, default=8, help="--fake without --policy")
    p.add_argument("--stale-ms", type=float, default=100.0, help="joint/ball data older than this -> hold")
    p.add_argument("--fake", action="store_true", help="fake robot and tracker (same as --station fake)")
    p.add_argument("--realtime", action="store_true", help="pace on the real clock")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timing", default=None,
                   help="--station sim: the station's timing: the export's (default: what the policy was "
                        "trained under) or a profile (nominal, zero)")
    p.add_argument("--allow-untrained-timing", action="store_true",
                   help="--station sim: play a station timing outside the policy's trained range")
    return p.parse_args(argv)


# --rate (the fake robot's control rate without an export): the fake stands in for the cell, whose
# ABB controller takes one joint target per EGM cycle, 4 ms (250 Hz, deploy/drivers/egm.py): a
# policy stepping faster sends targets the arm never receives, and the runner's per-tick logs grow
# with the rate (1e9 Hz: 1.6e9 ticks, a 77 GB observation array). Below 1 Hz an episode (1.6 s)
# holds fewer than two ticks. Exported policies carry their own rate (20, 60 or 100 Hz).
RATE_HZ = (1.0, 250.0)
# --frame-stack: as `ttmjx robot bench --frame-stack` (each frame is a policy input row).
FRAME_STACK = (1, 64)
# --repeat: episodes per goal, as `ttmjx robot run --n`.
REPEAT = (1, 100_000)
STALE_MS = (0.1, 10_000.0)          # as `ttmjx robot run --stale-ms`


def check_args(args: argparse.Namespace) -> None:
    """ValueError naming the flag, its value and the allowed range, before any work."""
    for flag, value, (lo, hi) in (("--repeat", args.repeat, REPEAT), ("--rate", args.rate, RATE_HZ),
                                  ("--frame-stack", args.frame_stack, FRAME_STACK),
                                  ("--stale-ms", args.stale_ms, STALE_MS), ("--seed", args.seed, (0, 2 ** 32 - 1))):
        if not lo <= value <= hi:      # NaN fails too
            unit = " Hz" if flag == "--rate" else ""
            num = lambda x: f"{x:g}" if isinstance(x, float) else str(x)   # noqa: E731
            raise ValueError(f"{flag} {num(value)}: expected {num(lo)} to {num(hi)}{unit}" +
                             (" (the cell's EGM cycle is 250 Hz; a 1.6 s episode needs >= 2 ticks)"
                              if flag == "--rate" else ""))


def run_fake(goals, out, policy_dir, rate, frame_stack, config, realtime) -> dict:
    """Play one episode per goal on the fake robot and tracker: the export in policy_dir, or
    without one a ball-following policy at `rate` Hz over `frame_stack` frames."""
    from deploy.fakes import FakeClock, FakeRobot, FakeTracker, FollowBallPolicy
    if policy_dir:
        from deploy.export import load_export
        policy, contract = load_export(policy_dir)
    else:
        contract = dataclasses.replace(Contract(), control_hz=rate, frame_stack=frame_stack)
        policy = FollowBallPolicy(contract)
    clock = MonotonicClock() if realtime else FakeClock(start=0.0)
    robot, tracker = FakeRobot(clock, contract), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, policy, contract, config)
    if out is not None:
        os.makedirs(out, exist_ok=True)
    episodes = runner.run_episodes(goals, out, on_armed=lambda i: tracker.throw_in(0.3))
    summary = {"episodes": len(episodes), "goals": len(goals), "mode": runner.mode.value,
               "overruns": runner.overruns, "skipped": runner.skipped,
               "faults": dict(runner.fault_counts), "policy_hash": runner.policy_hash,
               "ends": [e.meta["end"] for e in episodes], "out": out}
    if out is not None:
        write_json(os.path.join(out, SESSION_FILE), summary, indent=1)
    return summary


def run_cell_station(policy_dir, goals, config_path, out, config) -> dict:
    """--station cell: the export played on the cell of config_path (deploy/drivers/cell.py)."""
    if not policy_dir:
        raise ValueError("--station cell needs --policy DIR (an export)")
    if not config_path:
        raise ValueError("--station cell needs --config FILE (a cell config, deploy/drivers/cell.example.toml)")
    try:
        from deploy.drivers.cell import run_cell
    except ImportError as e:
        raise ValueError(f"--station cell needs the robot extra (pip install -e '.[robot]'): {e}") from None
    return run_cell(policy_dir, goals, config_path, out, runner_config=config)


def export_hash(policy_dir: str | None) -> str | None:
    """sha256 of an export's manifest.json (which hashes every other file), or None."""
    path = os.path.join(policy_dir, "manifest.json") if policy_dir else None
    return sha256_file(path) if path and os.path.isfile(path) else None


def play(station: str, policy: str | None, goals, out: str | None, config: RunnerConfig, *, seed: int = 0,
         distribution: str | None = None, timing: str | None = None, allow_untrained: bool = False,
         realtime: bool = False, charge_compute: bool = False, rate: float | None = None,
         frame_stack: int | None = None, cell_config: str | None = None, log=None) -> dict:
    """One session on `station` with its episode logs in `out` (deploy.episode_log.session): a new
    directory, or the same command's unfinished session, resumed (its logged episodes replayed
    and checked, the rest logged), or its finished one (its summary read back). A directory that
    holds anything else is refused, naming what it holds."""
    plan = {"station": station, "export": export_hash(policy), "goals": np.asarray(goals).tolist(), "seed": seed,
            "distribution": distribution, "timing": timing, "allow_untrained_timing": allow_untrained,
            "stale_s": config.stale_s, "realtime": realtime, "charge_compute": charge_compute,
            **({"rate": rate, "frame_stack": frame_stack} if station == "fake" and not policy else {})}
    state, done = session_state(out, plan)
    if state == "finished":
        if log:
            log(f"{out}: this session finished earlier ({done} episodes); its summary is {SESSION_FILE}")
        return read_session(out)
    if state == "resume":
        if station == "cell" or realtime or charge_compute:
            raise ValueError(f"--out {out!r} holds {done} episode(s) of this session, unfinished; a session on "
                             f"{'the cell' if station == 'cell' else 'the real clock'} cannot be replayed to resume "
                             f"it: choose a new --out for the remaining goals (ttmjx train --data reads both)")
        if log:
            log(f"resuming {out}: {done} of {len(goals)} episodes logged; the session is replayed from its start "
                f"(the logged episodes checked, not rewritten) and the rest logged")
    with session(out, plan):
        if station == "cell":
            return run_cell_station(policy, goals, cell_config, out, config)
        if station == "sim":
            if not policy:
                raise ValueError("--station sim needs --policy DIR (an export)")
            from deploy.station import run_sim
            return run_sim(policy, goals, out, seed=seed, distribution=distribution, realtime=realtime,
                           charge_compute=charge_compute, config=config, timing=timing,
                           allow_untrained=allow_untrained)
        return run_fake(goals, out, policy, rate, frame_stack, config, realtime)


class Stopped(BaseException):
    """SIGTERM during a session: unwinds like Ctrl-C (the logged episodes stay)."""


def main(argv=None) -> int:
    args = parse_args(argv)
    station = "fake" if args.fake else args.station
    import signal

    def stop(signum, frame):
        raise Stopped(signum)
    old = signal.signal(signal.SIGTERM, stop)
    try:
        check_args(args)
        goals = session_goals(args.goals, args.repeat, args.seed)
        config = RunnerConfig(stale_s=args.stale_ms / 1000.0)
        if station is None:
            raise ValueError("no station given; use --station cell --config cell.toml (the drivers), "
                             "--station sim (simulated station) or --fake (dry run)")
        out = play(station, args.policy, goals, args.out, config, seed=args.seed, realtime=args.realtime,
                   timing=args.timing, allow_untrained=args.allow_untrained_timing, rate=args.rate,
                   frame_stack=args.frame_stack, cell_config=args.config,
                   log=lambda m: print(f"python -m deploy: {m}", file=sys.stderr))
    except (ValueError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError) as e:
        print(f"python -m deploy: {' '.join(str(e).split())}", file=sys.stderr)
        return 2
    except OSError as e:          # disk full, permission: the machine, not the input
        where = f"{e.filename}: " if e.filename else ""
        print(f"python -m deploy: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except (Stopped, KeyboardInterrupt) as e:
        name = "SIGTERM" if isinstance(e, Stopped) else "SIGINT"
        print(f"python -m deploy: stopped by {name}; the episodes logged so far are kept"
              f"{' in ' + args.out + ': run the same command to resume' if args.out else ''}", file=sys.stderr)
        return 143 if isinstance(e, Stopped) else 130
    finally:
        signal.signal(signal.SIGTERM, old)
    print(json.dumps(json_safe(out), indent=1, allow_nan=False))
    return 0 if out["episodes"] == out["goals"] else 1
