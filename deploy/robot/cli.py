"""The robot side's commands, `ttmjx robot run` and `ttmjx robot bench` (standard library,
numpy and tyro at import: they start on a robot's computer without JAX or MuJoCo; ttmjx/entry.py
sends them here without importing the simulator side).

    ttmjx robot run --station fake --goals "0.7,0.3;0.4,-0.5" --n 5 --out runs/dry   (dry run)
    ttmjx robot run --policy EXPORT --station cell --config cell.toml --goals five --n 5
    ttmjx robot run --policy EXPORT --station sim --goals five --out runs/sim  (simulator side)

--station fake: fake kinematics (deploy/robot/fakes.py); cell: the real cell's drivers
(deploy/robot/drivers/, `pip install 'ttmjx[robot]'`); sim: the simulated station
(deploy/sim/station.py), which the simulator side's command line hands to `play`.
"""
from __future__ import annotations

import dataclasses
import os
import sys
from typing import Callable, ClassVar, Literal

import numpy as np

from deploy.robot.contract import Contract
from deploy.robot.episode_log import SESSION_FILE, read_session, session, session_state
from deploy.robot.exported import read_contract
from deploy.robot.goals import session_goals
from deploy.robot.hardware import MonotonicClock
from deploy.robot.policy_bench import benchmark
from deploy.robot.runner import Runner, RunnerConfig, stale_bound_error
from deploy.robot.session import StationHooks, run_session
from deploy.robot.timing_check import timing_line, trained_timing
from ttmjx import commandline
from ttmjx.commandline import Command, Flag, Report, report
from ttmjx.world.config import THROW_DISTRIBUTIONS
from ttmjx.world.files import sha256_file

STATIONS = ("sim", "fake", "cell")
# The dry run's policy without an export (--station fake, no --policy): a ball follower at a rate
# and frame stack of the exported policies' kind.
DRY_RUN_HZ = 20.0
DRY_RUN_FRAMES = 8


# --------------------------------------------------------------------------------------------
# Arguments
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotRunArgs(Report):
    """Play an exported policy toward goals on a station and log the episodes."""
    BOUNDS: ClassVar[dict] = {"n": (1, 100_000), "stale_ms": (0.1, 10_000.0)}
    policy: str | None = None
    """An export directory (ttmjx export --out); None only with --station fake: a ball-following
    dry-run policy (20 Hz, 8 frames) that checks the runner, its modes and logs without an export."""
    station: Literal[STATIONS]
    """sim: MuJoCo C physics and the thrower; fake: simple kinematics; cell: the drivers (--config)."""
    goals: str
    """A --goals value (ttmjx.world.goalspec, the grammar eval reads too): N uniform goals, 'uniform'
    (--n of them), 'five' (goals A-E), 'x,y;x,y' goals in metres, or a goal file (.csv header x,y,
    or .npy [N, 2]); goals on the opponent's half, each --n times in a row ('uniform': once)."""
    n: int = 1
    """Attempts per goal ('uniform': the number of goals)."""
    out: str | None = None
    """Directory for the episode logs (ttmjx train --data reads them), new or empty; the same command
    on it again resumes an unfinished session (or reports the finished one); None: no logs."""
    seed: int = 0
    """Seed of the throws (and of uniform goals)."""
    distribution: Literal[THROW_DISTRIBUTIONS] | None = None
    """Throws; None: the export's training world."""
    stale_ms: float = 100.0
    """Joint or ball data older than this (ms) -> hold."""
    realtime: Flag = False
    """Pace on the real clock."""
    charge_compute: Flag = False
    """sim: charge the runner's own computation time to the simulated clock (then two runs with
    the same seed can differ by the machine's speed); off: runs are reproducible by seed."""
    timing: str | None = None
    """sim: sensor and actuation timing of the station; None (or export): the timing the policy was
    trained under (the export's contract), each throw drawing its latencies and command delay
    within the trained ranges as a cell's drift; centre: that timing fixed at its centre; or a
    profile of ttmjx.world.config.TIMING_PROFILES: nominal (tracker 125 Hz, 10 ms; joints 250 Hz,
    4 ms; commands 8 ms) or zero (ideal). A timing outside the trained range is refused."""
    allow_untrained_timing: Flag = False
    """sim: play a station timing outside the range the policy was trained under (the summary says so)."""
    config: str | None = None
    """cell: the cell config (TOML: EGM, gantry Modbus, tracker, launcher; docs/ROBOT.md)."""

    def __post_init__(self):
        super().__post_init__()
        commandline.check_resumable_dir("out", self.out)     # a file there, or under one
        if self.policy is None and self.station != "fake":
            raise ValueError(f"--station {self.station} needs --policy DIR (an export; only --station fake "
                             f"runs without one)")
        if self.config is not None and self.station != "cell":
            raise ValueError(f"--config {self.config!r} configures the cell station; --station is {self.station!r} "
                             "(drop --config, or use --station cell)")
        sim_only = [flag for flag, given in (("--timing", self.timing is not None),
                                             ("--allow-untrained-timing", self.allow_untrained_timing),
                                             ("--charge-compute", self.charge_compute)) if given]
        if sim_only and self.station != "sim":
            raise ValueError(f"{sim_only[0]} sets the simulated station's timing; --station is {self.station!r} "
                             "(drop it, or use --station sim)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotBenchArgs(Report):
    """Step latency of the numpy or ONNX policy on one CPU core (the robot side's budget; docs/BENCHMARKS.md)."""
    BOUNDS: ClassVar[dict] = {"hidden": (1, 8192), "layers": (1, 16), "members": (1, 64), "steps": (1, 10**6),
                              "threads": (1, 1024), "frame_stack": (1, 64)}
    engine: Literal["numpy", "onnx"] = "numpy"
    """numpy (deploy/robot/numpy_policy.py) or the ONNX graph on onnxruntime
    (deploy/robot/onnx_policy.py; the `onnx` or `robot` extra)."""
    kind: Literal["lstm", "framestack"] = "lstm"
    """Policy type."""
    obs_size: Literal[13, 16] = 13
    """Values per frame: 13 (the robot's) or 16 (with the ball velocity, the paper-sim presets)."""
    frame_stack: int = 8
    """Frames of the frame-stack MLP's input."""
    hidden: int = 1024
    """Units per layer."""
    layers: int = 2
    """LSTM cells or MLP hidden layers."""
    members: int = 1
    """Ensemble members."""
    steps: int = 2000
    """Timed policy steps."""
    threads: int = 1
    """BLAS threads (numpy) or onnxruntime intra-op threads."""


# --------------------------------------------------------------------------------------------
# Sessions
# --------------------------------------------------------------------------------------------
def run_fake(goals, out, policy_dir, config, realtime) -> dict:
    """Play one episode per goal on the fake robot and tracker: the export in policy_dir, or
    without one a ball-following policy (DRY_RUN_HZ, DRY_RUN_FRAMES): a dry run of the runner,
    its modes and logs, with no export and no simulator."""
    from deploy.robot.fakes import FakeClock, FakeRobot, FakeTracker, FollowBallPolicy
    if policy_dir:
        from deploy.robot.exported import load_export
        policy, contract = load_export(policy_dir)
    else:
        contract = dataclasses.replace(Contract(), control_hz=DRY_RUN_HZ, frame_stack=DRY_RUN_FRAMES)
        policy = FollowBallPolicy(contract)
    clock = MonotonicClock() if realtime else FakeClock(start=0.0)
    robot, tracker = FakeRobot(clock, contract), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, policy, contract, config)
    return run_session(runner, goals, out, StationHooks(armed=lambda i: tracker.throw_in(0.3)))


