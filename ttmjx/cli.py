"""`ttmjx`: the simulator side's command line, on top of every package (world -> tools -> models
-> training -> eval -> deploy/robot -> deploy/sim -> here; only the console script's entry,
ttmjx/entry.py, imports it). The robot side's commands (`robot run`, `robot bench`) are defined
in deploy/robot/cli.py and listed here too.

Every subcommand is a row of COMMANDS (at the bottom): its arguments (a frozen dataclass whose
fields are its flags; `ttmjx CMD --help` lists each with its type, default and meaning, nested
configuration fields included), the function that runs it and a line of help. Subcommands that
report numbers take --json and then print one JSON object as their last line (non-finite numbers
as null). Bad input exits 2 with one line, `ttmjx CMD: error: ...`.
"""
from __future__ import annotations

import dataclasses
import json
import os
import sys
from typing import Annotated, ClassVar, Literal

import tyro

from deploy.robot import cli as robot_side
from ttmjx import commandline
from ttmjx.commandline import (Command, Flag, Report, check_new_path, check_resumable_dir, fail, report,
                               table)
from eval.ablate import ABLATION_NAMES, SCALE_NAMES
from training.baselines.config import ESConfig, PPOConfig, QTOptConfig, RewardConfig, SACConfig
from training import overrides
from training.runconfig import PRESET_NAMES, RunConfig
from ttmjx.world.backends import BACKENDS, backend_kind
from ttmjx.world.config import CONTROL_RATES, MJX_IMPLS, THROW_DISTRIBUTIONS, World

Backend = Literal[BACKENDS]


RunPath = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN_OR_CHECKPOINT")]
DatasetPath = Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="DIR")]


# --------------------------------------------------------------------------------------------
# Arguments: one frozen dataclass per subcommand; field docstrings are the --help lines.
# --------------------------------------------------------------------------------------------
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
    mjx_impl: Literal[MJX_IMPLS] = "jax"
    """MJX's implementation on the mjx backend: jax or warp (MuJoCo Warp; pip install 'ttmjx[warp]')."""

    def world(self) -> World:
        cfg = World(mjx_impl=self.mjx_impl) if self.control_hz is None else \
            World(control_hz=self.control_hz, mjx_impl=self.mjx_impl)
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
    procedure from scratch, ES included, ~45 min); everything it builds goes to OUT/bootstrap/,
    and the same command resumes it there (an OUT holding only bootstrap/)."""
    es_generations: tuple[int, int] = (134, 330)
    """With --rebuild all: ES generations of the contact and the return phase (48 candidates x 8
    throws each)."""

    @property
    def NEW_DIRS(self) -> tuple:   # noqa: N802 (the Report field list)
        # A rebuild cut short resumes: an --out that holds only its bootstrap/ is accepted.
        resuming = (self.rebuild != "none" and os.path.isdir(self.out)
                    and set(os.listdir(self.out)) == {"bootstrap"})
        return () if resuming else ("out",)

    def __post_init__(self):
        super().__post_init__()
        if self.rebuild != "none" and self.source != "paper":
            raise ValueError(f"--rebuild {self.rebuild} builds the paper procedure; --source is {self.source!r}")
        if self.rebuild != "none" and backend_kind(self.backend).traceable:
            raise ValueError("--rebuild runs ES and the stages on the MuJoCo C backend (--backend c)")
        if self.rebuild == "stages":
            from ttmjx.tools import es
            trained = es.read_meta(es.shipped_dir(self.distribution)).get("distribution")
            if trained != self.distribution:
                raise ValueError(f"--rebuild stages starts from the shipped ES policy, trained on {trained} throws, "
                                 f"not {self.distribution}: use --rebuild all")
        if self.rebuild != "none":
            from training.bootstrap_paper import Procedure
            Procedure(final=self.n, seed=self.seed, es_generations=self.es_generations).check(
                self.rebuild == "all", flags={"final": "--n", "es_generations": "--es-generations"})


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
        check_resumable_dir("run_dir", self.config.run_dir)
        self.config.check_meaningful()
        from training.loss import lstm_kernel      # JAX's backend: imported on use, as the command's work is
        lstm_kernel(self.config.policy, self.config.train)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ReportArgs(Report):
    """Why a run learns or not: per practice round, the pool's landing density (demonstrations
    and practice apart), success and good-per-100 by goal region, each ensemble member against
    the ensemble, the training loss (report.json, report.png; docs/RESULTS.md)."""
    run: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="RUN")]
    """Run directory (ttmjx train --run-dir; one seed of a batch: RUN/seed<s>)."""
    out: str | None = None
    """Directory for report.json and report.png; None: RUN/report."""

    def __post_init__(self):
        super().__post_init__()
        check_resumable_dir("out", self.out)     # a file there, or under one


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
    """A --goals value (ttmjx.world.goalspec, the grammar robot run reads too): N uniform goals,
    'uniform' (200 of them), 'five' (goals A-E, --per-goal attempts each), 'x,y;x,y' goals in
    metres, or a goal file (.csv with a header row x,y, or .npy [N, 2]); goals on the opponent's
    half, one attempt each."""
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
    skipped, a half-finished one resumes from its checkpoint.

    Every run-configuration field is a flag as in `ttmjx train` (`ttmjx train --help` lists
    them), e.g. `--demo-source paper` (the table on the paper's bootstrap procedure) or
    `--train.members 4`: set on the scale's base for every cell, before the variants' own fields.
    --devices N lays each program's lanes (the cells it trains together) over N local devices."""
    BOUNDS: ClassVar[dict] = {"seeds": (1, 1000), "trajectories": (1, None)}
    name: Annotated[Literal[ABLATION_NAMES], tyro.conf.Positional, tyro.conf.arg(metavar="NAME")]
    """The ablation: demos, noise, ensembles, inputs, bootstrap, practice or ratio."""
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
    config: Annotated[RunConfig, tyro.conf.arg(name="")]
    report: Flag = False
    """Only (re)build the table, curves, landing maps and summary from the finished cells."""
    plan: Flag = False
    """List the cells (index, name, finished / partial / to do) and exit."""

    def __post_init__(self):
        super().__post_init__()
        check_resumable_dir("out", self.out)     # a file there, or under one


