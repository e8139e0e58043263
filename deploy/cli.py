"""The runner's command line (python -m deploy): run episodes toward goals and log them.

    python -m deploy --fake --goals "0.7,0.3;0.4,-0.5" --repeat 5 --out runs/dry
    python -m deploy --fake --goals goals.json --out runs/dry --realtime

Until the robot drivers and the exported-policy loader land, only --fake (fake robot and
tracker, scripted follow-ball policy) runs; it prints a JSON summary. `main(argv)` is what
`ttmjx robot run` will call.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from deploy.contract import Contract
from deploy.goals import check_goal_region, episode_goals, goals_from_arg
from deploy.hardware import MonotonicClock
from deploy.runner import Runner, RunnerConfig


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m deploy", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--goals", required=True, help="'x,y;x,y' or a .json/.npy/.csv/.txt file")
    p.add_argument("--repeat", type=int, default=1, help="episodes per goal (in a row)")
    p.add_argument("--out", default=None, help="directory for the episode logs")
    p.add_argument("--rate", type=float, default=20.0, help="control rate, Hz (20 or 60 on the robot)")
    p.add_argument("--frame-stack", type=int, default=8)
    p.add_argument("--stale-ms", type=float, default=100.0, help="joint/ball data older than this -> hold")
    p.add_argument("--fake", action="store_true", help="fake robot and tracker (dry run)")
    p.add_argument("--realtime", action="store_true", help="with --fake: pace on the real clock")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        goals = episode_goals(check_goal_region(goals_from_arg(args.goals)), args.repeat)
        contract = dataclasses.replace(Contract(), control_hz=args.rate, frame_stack=args.frame_stack)
        config = RunnerConfig(stale_s=args.stale_ms / 1000.0)
    except (ValueError, OSError) as e:
        print(f"python -m deploy: {e}", file=sys.stderr)
        return 2
    if not args.fake:
        print("no robot or tracker driver is installed yet; use --fake for a dry run", file=sys.stderr)
        return 2
    from deploy.fakes import FakeClock, FakeRobot, FakeTracker, FollowBallPolicy
    clock = MonotonicClock() if args.realtime else FakeClock(start=0.0)
    robot, tracker = FakeRobot(clock, contract), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, FollowBallPolicy(contract), contract, config)
    episodes = runner.run_episodes(goals, args.out, on_armed=lambda i: tracker.throw_in(0.3))
    print(json.dumps({"episodes": len(episodes), "goals": len(goals), "mode": runner.mode.value,
                      "overruns": runner.overruns, "skipped": runner.skipped,
                      "faults": dict(runner.fault_counts),
                      "ends": [e.meta["end"] for e in episodes], "out": args.out}, indent=1))
    return 0 if len(episodes) == len(goals) else 1
