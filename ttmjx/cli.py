"""`ttmjx`: the command line, on top of every package (world -> tools -> models -> training ->
eval -> deploy -> here; nothing imports this module).

Every subcommand is a row of COMMANDS (at the bottom): its arguments (a frozen dataclass whose
fields are its flags; `ttmjx CMD --help` lists each with its type, default and meaning, nested
configuration fields included), the function that runs it and a line of help. Subcommands that
report numbers take --json and then print one JSON object as their last line (non-finite numbers
as null). Bad input exits 2 with one line, `ttmjx CMD: error: ...`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import sys
from typing import Annotated, Any, Callable, ClassVar, Literal, NamedTuple, NoReturn

import tyro

from deploy.cli import STATIONS
from eval.ablate import ABLATION_NAMES, SCALE_NAMES
from training.baselines.config import ESConfig, PPOConfig, RewardConfig, SACConfig
from training.runconfig import PRESET_NAMES, RunConfig, preset
from ttmjx.world.config import CONTROL_RATES, THROW_DISTRIBUTIONS, World
from ttmjx.world.files import json_safe

Flag = Annotated[bool, tyro.conf.FlagCreatePairsOff]   # a bare --flag, off by default
Backend = Literal["c", "mjx"]


RunPath = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_OR_CHECKPOINT")]
DatasetPath = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]


# --------------------------------------------------------------------------------------------
# Arguments: one frozen dataclass per subcommand; field docstrings are the --help lines.
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, kw_only=True)
class Report:
    json: Flag = False
    """Print one JSON object as the last line (non-finite numbers as null)."""

    # {field: (lowest, highest or None)} checked when the arguments are built, before any work.
    BOUNDS: ClassVar[dict] = {}
    # Fields naming a file or directory this command creates: refused up front if it exists as
    # the other kind (a file where a directory goes, or the reverse).
    NEW_DIRS: ClassVar[tuple] = ()
    NEW_FILES: ClassVar[tuple] = ()

    def __post_init__(self):
        if isinstance(getattr(self, "seed", None), int):
            check_range("seed", self.seed, 0, 2 ** 32 - 1)    # seeds outside wrap onto others
        for name, (low, high) in self.BOUNDS.items():
            check_range(name, getattr(self, name), low, high() if callable(high) else high)
        for name in self.NEW_DIRS:
            check_new_path(name, getattr(self, name), want_dir=True)
        for name in self.NEW_FILES:
            check_new_path(name, getattr(self, name), want_dir=False)


def check_range(name: str, value, low, high) -> None:
    """ValueError naming the flag, the value and the expected range (None values are unset)."""
    if value is None:
        return
    flag = "--" + name.replace("_", "-")
    if isinstance(value, float) and value != value:
        raise ValueError(f"{flag} is NaN; expected a number >= {low}")
    if value < low or (high is not None and value > high):
        expected = f">= {low}" if high is None else f"between {low} and {high}"
        raise ValueError(f"{flag} {value}: expected {expected}")


def check_new_path(name: str, path: str | None, want_dir: bool) -> None:
    flag = "--" + name.replace("_", "-")
    if path is None:
        return
    if want_dir and os.path.isfile(path):
        raise ValueError(f"{flag} {path!r} is a file; expected a new directory")
    if want_dir and os.path.isdir(path) and os.listdir(path):
        raise ValueError(f"{flag} {path!r} already holds files; expected a new or empty directory")
    if not want_dir and os.path.isdir(path):
        raise ValueError(f"{flag} {path!r} is a directory; expected a file path")
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK):
        raise ValueError(f"{flag} {path!r}: cannot write under {parent!r} (not a writable directory)")


def batch_limit() -> int:
    """Most episodes one command may simulate at once: half the device memory (training/budget.py)."""
    from training.budget import episodes_that_fit
    return episodes_that_fit(World())


@dataclasses.dataclass(frozen=True, kw_only=True)
class WorldArgs(Report):
    distribution: Literal[THROW_DISTRIBUTIONS] = "narrow"
    """Throw distribution (ttmjx/world/config.py Throws)."""
    spin: Flag = False
    """Throws with spin (off by default, as in the paper)."""
    control_hz: Literal[CONTROL_RATES] | None = None
    """Policy steps per second; None: the World's (100)."""

    def world(self) -> World:
        cfg = World() if self.control_hz is None else World(control_hz=self.control_hz)
        return cfg.with_throws(self.distribution, spin=self.spin)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ThrowArgs(WorldArgs):
    """Sample throws and simulate their first bounce; reports launch, aim and bounce of each."""
    BOUNDS: ClassVar[dict] = {"n": (1, batch_limit)}
    n: int = 10
    """Number of throws."""
    seed: int = 0
    """Seed of the throw sampler."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class BenchArgs(WorldArgs):
    """Physics throughput of a backend against the raw mujoco.rollout baseline; with --train
    PRESET, where a training round's time goes (docs/BENCHMARKS.md)."""
    BOUNDS: ClassVar[dict] = {"batch": (1, batch_limit), "threads": (1, 1024), "seeds": (1, 1000), "reps": (1, 100)}
    train: Literal[PRESET_NAMES] | None = None
    """Time a training round of this preset instead (rollout, relabel + insert, updates, the whole round,
    evaluation; rates, compile time, peak memory, the run's projected time); physics from the preset's
    backend (auto: MJX on an accelerator)."""
    seeds: int = 1
    """With --train: seeds trained together in one program (ttmjx train --seeds)."""
    reps: int = 2
    """With --train: timed calls per piece after the first (which compiles)."""
    backend: Backend = "c"
    """Physics backend: MuJoCo C (mujoco.rollout) or MJX."""
    batch: int = 1024
    """Episodes simulated together."""
    threads: int | None = None
    """C backend threads; None: all cores."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RenderArgs(WorldArgs):
    """Write a short video (GIF) of a few throws, headless (EGL, then OSMesa)."""
    BOUNDS: ClassVar[dict] = {"n": (1, 20)}
    NEW_FILES: ClassVar[tuple] = ("out",)
    n: int = 3
    """Number of throws."""
    seed: int = 0
    """Seed of the throw sampler."""
    source: Literal["scripted", "hold"] = "scripted"
    """Who plays: the scripted striker or a robot holding its home pose."""
    out: str = "throws.gif"
    """GIF path."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SimArgs(WorldArgs):
    """A short simulation run: the scripted striker plays N throws; prints what it did."""
    BOUNDS: ClassVar[dict] = {"n": (1, batch_limit)}
    backend: Backend = "c"
    """Physics backend: MuJoCo C (mujoco.rollout) or MJX."""
    n: int = 64
    """Number of throws."""
    seed: int = 0
    """Seed of the throw sampler."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class DemosArgs(WorldArgs):
    """Collect bootstrap demonstrations into a new dataset directory with its landing-coverage
    figure DIR/coverage.png (docs/DATA.md); for `paper`, the narrow ES policy's landings beside
    the dataset's (the paper's figure)."""
    BOUNDS: ClassVar[dict] = {"n": (1, batch_limit)}
    NEW_DIRS: ClassVar[tuple] = ("out",)
    source: Literal["paper", "striker", "es", "oracle", "scripted"] = "paper"
    """Demonstrator: paper (the paper's bootstrap procedure: ES until it returns balls, its
    rollouts with 4 joints perturbed, imitation and practice with goals shifted up the table, then
    over the whole half; a gather with the shipped weights), striker (a narrow scripted striker
    aimed at one point, 4 joints perturbed: `paper` in datasets without a source_version), es (the ES policy, same
    perturbation), oracle (the goal-directed striker: an UPPER BOUND, not the paper's setting;
    'scripted' is its old name)."""
    n: int = 1000
    """Number of episodes (the paper's bootstrap: 3600)."""
    seed: int = 0
    """Seed of the throws (and the demonstrator's noise; with --rebuild, of the procedure)."""
    out: str
    """New dataset directory (never overwritten)."""
    backend: Backend = "c"
    """Physics backend: MuJoCo C (mujoco.rollout) or MJX."""
    rebuild: Literal["none", "stages", "all"] = "none"
    """With --source paper: none (gather with the shipped weights, seconds), stages (the shift and
    expand stages again from the shipped ES weights, ~10 min on 2 CPU cores), all (the whole
    procedure from scratch, ES included, ~45 min); everything it builds goes to OUT/bootstrap/."""
    es_generations: tuple[int, int] = (134, 330)
    """With --rebuild all: ES generations of the contact and the return phase (48 candidates x 8
    throws each)."""

    def __post_init__(self):
        super().__post_init__()
        if self.rebuild != "none" and self.source != "paper":
            raise ValueError(f"--rebuild {self.rebuild} builds the paper procedure; --source is {self.source!r}")
        if self.rebuild != "none" and self.backend != "c":
            raise ValueError("--rebuild runs ES and the stages on the MuJoCo C backend (--backend c)")
        if self.rebuild == "stages":
            from ttmjx.tools import es
            trained = es.read_meta().get("distribution")
            if trained != self.distribution:
                raise ValueError(f"--rebuild stages starts from the shipped ES policy, trained on {trained} throws, "
                                 f"not {self.distribution}: use --rebuild all")
        if self.rebuild != "none":
            from training.bootstrap_paper import Procedure
            Procedure(final=self.n, seed=self.seed, es_generations=self.es_generations).check(self.rebuild == "all")


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlotArgs(Report):
    """Draw a dataset's landing points over the table (PNG)."""
    NEW_FILES: ClassVar[tuple] = ("out",)
    dir: DatasetPath
    """Dataset directory (ttmjx demos --out)."""
    out: str | None = None
    """PNG path; None: DIR/landings.png."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainArgs(Report):
    """GoalsEye training: demonstrations, GCBC, self-practice, evaluation, checkpoints, curves.

    --preset P picks the defaults (default, lfp, gcsl, paper-sim, paper-sim-new, tiny, cpu, gpu);
    `ttmjx train --preset P --help` shows P's. Every field below overrides it, e.g.
    `ttmjx train --preset paper-sim --seed 1 --train.members 4`. A non-zero --seed without
    --run-dir runs in the preset's run directory + '-seedN'. The same command resumes a run.
    """
    BOUNDS: ClassVar[dict] = {"max_iterations": (1, None), "seeds": (1, 1000)}
    config: Annotated[RunConfig, tyro.conf.arg(name="")]
    max_iterations: int | None = None
    """Stop (with a checkpoint) after this many iterations; the same command resumes later."""
    seeds: int = 1
    """Train seeds --seed .. --seed + N - 1 together in one program (training/seeds.py), each in
    RUN_DIR/seed<s>; 1: one run in RUN_DIR."""

    def __post_init__(self):
        super().__post_init__()
        self.config.check_meaningful()


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalArgs(Report):
    """Goal-reaching metrics of a run's checkpoint (its moving-average policy)."""
    BOUNDS: ClassVar[dict] = {"per_goal": (1, batch_limit), "member": (0, None), "step": (0, None),
                              "seed_index": (0, None)}
    NEW_DIRS: ClassVar[tuple] = ("out",)
    run: RunPath
    """Run directory (or its checkpoints/ directory)."""
    distribution: Literal[THROW_DISTRIBUTIONS] | None = None
    """Throws; None: the run's."""
    goals: str = "200"
    """Number of uniform goals over the opponent's half, 'five' for goals A-E, or a goal file (.csv
    with a header row x,y, or .npy [N, 2]; goals on the opponent's half; one attempt each)."""
    out: str | None = None
    """New or empty directory for summary.json, episodes.csv and tracks.npz (docs/DATA.md)."""
    per_goal: int = 40
    """Attempts per goal with --goals five."""
    backend: Backend | None = None
    """Physics backend; None: the run's."""
    seed: int = 1234
    """Seed of the throws and uniform goals."""
    member: int | None = None
    """Evaluate one ensemble member alone; None: the whole ensemble."""
    step: int | None = None
    """Checkpoint step; None: the newest intact one."""
    seed_index: int | None = None
    """A batch of seeds (ttmjx train --seeds N): evaluate seed K alone; None: every seed, with the mean and spread."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class AblateArgs(Report):
    """One of the paper's simulated ablations: every (variant, seed) cell a training run, then a
    markdown table (mean +- 95% interval over seeds), learning curves and landing maps
    (eval/ablate.py ABLATIONS lists the variants). The same command resumes: finished cells are
    skipped, a half-finished one resumes from its checkpoint."""
    BOUNDS: ClassVar[dict] = {"seeds": (1, 1000), "trajectories": (1, None)}
    name: Annotated[Literal[ABLATION_NAMES], tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """The ablation: demos, noise, ensembles, inputs, bootstrap or practice."""
    scale: Literal["auto", *SCALE_NAMES] = "auto"
    """tiny (tests), cpu (2 CPU cores) or full (paper-sim-like, one GPU per cell); auto: full on an accelerator."""
    seeds: int = 5
    """Seeds per variant (0..N-1)."""
    cells: str | None = None
    """Run only these cells: indices (3), ranges (0:3, 4:) or variant names, comma-separated; --plan lists them."""
    trajectories: int | None = None
    """Total trajectories per cell; None: the scale's."""
    out: str | None = None
    """Ablation directory; None: ablations/NAME-SCALE."""
    report: Flag = False
    """Only (re)build the table, curves, landing maps and summary from the finished cells."""
    plan: Flag = False
    """List the cells (index, name, finished / partial / to do) and exit."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class BaselineArgs(Report):
    """The paper's Table I on this world: RL baselines through brax (ppo, sac, es), GCSL, LFP and
    GoalsEye at one trajectory budget, each (method, seed) a cell as in `ttmjx ablate`: a markdown
    table (mean +- 95% interval over seeds), learning curves, landing maps, JSON per cell. The same
    command skips finished cells (an RL cell cut short is redone; GoalsEye cells resume)."""
    BOUNDS: ClassVar[dict] = {"seeds": (1, 1000), "trajectories": (1, None)}
    method: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="METHOD")]
    """ppo, sac, es, gcsl, lfp or goalseye; several comma-separated, or all."""
    trajectories: int | None = None
    """Trajectories per cell; None: the scale's (full: 120,000, the paper's)."""
    seeds: int = 5
    """Seeds per method: --seed..--seed+N-1."""
    seed: int = 0
    """The first seed (so that several machines or calls each run some seeds of one table)."""
    scale: Literal["tiny", "full"] = "full"
    """tiny (CPU tests: 2 environments, tiny batches) or full (one GPU per cell)."""
    out: str | None = None
    """Table directory; None: baselines/SCALE."""
    reward: RewardConfig = RewardConfig()
    """The RL reward's weights (training/baselines/config.py)."""
    ppo: PPOConfig = PPOConfig()
    """brax PPO's settings at --scale full (training/baselines/config.py); e.g. --ppo.num-envs."""
    sac: SACConfig = SACConfig()
    """brax SAC's settings at --scale full."""
    es: ESConfig = ESConfig()
    """brax ES's settings at --scale full."""
    report: Flag = False
    """Only (re)build the table, curves, landing maps and summary from the finished cells."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ExportArgs(Report):
    """Safetensors weights + contract + golden self-test (+ ONNX graph) of a checkpoint, for the
    robot runner, under a manifest of SHA-256 hashes (docs/DATA.md)."""
    BOUNDS: ClassVar[dict] = {"step": (0, None), "member": (0, None), "seed_index": (0, None)}
    NEW_DIRS: ClassVar[tuple] = ("out",)
    checkpoint: RunPath
    """A run directory holding checkpoints/, or a checkpoint directory."""
    seed_index: int | None = None
    """A batch of seeds (ttmjx train --seeds N): export seed K (required for a batch)."""
    out: str
    """Export directory (must not hold an export)."""
    step: int | None = None
    """Checkpoint step; None: the newest."""
    ensemble: Flag = False
    """All members; their actions are averaged (not with --member). Without --member this is what
    is exported: the whole ensemble, the policy `ttmjx eval` scores."""
    member: int | None = None
    """One member of an ensemble (not with --ensemble)."""
    control_hz: Literal[CONTROL_RATES] | None = None
    """The robot's control rate; None: the rate the policy was trained at."""
    onnx: Literal["auto", "on", "off"] = "auto"
    """policy.onnx (one policy step as an ONNX graph): auto = when the optional `onnx` package is installed."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotRunArgs(Report):
    """Play an exported policy toward goals on a station and log the episodes."""
    BOUNDS: ClassVar[dict] = {"n": (1, 100_000), "stale_ms": (0.1, 10_000.0)}
    policy: str
    """An export directory (ttmjx export --out)."""
    station: Literal[STATIONS]
    """sim: MuJoCo C physics and the thrower; fake: simple kinematics; cell: the drivers (--config)."""
    goals: str
    """'x,y;x,y', a goal file (.json/.npy/.csv/.txt), 'five' (goals A-E) or 'uniform'."""
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
class RobotSweepArgs(Report):
    """Strict success of an exported policy on the simulated station against added latency of the
    ball tracker, of the commands, added jitter, and all three together (the export verified and
    its policy built once for every point): a table, sweep.json and sweep.png."""
    BOUNDS: ClassVar[dict] = {"n": (1, 100_000), "max_ms": (0.0, 1000.0), "points": (2, 50),
                              "max_jitter_ms": (0.0, 1000.0)}
    policy: str
    """An export directory (ttmjx export --out)."""
    out: str
    """Directory for sweep.json and sweep.png: new, empty, or this sweep's own (an interrupted sweep
    goes on: the points it measured are kept, the rest measured)."""
    n: int = 100
    """Uniform goals per point (the same goals and throws at every point)."""
    max_ms: float = 150.0
    """Largest added latency (ms)."""
    points: int = 6
    """Latencies from 0 to max_ms, evenly spaced."""
    max_jitter_ms: float = 20.0
    """Largest added per-sample jitter (ms) of the jitter series (and of 'all')."""
    series: str = "ball,action,jitter,all"
    """Series to sweep, comma-separated: ball (tracker latency), action (command delay), jitter, all (together)."""
    seed: int = 0
    """Seed of the goals and throws."""
    timing: str | None = None
    """The station's timing the latency is added to; None: the timing the policy was trained under
    (its centre); or a profile (nominal, zero)."""

    def __post_init__(self):
        super().__post_init__()
        if not os.path.isdir(self.out):
            check_new_path("out", self.out, want_dir=True)     # a file there, or an unwritable parent
        else:
            other = sorted(n for n in os.listdir(self.out) if n not in ("sweep.json", "sweep.png") and not n.startswith("."))
            if other:
                raise ValueError(f"--out {self.out!r} holds {', '.join(other[:4])}{', ...' if len(other) > 4 else ''}, "
                                 f"not a sweep's sweep.json and sweep.png; choose a new or empty directory")


@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotServeArgs(Report):
    """Serve the simulated station over the cell's protocols (EGM, Modbus TCP, tracker UDP,
    launcher) in real time, for `ttmjx robot run --station cell` (docs/ROBOT.md)."""
    BOUNDS: ClassVar[dict] = {"egm_hz": (1.0, 1000.0), "duration_s": (0.0, None)}
    config: str
    """The cell config (TOML) the runner uses: where to send and listen."""
    policy: str | None = None
    """An export: its training world and control rate; None: the default World at --control-hz."""
    control_hz: Literal[CONTROL_RATES] | None = None
    """Without --policy: the runner's control rate (the station ramps each target over one period)."""
    seed: int = 0
    """Seed of the throws (as `robot run --station sim --seed`)."""
    distribution: Literal[THROW_DISTRIBUTIONS] | None = None
    """Throws; None: the export's training world."""
    timing: str | None = None
    """Sensor and actuation timing of the station; None: with --policy the timing the policy was
    trained under (the export's contract, drawn per throw within its ranges), without it nominal;
    centre (the trained timing, fixed); or a profile (nominal, zero)."""
    allow_untrained_timing: Flag = False
    """Serve a station timing outside the range the policy was trained under (the summary says so)."""
    faults: str = ""
    """Injected faults, e.g. 'egm.loss=0.05,modbus.delay_ms=10' (deploy/serve.py FAULT_KINDS)."""
    egm_hz: float = 250.0
    """EGM cycle rate of the simulated controller."""
    duration_s: float | None = None
    """Stop after this many seconds; None: until interrupted."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RobotBenchArgs(Report):
    """Step latency of the numpy or ONNX policy on one CPU core (the robot side's budget; docs/BENCHMARKS.md)."""
    BOUNDS: ClassVar[dict] = {"hidden": (1, 8192), "layers": (1, 16), "members": (1, 64), "steps": (1, 10**6),
                              "threads": (1, 1024), "frame_stack": (1, 64)}
    engine: Literal["numpy", "onnx"] = "numpy"
    """numpy (deploy/numpy_policy.py) or the ONNX graph on onnxruntime (deploy/onnx_policy.py; the `onnx` extra)."""
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
# Commands
# --------------------------------------------------------------------------------------------
def report(args: Report, obj: dict, text: str) -> None:
    """Print `text`, or with --json `obj` as one line of valid JSON (non-finite -> null)."""
    print(json.dumps(json_safe(obj), allow_nan=False) if args.json else text)


def table(obj: dict, skip: tuple = ()) -> str:
    """key  value lines (floats to 4 significant digits)."""
    width = max((len(k) for k in obj), default=0)
    return "\n".join(f"{k:{width}s}  {v:.4g}" if isinstance(v, float) else f"{k:{width}s}  {v}"
                     for k, v in obj.items() if k not in skip)


def throw(a: ThrowArgs) -> None:
    from ttmjx.world import thrower
    rep = thrower.throw_report(a.world(), a.n, a.seed)
    errs = [((t["aim"][0] - t["bounce"][0]) ** 2 + (t["aim"][1] - t["bounce"][1]) ** 2) ** 0.5
            for t in rep["throws"]]
    report(a, rep, f"{a.n} {a.distribution} throws; bounce error vs aim: max "
                   f"{100 * max(errs):.2f} cm, mean {100 * sum(errs) / len(errs):.2f} cm")


def bench(a: BenchArgs) -> None:
    if a.train is not None:
        from eval.bench_train import bench_training
        out = bench_training(a.train, a.seeds, a.reps, log=lambda m: print(m, file=sys.stderr))
        report(a, out, table({k: v for k, v in out.items() if k != "schedule"}) + f"\nschedule  {out['schedule']}")
        return
    from ttmjx.tools import bench as physics_bench
    out = physics_bench.bench(a.world(), a.backend, a.batch, a.threads)
    report(a, out, table(out))


def render(a: RenderArgs) -> None:
    from ttmjx.tools import render as video
    path = video.render_throws(a.world(), a.out, a.n, a.seed, source=a.source)
    report(a, {"video": path}, f"wrote {path}")


def sim(a: SimArgs) -> None:
    from ttmjx.tools import simrun
    out = simrun.run(a.world(), a.backend, a.n, a.seed)
    report(a, out, table(out))


def demos(a: DemosArgs) -> None:
    from ttmjx.tools import demos as demonstrations
    params_dir = es_dir = None
    if a.rebuild != "none":
        from training import bootstrap_paper
        built = os.path.join(a.out, "bootstrap")
        bootstrap_paper.build(built, bootstrap_paper.default_world().with_throws(a.distribution, spin=a.spin),
                              bootstrap_paper.Procedure(final=a.n, seed=a.seed, es_generations=a.es_generations),
                              rebuild_es=a.rebuild == "all",
                              progress=not a.json, log=(lambda m: print(m, file=sys.stderr)))
        params_dir, es_dir = built, (built if a.rebuild == "all" else None)
    fresh = not os.path.exists(a.out) or not os.listdir(a.out)
    try:
        out = demonstrations.make_dataset(a.world(), a.source, a.n, a.seed, a.out, a.backend,
                                          progress=not a.json, params_dir=params_dir, es_dir=es_dir)
    except BaseException:
        # Whole or absent: a dataset cut short (a full disk, a signal) leaves no partial files
        # (a temporary .npz, a dataset without its figure), so the same command runs again. What
        # --rebuild built (OUT/bootstrap/) stays.
        if fresh and os.path.isdir(a.out):
            import shutil
            for name in os.listdir(a.out):
                if name != "bootstrap":
                    p = os.path.join(a.out, name)
                    shutil.rmtree(p) if os.path.isdir(p) else os.remove(p)
            if not os.listdir(a.out):
                os.rmdir(a.out)
        raise
    report(a, out, f"{table(out)}\nwrote {a.out} (and {os.path.join(a.out, 'coverage.png')})")


def plot_landings(a: PlotArgs) -> None:
    from ttmjx.tools import demos as demonstrations
    path = demonstrations.plot_landings(a.dir, a.out)
    report(a, {"plot": path}, f"wrote {path}")


def given(argv: list[str], *flags: str) -> bool:
    """Whether any of `flags` ('--a-b', also spelled --a_b or --a-b=V) is on the command line."""
    return any(arg.split("=")[0].replace("_", "-") in flags for arg in argv)


def parse_train(argv: list[str]) -> TrainArgs:
    """--preset P picks the defaults tyro shows and overrides (`--preset` is RunConfig.preset)."""
    name = "default"
    for i, arg in enumerate(argv):
        if arg.startswith("--preset="):
            name = arg.split("=", 1)[1]
        elif arg == "--preset" and i + 1 < len(argv):
            name = argv[i + 1]
    if name not in PRESET_NAMES:
        raise ValueError(f"--preset {name!r}: expected one of {', '.join(PRESET_NAMES)}")
    base = preset(name)
    if given(argv, "--world.control-hz", "--world.max-physics-dt") and not given(argv, "--world.physics-dt"):
        argv = ["--world.physics-dt", "None", *argv]   # derived again from the new rate
    a = parse_args("train", TrainArgs, argv, default=TrainArgs(config=base))
    if a.config.world.timing.ideal_timing:
        ignored = [arg.split("=")[0] for arg in argv if arg.startswith("--world.timing.")
                   and arg.split("=")[0].replace("_", "-") not in ("--world.timing.ideal-timing",
                                                                   "--world.timing.no-ideal-timing",
                                                                   "--world.timing.extrapolate-s")]
        if ignored:
            raise ValueError(f"{ignored[0]} would be ignored: this run's timing is ideal (--world.timing.ideal-timing, "
                             f"preset {name}), which resets every delay and rate; add --world.timing.no-ideal-timing "
                             f"to use it")
    if a.config.seed != 0 and not given(argv, "--run-dir"):
        a = dataclasses.replace(a, config=dataclasses.replace(
            a.config, run_dir=f"{base.run_dir}-seed{a.config.seed}"))
    return a


def train(a: TrainArgs) -> None:
    from eval.evaluate import training_evaluation
    from training.pool import check_sources
    from training.trainer import Run
    cfg = a.config
    check_sources(cfg)
    if a.seeds > 1:
        from eval.evaluate import training_evaluation_seeds
        from training.seeds import SeedRuns, seed_configs
        out = SeedRuns(seed_configs(cfg, a.seeds), training_evaluation_seeds(cfg), progress=not a.json,
                       parent=cfg.run_dir).run(max_iterations=a.max_iterations)
        lines = [f"seed {r['seed']}: " + table({k: v for k, v in r.items() if k.startswith("eval_")})
                 .replace("\n", ", ") for r in out["runs"]]
        report(a, out, table({k: v for k, v in out.items() if k != "runs"}) + "\n" + "\n".join(lines))
    else:
        out = Run(cfg, evaluate=training_evaluation(cfg), progress=not a.json).run(max_iterations=a.max_iterations)
        report(a, out, table(out))
    if out["stopped_by_signal"]:
        sys.exit(128 + out["stopped_by_signal"])   # the shell's convention for a signalled exit


def evaluate(a: EvalArgs) -> None:
    from eval.evaluate import evaluate_checkpoint
    from training.seeds import pick_seed, seed_run_dirs, seed_spread
    dirs = seed_run_dirs(a.run)
    if dirs is not None and a.seed_index is None:   # a batch of seeds: each one, then the spread
        if a.out:
            raise ValueError(f"--out with {a.run} (a batch of {len(dirs)} seeds): choose one with --seed-index")
        runs = [{"run_dir": d, **{f"eval_{k}": v for k, v in evaluate_checkpoint(
                    d, a.goals, a.per_goal, a.distribution, a.backend, a.seed, a.member, a.step).items()
                    if isinstance(v, (int, float))}} for d in dirs]
        out = {"run": a.run, "seeds": len(dirs), **seed_spread(runs), "runs": runs}
        lines = [f"{os.path.basename(r['run_dir'])}: <=30cm {r['eval_within_30cm']:.1%} <=20cm "
                 f"{r['eval_within_20cm']:.1%} hit {r['eval_hit_rate']:.1%}" for r in runs]
        report(a, out, "\n".join(lines) + "\n" + table({k: v for k, v in out.items() if k.endswith(("_mean", "_std"))}))
        return
    out = evaluate_checkpoint(pick_seed(a.run, a.seed_index), a.goals, a.per_goal, a.distribution, a.backend,
                              a.seed, a.member, a.step, out=a.out)
    text = table(out, skip=("per_goal",))
    for g, m in out.get("per_goal", {}).items():
        text += (f"\ngoal {g}: <=30cm {m['within_30cm']:.0%} <=20cm {m['within_20cm']:.0%} "
                 f"hit {m['hit_rate']:.0%} on table {m['on_table_rate']:.0%}")
    if a.out:
        text += f"\nwrote {a.out}/summary.json, episodes.csv, tracks.npz"
    report(a, out, text)


def ablate(a: AblateArgs) -> None:
    from eval import ablate as ablations
    scale = ablations.resolve_scale(a.scale)
    out = a.out or ablations.default_out(a.name, scale)
    if a.plan:
        ablations.plan(a.name, scale, a.seeds, out, a.cells, a.trajectories)   # refuses what would fail
        print("\n".join(ablations.status(out, a.name, a.seeds)))
        return
    command = " ".join(["ttmjx ablate", a.name, "--scale", scale, "--seeds", str(a.seeds)]
                       + (["--cells", a.cells] if a.cells else [])
                       + (["--trajectories", str(a.trajectories)] if a.trajectories else [])
                       + (["--out", a.out] if a.out else []))
    if a.report:
        summary = ablations.build_report(a.name, scale, out, command)
    else:
        summary = ablations.run(a.name, scale, a.seeds, out, a.cells, a.trajectories, progress=not a.json,
                                command=command)
    table_report(a, "ablate", summary, out)


def table_report(a: Report, name: str, summary: dict, out: str) -> None:
    """The table (if any cell has finished) or its JSON; after a signal that cut a cell short
    (its run saved a checkpoint first), one line naming the unfinished runs and exit 128 + signal."""
    path = summary.get("outputs", {}).get("table")
    if path:
        with open(path) as f:
            report(a, summary, f.read() + f"\nwrote {out}/ (table.md, curves.png, landings/, summary.json)")
    elif a.json:
        report(a, summary, "")
    sig = summary.get("stopped_by_signal")
    if sig:
        import signal
        runs = summary.get("unfinished", [])
        saved = [r for r in runs if os.path.isdir(os.path.join(r, "checkpoints"))]
        fail(name, f"stopped by {signal.Signals(sig).name}: {len(runs)} cell(s) unfinished; checkpoint saved in "
                   f"{', '.join(saved) or 'none yet'}; run the same command to resume", code=128 + sig)


def baseline(a: BaselineArgs) -> None:
    from eval import baselines
    methods = baselines.parse_methods(a.method)
    out = a.out or os.path.join("baselines", a.scale)
    command = " ".join(["ttmjx baseline", a.method, "--scale", a.scale, "--seeds", str(a.seeds)]
                       + (["--seed", str(a.seed)] if a.seed else [])
                       + (["--trajectories", str(a.trajectories)] if a.trajectories else [])
                       + (["--out", a.out] if a.out else []))
    if a.report:
        summary = baselines.build_report(a.scale, out, command)
    else:
        rl = {name: c for name, c in (("ppo", a.ppo), ("sac", a.sac), ("es", a.es)) if c != type(c)()}
        summary = baselines.run(methods, a.scale, a.seeds, out, a.trajectories, a.reward, progress=not a.json,
                                command=command, rl=rl, first_seed=a.seed)
    table_report(a, "baseline", summary, out)


def export(a: ExportArgs) -> None:
    from deploy.export import export_checkpoint, load_export
    from training.seeds import pick_seed
    path = export_checkpoint(pick_seed(a.checkpoint, a.seed_index), a.out, step=a.step, member=a.member,
                             ensemble=a.ensemble or a.member is None,
                             control_hz=a.control_hz, onnx={"auto": None, "on": True, "off": False}[a.onnx])
    policy, contract = load_export(path)       # the export must pass its own checks
    doc = policy.contract_doc
    spec, source, graph = policy.spec, doc["source"]["checkpoint"], doc.get("onnx")
    out = {"out": path, "source": source, "kind": spec.kind, "hidden": spec.hidden,
           "layers": spec.layers, "members": policy.members, "control_hz": contract.control_hz,
           "policy_hash": policy.policy_hash, "self_test_error": policy.self_test_error,
           "onnx": graph and {k: graph[k] for k in ("file", "sha256", "golden_error", "checked_with")}}
    report(a, out, f"exported {source} -> {path} ({spec.kind} {spec.layers}x{spec.hidden}, "
                   f"{policy.members} member(s), {contract.control_hz:g} Hz); golden self-test "
                   f"max error {policy.self_test_error:.2g}; " +
           (f"{graph['file']}: golden max error {graph['golden_error']:.2g} ({graph['checked_with']})"
            if graph else "no ONNX graph (pip install 'ttmjx[onnx]' for one)"))


def robot_run(a: RobotRunArgs) -> None:
    from deploy.goals import session_goals
    from deploy.runner import RunnerConfig
    from deploy.cli import play
    goals = session_goals(a.goals, a.n, a.seed)
    config = RunnerConfig(stale_s=a.stale_ms / 1000.0)
    if a.station == "cell":
        from deploy.export import read_contract
        from deploy.timing_check import trained_timing
        trained_timing(read_contract(a.policy), a.policy)   # an export without a timing record is refused
    # --out: a new directory, or this command's own session: resumed if unfinished (deploy/cli.py play)
    out = play(a.station, a.policy, goals, a.out, config, seed=a.seed, distribution=a.distribution,
               timing=a.timing, allow_untrained=a.allow_untrained_timing, realtime=a.realtime,
               charge_compute=a.charge_compute, cell_config=a.config,
               log=lambda m: print(f"ttmjx robot run: {m}", file=sys.stderr))
    m = out.get("metrics", {})
    from deploy.timing_check import timing_line
    tm = out.get("timing") or {}
    report(a, out, f"{out['episodes']}/{out['goals']} episodes; " +
           (f"within 30 cm {m.get('within_30cm', 0):.1%}, 20 cm {m.get('within_20cm', 0):.1%}, "
            f"hit rate {m.get('hit_rate', 0):.0%}; " if m else "") +
           (f"timing {tm['source']}{' (inside the trained range)' if tm['within_trained'] else ''}; "
            if tm else "") +
           f"faults {out['faults']}; logs in {out['out']}" +
           (f"\n{timing_line(tm)}" if tm and not tm["within_trained"] else ""))
    if out["episodes"] != out["goals"]:
        sys.exit(1)


def robot_sweep(a: RobotSweepArgs) -> None:
    from deploy.goals import session_goals
    import numpy as np
    from deploy.sweep import latency_sweep, parse_series, sweep_table
    series = parse_series(a.series)
    goals = session_goals("uniform", a.n, a.seed)
    out = latency_sweep(a.policy, goals, a.out, np.linspace(0.0, a.max_ms, a.points), a.seed, a.timing,
                        series=series, jitter_ms=np.linspace(0.0, a.max_jitter_ms, a.points), progress=not a.json)
    report(a, out, sweep_table(out) + f"\nwrote {a.out}/sweep.json and sweep.png")


def robot_serve(a: RobotServeArgs) -> None:
    from deploy.contract import contract_from_world
    from deploy.drivers.config import load_cell_config
    from deploy.serve import check_ports, make_station, parse_faults, serve
    cell = load_cell_config(a.config)
    faults = parse_faults(a.faults)
    check_ports(cell)                  # before the station's slow start
    timing_info = None
    if a.policy is not None:
        from deploy.station import load_for_station, resolve_timing
        loaded = load_for_station(a.policy, a.distribution)   # its timing record is required
        cfg, contract = loaded.cfg, loaded.contract
        timing, timing_info = resolve_timing(loaded, a.timing, a.allow_untrained_timing)
    else:
        from deploy.timing_check import TimingError
        from ttmjx.world.config import TIMING_PROFILES
        name = a.timing or "nominal"
        if name not in TIMING_PROFILES:
            raise TimingError(f"unknown station timing profile {name!r}; expected one of {', '.join(TIMING_PROFILES)}")
        timing = TIMING_PROFILES[name]
        cfg = World() if a.control_hz is None else World(control_hz=a.control_hz)
        contract = contract_from_world(cfg, cfg.control_hz)
        if a.distribution:
            cfg = cfg.with_throws(a.distribution)
    station = make_station(cfg, contract, a.seed, timing)
    if timing_info is not None and not timing_info["within_trained"]:
        from deploy.timing_check import timing_line
        print(f"ttmjx robot serve: warning: {timing_line(timing_info)}", file=sys.stderr, flush=True)
    out = serve(cell, station, faults, egm_hz=a.egm_hz, seed=a.seed, duration_s=a.duration_s)
    if timing_info is not None:
        out["timing"] = timing_info
    report(a, out, table({k: json.dumps(v) for k, v in out.items()}))


def robot_bench(a: RobotBenchArgs) -> None:
    from deploy.policy_bench import benchmark
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


class Command(NamedTuple):
    args: type                                   # frozen dataclass: its fields are the flags
    run: Callable[[Any], None]                   # does the work and prints
    help: str                                    # one line for `ttmjx --help`
    parse: Callable[[list[str]], Any] | None = None   # instead of tyro on `args`' own defaults


COMMANDS: dict[str, Command] = {
    "throw": Command(ThrowArgs, throw, "sample throws and simulate their first bounce"),
    "bench": Command(BenchArgs, bench, "physics throughput of a backend"),
    "render": Command(RenderArgs, render, "write a short video (GIF) of a few throws, headless"),
    "sim": Command(SimArgs, sim, "a short simulation run that prints what it did"),
    "demos": Command(DemosArgs, demos, "collect bootstrap demonstrations into a dataset directory"),
    "plot-landings": Command(PlotArgs, plot_landings, "draw a dataset's landing points over the table (PNG)"),
    "train": Command(TrainArgs, train, "GoalsEye training: demonstrations, GCBC, self-practice, evaluation",
                     parse_train),
    "eval": Command(EvalArgs, evaluate, "goal-reaching metrics of a run or checkpoint"),
    "ablate": Command(AblateArgs, ablate, "a paper ablation: cells of (variant, seed) runs -> table, curves, landing maps"),
    "baseline": Command(BaselineArgs, baseline, "Table I: RL baselines (brax PPO, SAC, ES), GCSL, LFP and GoalsEye -> table, curves"),
    "export": Command(ExportArgs, export, "safetensors weights + contract + golden self-test + ONNX graph for the robot runner"),
    "robot run": Command(RobotRunArgs, robot_run, "the robot runner: play an exported policy on a station"),
    "robot sweep": Command(RobotSweepArgs, robot_sweep, "strict success against added ball and command latency"),
    "robot serve": Command(RobotServeArgs, robot_serve, "serve the simulated station over EGM, Modbus TCP and UDP (rehearsal)"),
    "robot bench": Command(RobotBenchArgs, robot_bench, "numpy or ONNX policy step latency on one CPU core"),
}


# --------------------------------------------------------------------------------------------
# Parsing and errors
# --------------------------------------------------------------------------------------------
FLAG_PREFIX = {"RunConfig": "--", "TrainConfig": "--train.", "PolicyConfig": "--policy.", "Robot": "--world.robot.",
               "Throws": "--world.throws.", "Timing": "--world.timing."}


def fail(name: str, message: str, code: int = 2) -> NoReturn:
    """One line on stderr and exit `code` (2: bad input; 1: the work itself failed)."""
    if name == "train":            # a config's own message names its field: name the flag
        message = re.sub(r"\b(RunConfig|TrainConfig|PolicyConfig|Robot|Throws|Timing)\.(\w+)=?",
                         lambda m: FLAG_PREFIX[m[1]] + m[2].replace("_", "-") + " ", message)
    print(f"ttmjx{' ' + name if name else ''}: error: {' '.join(message.split())}", file=sys.stderr)
    sys.exit(code)


def file_error(e: OSError) -> str:
    """'PATH: cause' of a failed file operation. A write through an open file (numpy's savez, a
    stream) raises without the file's name: it is then the path the project's innermost frame
    was writing (its local `path`, `tmp`, ...), so a full disk always names where."""
    where = e.filename or culprit_path(e.__traceback__)
    return f"{where}: {e.strerror or e}" if where else f"{e.strerror or e}"


PROJECT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def culprit_path(tb) -> str | None:
    frames = []
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):          # innermost first
        code = os.path.abspath(frame.f_code.co_filename)
        if not code.startswith(PROJECT) or os.sep + "site-packages" + os.sep in code:
            continue
        for name in ("path", "tmp", "filename", "file", "out", "out_dir", "directory", "run_dir"):
            value = frame.f_locals.get(name)
            if isinstance(value, str) and value:
                return value
    return None


