"""The runner's command lines: `python -m deploy` and the `ttmjx export` / `ttmjx robot ...`
subcommands (registered into ttmjx/cli.py through `register`).

    ttmjx export RUN_OR_CHECKPOINT --out DIR [--ensemble | --member I] [--control-hz HZ] --json
    ttmjx robot run --policy DIR --station sim --goals "0.7,0.3;0.4,-0.5" --n 5 --out LOGDIR --json
    ttmjx robot run --policy DIR --station sim --goals five --n 5 --json    (the five-goal protocol)
    ttmjx robot bench --json                    (numpy LSTM 2x1024 step latency on one core)
    python -m deploy --fake --goals "0.7,0.3;0.4,-0.5" --repeat 5 --out runs/dry
    python -m deploy --policy DIR --station sim --goals goals.json --out runs/sim

--station sim: the simulated station (deploy/station.py, MuJoCo C physics and the thrower);
--station fake / --fake: fake kinematics (deploy/fakes.py). There is no hardware driver yet.
Every command prints one JSON object as its last line with --json.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys

from deploy.contract import Contract
from deploy.goals import check_goal_region, episode_goals, goals_from_arg
from deploy.hardware import MonotonicClock
from deploy.runner import Runner, RunnerConfig

STATIONS = ("sim", "fake")


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def session_goals(spec: str, n: int, seed: int = 0):
    """[N, 2] goals of a session: 'five' (goals A..E, n attempts each), 'uniform' (n goals
    uniform over the opponent's half), or an inline 'x,y;x,y' / goal file (each repeated n
    times in a row). All must lie on the opponent's half."""
    import numpy as np
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    if spec == "five":
        from eval.metrics import FIVE_GOALS
        g = np.array([FIVE_GOALS[k] for k in FIVE_GOALS for _ in range(n)], np.float32)
    elif spec == "uniform":
        from ttmjx.world.config import Table, opponent_half
        (x0, x1), (y0, y1) = opponent_half(Table())
        u = np.random.default_rng(seed).uniform(size=(n, 2))
        g = np.stack([x0 + u[:, 0] * (x1 - x0), y0 + u[:, 1] * (y1 - y0)], 1).astype(np.float32)
    else:
        g = episode_goals(goals_from_arg(spec), n)
    return check_goal_region(g)


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
    p.add_argument("--station", choices=STATIONS, default=None, help="sim (MuJoCo) or fake")
    p.add_argument("--rate", type=float, default=20.0, help="--fake without --policy: control rate, Hz")
    p.add_argument("--frame-stack", type=int, default=8, help="--fake without --policy")
    p.add_argument("--stale-ms", type=float, default=100.0, help="joint/ball data older than this -> hold")
    p.add_argument("--fake", action="store_true", help="fake robot and tracker (same as --station fake)")
    p.add_argument("--realtime", action="store_true", help="pace on the real clock")
    p.add_argument("--seed", type=int, default=0)
    return p.parse_args(argv)


def _run_fake(goals, out, policy_dir, rate, frame_stack, config, realtime) -> dict:
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


def main(argv=None) -> int:
    args = parse_args(argv)
    station = "fake" if args.fake else args.station
    try:
        goals = session_goals(args.goals, args.repeat, args.seed)
        config = RunnerConfig(stale_s=args.stale_ms / 1000.0)
        if station is None:
            raise ValueError("no robot or tracker driver is installed yet; use --station sim "
                             "(simulated station) or --fake (dry run)")
        if station == "sim":
            if not args.policy:
                raise ValueError("--station sim needs --policy DIR (an export)")
            from deploy.station import run_sim
            out = run_sim(args.policy, goals, args.out, seed=args.seed, realtime=args.realtime,
                          config=config)
        else:
            out = _run_fake(goals, args.out, args.policy, args.rate, args.frame_stack, config,
                            args.realtime)
    except (ValueError, OSError) as e:
        print(f"python -m deploy: {e}", file=sys.stderr)
        return 2
    print(json.dumps(_json_safe(out), indent=1))
    return 0 if out["episodes"] == out["goals"] else 1


# --------------------------------------------------------------------------------------------
# ttmjx export / ttmjx robot
# --------------------------------------------------------------------------------------------
def _print(args, obj: dict, text: str) -> None:
    obj = _json_safe(obj)
    print(json.dumps(obj) if args.json else text)


def cmd_export(args) -> None:
    from deploy.export import export, params_from_checkpoint
    params, pcfg, world, source = params_from_checkpoint(args.checkpoint, args.step)
    path = export(params, pcfg, world, args.out, member=args.member, ensemble=args.ensemble,
                  source=source, control_hz=args.control_hz)
    from deploy.export import load_export
    policy, contract = load_export(path)       # the export must pass its own checks
    out = {"out": path, "source": source, "kind": pcfg.kind, "hidden": pcfg.hidden,
           "layers": pcfg.layers, "members": policy.members, "control_hz": contract.control_hz,
           "policy_hash": policy.policy_hash, "self_test_error": policy.self_test_error}
    _print(args, out, f"exported {source} -> {path} ({pcfg.kind} {pcfg.layers}x{pcfg.hidden}, "
                      f"{policy.members} member(s), {contract.control_hz:g} Hz); golden self-test "
                      f"max error {policy.self_test_error:.2g}")