@dataclasses.dataclass(frozen=True, kw_only=True)
class BaselineArgs(Report):
    """The paper's Table I on this world: RL baselines (ppo, sac, es through brax; qtopt), GCSL,
    LFP and GoalsEye at one trajectory budget, each (method, seed) a cell as in `ttmjx ablate`: a markdown
    table (mean +- 95% interval over seeds), learning curves, landing maps, JSON per cell. The seeds
    of a method train together as one program (RL seeds in groups, where all of them would not
    fit the GPU's memory). The same command skips finished cells and resumes
    cut ones (RL cells from the state saved after every epoch).

    --seed S: the first seed (so that several machines or calls each run some seeds of one
    table). Every other run-configuration field is a flag as in `ttmjx train` (`ttmjx train
    --help` lists them), e.g. `--demo-source paper` or `--world.timing.ideal-timing`: set on the
    scale's GoalsEye base for every cell (RL methods' world and policy included)."""
    BOUNDS: ClassVar[dict] = {"seeds": (1, 1000), "trajectories": (1, None)}
    method: Annotated[str, tyro.conf.Positional, tyro.conf.arg(metavar="METHOD")]
    """ppo, sac, es, qtopt, gcsl, lfp or goalseye; several comma-separated, or all."""
    trajectories: int | None = None
    """Trajectories per cell; None: the scale's (full: 120,000, the paper's)."""
    seeds: int = 5
    """Seeds per method: --seed..--seed+N-1."""
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
    qtopt: QTOptConfig = QTOptConfig()
    """QT-Opt's settings at --scale full (its CEM, target networks, replay; training/baselines/config.py)."""
    config: Annotated[RunConfig, tyro.conf.arg(name="")]
    report: Flag = False
    """Only (re)build the table, curves, landing maps and summary from the finished cells."""

    def __post_init__(self):
        super().__post_init__()
        check_resumable_dir("out", self.out)     # a file there, or under one


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
class RobotParityArgs(Report):
    """An export played twice on the same throws, goals, start poses and timing draws: by the
    training world (MuJoCo C or MJX) and by the robot runner on the simulated station; per
    control step where the frames and the sent commands first part, then both sides' hits,
    landings and strict metrics (deploy/sim/parity.py)."""
    BOUNDS: ClassVar[dict] = {"n": (1, 100_000)}
    policy: str
    """An export directory (ttmjx export --out), with its timing record."""
    n: int = 16
    """Uniform goals (episodes): the draw of `ttmjx eval --goals N --seed S`."""
    seed: int = 1234
    """Seed of the goals, throws, start poses and timing draws."""
    backend: Backend = "c"
    """The world's physics: MuJoCo C or MJX (the station is always MuJoCo C)."""
    timing: str = "trained"
    """trained (the export's timing, its per-episode delays drawn), centre (fixed at its centre) or a
    profile (nominal, zero)."""
    out: str | None = None
    """Directory for parity.json and parity.png (new or empty)."""

    def __post_init__(self):
        super().__post_init__()
        if self.out is not None:
            check_new_path("out", self.out, want_dir=True)


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
    """Injected faults, e.g. 'egm.loss=0.05,modbus.delay_ms=10' (deploy/sim/serve.py FAULT_KINDS)."""
    egm_hz: float = 250.0
    """EGM cycle rate of the simulated controller."""
    duration_s: float | None = None
    """Stop after this many seconds; None: until interrupted."""





# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------
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
        out = bench_training(a.train, a.seeds, a.reps, log=lambda m: print(m, file=sys.stderr),
                             mjx_impl=a.mjx_impl)
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
    from training import dataset_build
    out = dataset_build.dataset(a.world(), a.source, a.n, a.seed, a.out, a.backend, a.rebuild, a.es_generations,
                                progress=not a.json, log=lambda m: print(m, file=sys.stderr))
    report(a, out, f"{table(out)}\nwrote {a.out} (and {os.path.join(a.out, 'coverage.png')})")


def plot_landings(a: PlotArgs) -> None:
    from ttmjx.tools import demos as demonstrations
    path = demonstrations.plot_landings(a.dir, a.out)
    report(a, {"plot": path}, f"wrote {path}")


def parse_train(argv: list[str]) -> TrainArgs:
    """--preset P picks the defaults tyro shows and overrides (`--preset` is RunConfig.preset)."""
    name, base = overrides.preset_named(argv)
    a = overrides.parse_config_args("train", TrainArgs, argv, TrainArgs(config=base), f"preset {name}")
    return dataclasses.replace(a, config=overrides.seed_run_dir(a.config, base, argv))


def ablation_base(name: str, scale: str) -> tuple[RunConfig, str]:
    from eval.ablate import base_config, resolve_scale
    return base_config(name, resolve_scale(scale)), f"ablation {name}'s base at scale {scale}"


def parse_ablate(argv: list[str]) -> AblateArgs:
    name = next((arg for arg in argv if arg in ABLATION_NAMES), None)
    scale = overrides.flag_value(argv, "--scale", "auto")
    valid = name is not None and scale in ("auto", *SCALE_NAMES)
    return overrides.parse_cells("ablate", AblateArgs, argv, {"name": name, "scale": scale} if valid else None,
                                 ablation_base)


def baseline_base(method: str, scale: str) -> tuple[RunConfig, str]:
    from eval.baselines import goalseye_base
    return goalseye_base(scale), f"the GoalsEye base at scale {scale}"


def parse_baseline(argv: list[str]) -> BaselineArgs:
    from eval.baselines import METHODS
    method = next((arg for arg in argv
                   if arg == "all" or (not arg.startswith("-") and arg.split(",")[0] in METHODS)), None)
    scale = overrides.flag_value(argv, "--scale", "full")
    valid = method is not None and scale in ("tiny", "full")
    return overrides.parse_cells("baseline", BaselineArgs, argv, {"method": method, "scale": scale} if valid else None,
                       baseline_base)


def train(a: TrainArgs) -> None:
    import functools

    from eval.evaluate import training_evaluation
    from training.pool import check_sources
    from training.seeds import seed_configs
    from training.trainer import Run
    cfg = a.config
    check_sources(cfg)
    # one seed is a batch of one lane; --seeds N trains seeds --seed .. --seed + N - 1 in one program
    runs = cfg if a.seeds == 1 else seed_configs(cfg, a.seeds)
    out = Run(runs, functools.partial(training_evaluation, heldout=True), progress=not a.json,
              parent=None if a.seeds == 1 else cfg.run_dir).run(max_iterations=a.max_iterations)
    if a.seeds == 1:
        report(a, out, table(out))
    else:
        lines = [f"seed {r['seed']}: " + table({k: v for k, v in r.items() if k.startswith("eval_")})
                 .replace("\n", ", ") for r in out["runs"]]
        report(a, out, table({k: v for k, v in out.items() if k != "runs"}) + "\n" + "\n".join(lines))
    if out["stopped_by_signal"]:
        sys.exit(commandline.signal_exit_code(out["stopped_by_signal"]))


def run_report(a: ReportArgs) -> None:
    from eval.diagnostics import write_report
    out = write_report(a.run, a.out)
    last = out["summary"]["rounds"][-1]
    report(a, {k: out[k] for k in ("json", "png")} | {"last_round": last},
           f"wrote {out['json']} and {out['png']}\n"
           f"last round (trajectories {last['trajectories']}): good per 100 {last['good_per_100']:.1f}, "
           f"pool landings off the half {100 * last['pool_landings']['off_half']:.1f}%")