def run_cell_station(policy_dir, goals, config_path, out, config) -> dict:
    """--station cell: the export played on the cell of config_path (deploy/robot/drivers/cell.py)."""
    if not policy_dir:
        raise ValueError("--station cell needs --policy DIR (an export)")
    if not config_path:
        raise ValueError("--station cell needs --config FILE (a cell config, deploy/robot/drivers/cell.example.toml)")
    try:
        from deploy.robot.drivers.cell import run_cell
    except ImportError as e:
        raise ValueError(f"--station cell needs the robot extra (pip install -e '.[robot]'): {e}") from None
    return run_cell(policy_dir, goals, config_path, out, runner_config=config)


def export_hash(policy_dir: str | None) -> str | None:
    """sha256 of an export's manifest.json (which hashes every other file), or None."""
    path = os.path.join(policy_dir, "manifest.json") if policy_dir else None
    return sha256_file(path) if path and os.path.isfile(path) else None


def play(station: str, policy: str | None, goals, out: str | None, config: RunnerConfig, *, seed: int = 0,
         distribution: str | None = None, timing: str | None = None, allow_untrained: bool = False,
         realtime: bool = False, charge_compute: bool = False, cell_config: str | None = None,
         sim_station: Callable[..., dict] | None = None, log=None) -> dict:
    """One session on `station` with its episode logs in `out` (deploy.robot.episode_log.session): a new
    directory, or the same command's unfinished session, resumed (its logged episodes replayed
    and checked, the rest logged), or its finished one (its summary read back). A directory that
    holds anything else is refused, naming what it holds."""
    plan = {"station": station, "export": export_hash(policy), "goals": np.asarray(goals).tolist(), "seed": seed,
            "distribution": distribution, "timing": timing, "allow_untrained_timing": allow_untrained,
            "stale_s": config.stale_s, "realtime": realtime, "charge_compute": charge_compute,
            **({"rate": DRY_RUN_HZ, "frame_stack": DRY_RUN_FRAMES} if station == "fake" and not policy else {})}
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
            return sim_station(policy, goals, out, seed=seed, distribution=distribution, realtime=realtime,
                               charge_compute=charge_compute, config=config, timing=timing,
                               allow_untrained=allow_untrained)
        return run_fake(goals, out, policy, config, realtime)