def cmd_robot_run(args) -> None:
    goals = session_goals(args.goals, args.n, args.seed)
    config = RunnerConfig(stale_s=args.stale_ms / 1000.0)
    if args.station == "sim":
        from deploy.station import run_sim
        out = run_sim(args.policy, goals, args.out, seed=args.seed, distribution=args.distribution,
                      realtime=args.realtime, charge_compute=not args.no_compute_time, config=config)
    else:
        out = _run_fake(goals, args.out, args.policy, None, None, config, args.realtime)
    m = out.get("metrics", {})
    text = (f"{out['episodes']}/{out['goals']} episodes; " +
            (f"within 30 cm {m.get('within_30cm', 0):.0%}, 20 cm {m.get('within_20cm', 0):.0%}, "
             f"hit rate {m.get('hit_rate', 0):.0%}; " if m else "") +
            f"faults {out['faults']}; logs in {out['out']}")
    _print(args, out, text)
    if out["episodes"] != out["goals"]:
        sys.exit(1)


def cmd_robot_bench(args) -> None:
    from deploy.numpy_policy import benchmark
    out = benchmark(args.kind, args.hidden, args.layers, args.members, steps=args.steps,
                    threads=args.threads)
    text = (f"{args.kind} {args.layers}x{args.hidden} x{args.members} on {args.threads} thread(s), "
            f"core {out['cpu']}: step p50 {out['p50_ms']:.3f} ms, p99 {out['p99_ms']:.3f} ms, "
            f"max {out['max_ms']:.3f} ms")
    if "prepared_p50_ms" in out:
        text += (f"; after prepare(): p50 {out['prepared_p50_ms']:.3f} ms, p99 "
                 f"{out['prepared_p99_ms']:.3f} ms (prepare p50 {out['prepare_p50_ms']:.3f} ms)")
    _print(args, out, text)


def register(sub, common) -> None:
    """Add `export` and `robot {run, bench}` to the ttmjx command line."""
    sp = sub.add_parser("export", help="safetensors weights + contract + golden self-test for the robot runner")
    common(sp, dist=False)          # --json, --control-hz (the robot's rate; default: the training rate)
    sp.add_argument("checkpoint", help="a checkpoint directory or a run directory holding checkpoints/")
    sp.add_argument("--out", required=True, help="export directory (must not hold an export)")
    sp.add_argument("--step", type=int, default=None, help="checkpoint step (default: the newest)")
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--ensemble", action="store_true", help="all members; the actions are averaged")
    g.add_argument("--member", type=int, default=None, help="one member of an ensemble")
    sp.set_defaults(fn=cmd_export)

    rp = sub.add_parser("robot", help="the robot runner: play an exported policy on a station")
    rsub = rp.add_subparsers(dest="robot_cmd", required=True)
    run = rsub.add_parser("run", help="play episodes toward goals and log them")
    run.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    run.add_argument("--policy", required=True, help="an export directory (ttmjx export)")
    run.add_argument("--station", choices=STATIONS, required=True,
                     help="sim: MuJoCo C physics and the thrower; fake: simple kinematics")
    run.add_argument("--goals", required=True,
                     help="'x,y;x,y', a goal file, 'five' (goals A..E) or 'uniform'")
    run.add_argument("--n", type=int, default=1,
                     help="attempts per goal ('uniform': the number of goals)")
    run.add_argument("--out", default=None, help="directory for the episode logs")
    run.add_argument("--seed", type=int, default=0, help="throws (and uniform goals)")
    run.add_argument("--distribution", default=None, choices=("narrow", "any", "varied"),
                     help="throws (default: the export's training world)")
    run.add_argument("--stale-ms", type=float, default=100.0)
    run.add_argument("--realtime", action="store_true", help="pace on the real clock")
    run.add_argument("--no-compute-time", action="store_true",
                     help="sim: do not charge the runner's computation time to the simulated clock")
    run.set_defaults(fn=cmd_robot_run)

    bench = rsub.add_parser("bench", help="numpy policy step latency on one CPU core")
    bench.add_argument("--json", action="store_true")
    bench.add_argument("--kind", choices=("lstm", "framestack"), default="lstm")
    bench.add_argument("--hidden", type=int, default=1024)
    bench.add_argument("--layers", type=int, default=2)
    bench.add_argument("--members", type=int, default=1)
    bench.add_argument("--steps", type=int, default=2000)
    bench.add_argument("--threads", type=int, default=1)
    bench.set_defaults(fn=cmd_robot_bench)