def evaluate(a: EvalArgs) -> None:
    from eval.evaluate import evaluate_checkpoint
    from eval.seed_batch import evaluate_seeds
    from training.baselines.qtopt import check_exportable
    from training.seeds import pick_seed
    check_exportable(a.run)
    if a.seed_index is None:
        out = evaluate_seeds(a.run, a.goals, a.per_goal, a.distribution, a.backend, a.seed, a.member, a.step, a.out)
        if out is not None:     # a batch of seeds: each one, then the spread
            lines = [f"{os.path.basename(r['run_dir'])}: <=30cm {r['eval_within_30cm']:.1%} <=20cm "
                     f"{r['eval_within_20cm']:.1%} hit {r['eval_hit_rate']:.1%}" for r in out["runs"]]
            report(a, out, "\n".join(lines) + "\n" +
                   table({k: v for k, v in out.items() if k.endswith(("_mean", "_std"))}))
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
    from training.mesh import check_local_devices
    devices = a.config.devices
    check_local_devices(devices)   # before any cell is planned or compiled
    scale = ablations.resolve_scale(a.scale)
    changed = ablations.cell_overrides(ablations.base_config(a.name, scale), a.config, taken=("devices",))
    out = a.out or ablations.default_out(a.name, scale)
    if a.plan:
        ablations.plan(a.name, scale, a.seeds, out, a.cells, a.trajectories, changed, devices)   # refuses what would fail
        print("\n".join(ablations.status(out, a.name, a.seeds)))
        return
    command = ablations.command_line(a.name, scale, a.seeds, a.cells, a.trajectories, a.out, changed, devices)
    if a.report:
        summary = ablations.build_report(a.name, scale, out, command)
    else:
        summary = ablations.run(a.name, scale, a.seeds, out, a.cells, a.trajectories, progress=not a.json,
                                command=command, changed=changed, devices=devices)
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
                   f"{', '.join(saved) or 'none yet'}; run the same command to resume",
             code=commandline.signal_exit_code(sig))


def baseline(a: BaselineArgs) -> None:
    from eval import ablate, baselines
    methods = baselines.parse_methods(a.method)
    first = a.config.seed
    changed = ablate.cell_overrides(baselines.goalseye_base(a.scale), a.config, taken=("seed",))
    out = a.out or os.path.join("baselines", a.scale)
    command = baselines.command_line(a.method, a.scale, a.seeds, first, a.trajectories, a.out, changed)
    if a.report:
        summary = baselines.build_report(a.scale, out, command)
    else:
        rl = baselines.rl_settings(ppo=a.ppo, sac=a.sac, es=a.es, qtopt=a.qtopt)
        summary = baselines.run(methods, a.scale, a.seeds, out, a.trajectories, a.reward, progress=not a.json,
                                command=command, rl=rl, first_seed=first, changed=changed)
    table_report(a, "baseline", summary, out)


def export(a: ExportArgs) -> None:
    from deploy.robot.exported import load_export
    from deploy.sim.export import export_checkpoint
    from training.baselines.qtopt import check_exportable
    from training.seeds import pick_seed
    check_exportable(a.checkpoint)      # QT-Opt's policy is no checkpoint: one line, not "none found"
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
    report(a, out, f"exported {source} -> {path} ({spec.kind} {spec.layers}x{spec.hidden}, {spec.head} head, "
                   f"{policy.members} member(s), {contract.control_hz:g} Hz); golden self-test "
                   f"max error {policy.self_test_error:.2g}; " +
           (f"{graph['file']}: golden max error {graph['golden_error']:.2g} ({graph['checked_with']})"
            if graph else f"no ONNX graph (the {spec.head} head plays on the numpy engine; the graph is "
                          f"built for the mean head)" if spec.head != "mean" else
            "no ONNX graph (pip install 'ttmjx[onnx]' for one)"))


def sim_station(*args, **kwargs) -> dict:
    """A session on the simulated station (deploy.sim.station.run_sim), which `ttmjx robot run
    --station sim` plays on: the robot side's command is handed it from here, and never imports
    the simulator side."""
    from deploy.sim.station import run_sim
    return run_sim(*args, **kwargs)


