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
import sys

from deploy.contract import Contract
from deploy.goals import session_goals
from deploy.hardware import MonotonicClock
from deploy.runner import Runner, RunnerConfig
from ttmjx.world.files import json_safe

STATIONS = ("sim", "fake", "cell")


# --------------------------------------------------------------------------------------------
# python -m deploy
# --------------------------------------------------------------------------------------------
def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m deploy", description=__doc__,
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
    episodes = runner.run_episodes(goals, out, on_armed=lambda i: tracker.throw_in(0.3))
    return {"episodes": len(episodes), "goals": len(goals), "mode": runner.mode.value,
            "overruns": runner.overruns, "skipped": runner.skipped,
            "faults": dict(runner.fault_counts), "policy_hash": runner.policy_hash,
            "ends": [e.meta["end"] for e in episodes], "out": out}


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


def main(argv=None) -> int:
    args = parse_args(argv)
    station = "fake" if args.fake else args.station
    try:
        goals = session_goals(args.goals, args.repeat, args.seed)
        config = RunnerConfig(stale_s=args.stale_ms / 1000.0)
        if station is None:
            raise ValueError("no station given; use --station cell --config cell.toml (the drivers), "
                             "--station sim (simulated station) or --fake (dry run)")
        if station == "cell":
            out = run_cell_station(args.policy, goals, args.config, args.out, config)
        elif station == "sim":
            if not args.policy:
                raise ValueError("--station sim needs --policy DIR (an export)")
            from deploy.station import run_sim
            out = run_sim(args.policy, goals, args.out, seed=args.seed, realtime=args.realtime,
                          config=config, timing=args.timing, allow_untrained=args.allow_untrained_timing)
        else:
            out = run_fake(goals, args.out, args.policy, args.rate, args.frame_stack, config,
                           args.realtime)
    except (ValueError, OSError) as e:
        print(f"python -m deploy: {e}", file=sys.stderr)
        return 2
    print(json.dumps(json_safe(out), indent=1, allow_nan=False))
    return 0 if out["episodes"] == out["goals"] else 1