def robot_run(a: RobotRunArgs, sim_station: Callable[..., dict] | None = None) -> None:
    """`ttmjx robot run`; sim_station plays --station sim (deploy.sim.station.run_sim, handed in
    by the simulator side's command line: this side never imports it)."""
    if a.station == "sim" and sim_station is None:
        raise ValueError("--station sim needs the simulator side (MuJoCo, JAX): pip install 'ttmjx[sim]'")
    goals = session_goals(a.goals, a.n, a.seed)
    config = RunnerConfig(stale_s=a.stale_ms / 1000.0)
    if a.station == "cell":
        trained = trained_timing(read_contract(a.policy), a.policy)["timing"]   # none: refused
        from deploy.robot.drivers.config import sample_ages       # no driver packages needed
        ages, why = sample_ages(trained)
        error = stale_bound_error(config.stale_s, ages, "the cell's", why)
        if error:
            raise ValueError(error)
    # --out: a new directory, or this command's own session: resumed if unfinished (play)
    out = play(a.station, a.policy, goals, a.out, config, seed=a.seed, distribution=a.distribution,
               timing=a.timing, allow_untrained=a.allow_untrained_timing, realtime=a.realtime,
               charge_compute=a.charge_compute, cell_config=a.config, sim_station=sim_station,
               log=lambda m: print(f"ttmjx robot run: {m}", file=sys.stderr))
    m = out.get("metrics", {})
    tm = out.get("timing") or {}
    report(a, out, f"{out['episodes']}/{out['goals']} episodes; " +
           (f"within 30 cm {m.get('within_30cm', 0):.1%}, 20 cm {m.get('within_20cm', 0):.1%}, "
            f"hit rate {m.get('hit_rate', 0):.0%}; " if m else "") +
           (f"timing {tm['source']}{' (inside the trained range)' if tm['within_trained'] else ''}; "
            if tm else "") +
           f"faults {out['faults']}; " + gantry_link_line(out.get("gantry")) +
           (f"logs in {out['out']}" if out["out"] else "no episode logs (--out DIR keeps them)") +
           (f"\n{timing_line(tm)}" if tm and not tm["within_trained"] else ""))
    if out["episodes"] != out["goals"]:
        sys.exit(1)


def gantry_link_line(gantry: dict | None) -> str:
    """'gantry link +X ms over the arm's, targets led Y ms (p50); ' from a cell session's
    summary (`gantry`: drivers/lead.py's reports), '' for other stations."""
    if not gantry or not gantry.get("link"):
        return ""
    link, lead = gantry["link"], gantry.get("lead") or {}
    led = (f"targets led {lead['lead_p50_ms']:.1f} ms (p50)" if lead.get("enabled")
           else "targets not led ([gantry] compensate_latency = false)")
    return f"gantry link +{link['excess_ms']:.1f} ms over the arm's, {led}; "


def robot_bench(a: RobotBenchArgs) -> None:
    out = benchmark(a.kind, a.hidden, a.layers, a.members, steps=a.steps, threads=a.threads,
                    engine=a.engine, obs_size=a.obs_size, frame_stack=a.frame_stack)
    shape = f"[{a.frame_stack}, {a.obs_size}]" if a.kind == "framestack" else f"[{a.obs_size}]"
    text = (f"{a.engine} {a.kind} {a.layers}x{a.hidden} x{a.members}, input {shape}, on {a.threads} thread(s), "
            f"core {out['cpu']}: step p50 {out['p50_ms']:.3f} ms, p99 {out['p99_ms']:.3f} ms, "
            f"max {out['max_ms']:.3f} ms")
    if "prepared_p50_ms" in out:
        text += (f"; after prepare(): p50 {out['prepared_p50_ms']:.3f} ms, p99 "
                 f"{out['prepared_p99_ms']:.3f} ms (prepare p50 {out['prepare_p50_ms']:.3f} ms)")
    report(a, out, text)


# --------------------------------------------------------------------------------------------
# The commands
# --------------------------------------------------------------------------------------------
COMMANDS: dict[str, Command] = {
    "robot run": Command(RobotRunArgs, robot_run, "the robot runner: play an exported policy on a station"),
    "robot bench": Command(RobotBenchArgs, robot_bench, "numpy or ONNX policy step latency on one CPU core",
                           resumes=False),
}


def main(argv: list[str] | None = None) -> None:
    """`ttmjx robot run|bench` on the robot side alone (--station sim needs the simulator side)."""
    commandline.run(COMMANDS, sys.argv[1:] if argv is None else list(argv))