def one_line(box: str) -> str:
    """tyro's boxed error as one line: the message section, without the title ('Value error'),
    borders, rules, colours or the closing 'For full helptext' hint (rich draws the box in
    unicode on a terminal and in ASCII when the streams are captured)."""
    sections, current = [], []
    for line in re.sub(r"\x1b\[[0-9;]*m", "", box).splitlines():
        line = line.strip()
        if line.startswith(("╭", "╰")):
            continue
        line = line.strip("│|").strip()
        if line and set(line) <= set("─-━═+"):
            sections.append(current)
            current = []
        elif line:
            current.append(line)
    sections.append(current)
    if "╭" not in box:
        sections = sections[1:]          # the ASCII box's title ('Value error') above its first rule
    sections = [s for s in sections if s and not s[0].startswith("For full helptext")]
    text = " ".join(sections[0]) if sections else ""
    # A bound checked by an argument class or a config: tyro prefixes its message with where.
    return re.sub(r"^Error parsing [\w.]+: ", "", text) or box


def parse_args(name: str, cls: type, argv: list[str], default: Any = None) -> Any:
    """tyro on `cls` (starting from `default` if given); a parse error exits 2 with one line."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            args = tyro.cli(cls, args=argv, prog=f"ttmjx {name}",
                            **({} if default is None else {"default": default}))
    except SystemExit as e:
        if e.code == 2:
            fail(name, one_line(err.getvalue()))
        sys.stderr.write(err.getvalue())
        raise
    sys.stderr.write(err.getvalue())
    return args


def usage(group: str = "") -> str:
    names = [n for n in COMMANDS if n.startswith(group)]
    width = max(map(len, names))
    return "\n".join([f"usage: ttmjx {group or 'COMMAND'}{' COMMAND' if group else ''} [--help] [OPTIONS]",
                      "", "commands:", *(f"  {n:{width}s}  {COMMANDS[n].help}" for n in names), "",
                      "`ttmjx COMMAND --help` lists every option with its type, default and meaning."])


def command_of(argv: list[str]) -> tuple[str, list[str]]:
    """(subcommand name, its arguments); `ttmjx [GROUP] --help` prints the table and exits."""
    for k in (2, 1):
        if " ".join(argv[:k]) in COMMANDS:
            return " ".join(argv[:k]), argv[k:]
    group = argv[0] if argv and any(n.startswith(argv[0] + " ") for n in COMMANDS) else ""
    rest = argv[1:] if group else argv
    if rest[:1] in (["-h"], ["--help"]):
        print(usage(group))
        sys.exit(0)
    expected = ", ".join(n.removeprefix(group).strip() for n in COMMANDS if n.startswith(group))
    fail(group, f"{'unknown command ' + repr(rest[0]) if rest else 'no command'}; expected one of {expected}")


def enable_compile_cache():
    """JAX's persistent compilation cache: compiled rollouts and training steps are reused
    across runs (first compiles take tens of seconds on a CPU)."""
    import jax
    path = os.environ.get("TTMJX_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "ttmjx", "jax"))
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


class Stopped(BaseException):
    """SIGTERM outside a training loop (whose own handler saves a checkpoint and stops it at the
    end of the iteration, training/trainer.py): the command ends as after Ctrl-C, with 143."""
    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def stop_on_sigterm():
    """SIGTERM raises Stopped (a KeyboardInterrupt's counterpart) while the command runs, so it
    unwinds like Ctrl-C: outputs written through a temporary name stay whole or absent, what was
    saved (checkpoints, episode logs) stays, and main exits 143 with one line."""
    import signal
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Stopped(signum)
    old = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


def main(argv: list[str] | None = None) -> None:
    from training.mesh import initialize_distributed
    name, rest = command_of(sys.argv[1:] if argv is None else list(argv))
    cmd = COMMANDS[name]
    try:
        with stop_on_sigterm():
            initialize_distributed()   # several processes: before JAX's first computation (presets probe devices)
            args = cmd.parse(rest) if cmd.parse else parse_args(name, cmd.args, rest)
            enable_compile_cache()
            cmd.run(args)
    except Stopped:
        fail(name, "stopped by SIGTERM; what was saved is kept: run the same command to resume", code=143)
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError, IsADirectoryError) as e:
        fail(name, str(e) if not isinstance(e, OSError) or not e.strerror else file_error(e))
    except OSError as e:          # permission denied, disk full: the environment, not the input
        fail(name, file_error(e), code=1)
    except (RuntimeError, ArithmeticError) as e:   # e.g. training.trainer.NonFiniteError
        fail(name, f"{type(e).__name__}: {e}", code=1)
    except KeyboardInterrupt:
        fail(name, "stopped by SIGINT (Ctrl-C); what was saved is kept: run the same command to resume", code=130)


if __name__ == "__main__":
    main()