def robot_sweep(a: RobotSweepArgs) -> None:
    import numpy as np

    from deploy.robot.goals import session_goals
    from deploy.sim.sweep import latency_sweep, parse_series, sweep_table
    series = parse_series(a.series)
    goals = session_goals("uniform", a.n, a.seed)
    out = latency_sweep(a.policy, goals, a.out, np.linspace(0.0, a.max_ms, a.points), a.seed, a.timing,
                        series=series, jitter_ms=np.linspace(0.0, a.max_jitter_ms, a.points), progress=not a.json)
    report(a, out, sweep_table(out) + f"\nwrote {a.out}/sweep.json and sweep.png")


def robot_parity(a: RobotParityArgs) -> None:
    from deploy.sim.parity import parity_table, run_parity
    out = run_parity(a.policy, a.n, a.seed, a.backend, a.timing, a.out)
    report(a, out, parity_table(out) + (f"\nwrote {a.out}/parity.json and parity.png" if a.out else ""))


def robot_serve(a: RobotServeArgs) -> None:
    from deploy.robot.drivers.config import load_cell_config
    from deploy.sim.serve import check_ports, make_station, parse_faults, serve
    from deploy.sim.serve_setup import served_station
    cell = load_cell_config(a.config)
    faults = parse_faults(a.faults)
    check_ports(cell)                  # before the station's slow start
    served = served_station(a.policy, a.distribution, a.control_hz, a.timing, a.allow_untrained_timing)
    station = make_station(served.cfg, served.contract, a.seed, served.timing)
    if served.timing_info is not None and not served.timing_info["within_trained"]:
        from deploy.robot.timing_check import timing_line
        print(f"ttmjx robot serve: warning: {timing_line(served.timing_info)}", file=sys.stderr, flush=True)
    out = serve(cell, station, faults, egm_hz=a.egm_hz, seed=a.seed, duration_s=a.duration_s)
    if served.timing_info is not None:
        out["timing"] = served.timing_info
    report(a, out, table({k: json.dumps(v) for k, v in out.items()}))


COMMANDS: dict[str, Command] = {
    "throw": Command(ThrowArgs, throw, "sample throws and simulate their first bounce", resumes=False),
    "bench": Command(BenchArgs, bench, "physics throughput of a backend", resumes=False),
    "render": Command(RenderArgs, render, "write a short video (GIF) of a few throws, headless", resumes=False),
    "sim": Command(SimArgs, sim, "a short simulation run that prints what it did", resumes=False),
    "demos": Command(DemosArgs, demos, "collect bootstrap demonstrations into a dataset directory"),
    "plot-landings": Command(PlotArgs, plot_landings, "draw a dataset's landing points over the table (PNG)",
                             resumes=False),
    "train": Command(TrainArgs, train, "GoalsEye training: demonstrations, GCBC, self-practice, evaluation",
                     parse_train),
    "eval": Command(EvalArgs, evaluate, "goal-reaching metrics of a run or checkpoint", resumes=False),
    "report": Command(ReportArgs, run_report, "why a run learns or not: practice by goal region, members, pool density",
                      resumes=False),
    "ablate": Command(AblateArgs, ablate, "a paper ablation: cells of (variant, seed) runs -> table, curves, landing maps",
                      parse_ablate),
    "baseline": Command(BaselineArgs, baseline, "Table I: RL baselines (brax PPO, SAC, ES; QT-Opt), GCSL, LFP and GoalsEye -> table, curves",
                        parse_baseline),
    "export": Command(ExportArgs, export, "safetensors weights + contract + golden self-test + ONNX graph for the robot runner",
                      resumes=False),
    "robot run": robot_side.COMMANDS["robot run"]._replace(run=lambda a: robot_side.robot_run(a, sim_station)),
    "robot sweep": Command(RobotSweepArgs, robot_sweep, "strict success against added ball and command latency"),
    "robot parity": Command(RobotParityArgs, robot_parity, "the world and the runner on the same draws: where they part",
                            resumes=False),
    "robot serve": Command(RobotServeArgs, robot_serve, "serve the simulated station over EGM, Modbus TCP and UDP (rehearsal)",
                           resumes=False),
    "robot bench": robot_side.COMMANDS["robot bench"],
}


# --------------------------------------------------------------------------------------------
# Running a command
# --------------------------------------------------------------------------------------------
def enable_compile_cache():
    """JAX's persistent compilation cache: compiled rollouts and training steps are reused
    across runs (first compiles take tens of seconds on a CPU)."""
    import jax
    path = os.environ.get("TTMJX_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "ttmjx", "jax"))
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def prepare() -> None:
    """Before parsing: the persistent compilation cache."""
    enable_compile_cache()


def main(argv: list[str] | None = None) -> None:
    commandline.run(COMMANDS, sys.argv[1:] if argv is None else list(argv), prepare)

