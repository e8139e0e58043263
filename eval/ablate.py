"""`ttmjx ablate NAME`: the paper's simulated ablations as tables of training runs.

An ablation is a base configuration (a scale's setting, SCALES) and variants, each a set of
field overrides applied with dataclasses.replace through the nested frozen configs (ABLATIONS,
the one table of what is compared). A cell is one (variant, seed): one training run in its own
directory under the ablation's output directory, reduced to a small JSON result when it finishes
(eval/table_cells.py). The outputs (eval/tables.py) are rebuilt from the results present.

    OUT/runs/<variant>-seed<s>/     the cell's run (config.json, metrics.jsonl, checkpoints/)
    OUT/results/<variant>-seed<s>.json   the finished cell (skipped when it exists)
    OUT/table.md, curves.png, landings/<variant>.png, summary.json

Cells are ordered seed-major (every variant of seed 0, then seed 1, ...) for --plan and --cells.
The unfinished seeds of a variant train together as one program (training/seeds.py: the lane
is a vmapped axis, laid over every local device or --devices of them), and so do variants that
differ only in the settings a lane carries as data (practice on or off, learning rate, moving
average, practice noise scale: the practice ablation's goalseye and lfp-equal-updates; the noise
ablation's off and bX) or in their demonstrations with
the same schedule (demos d10/d100/d1000 at full scale); the other programs run one after another
in the same process. Each cell keeps its own run directory and result, so it is the same experiment
as when it ran alone.
"""
from __future__ import annotations

import dataclasses
import os
import re
import sys
import typing
from typing import Any, Callable, Literal, NamedTuple

from eval import table_cells
from eval import tables
from training import overrides, runconfig
from training.runconfig import RunConfig
from training.schedule import practice_iterations, pretrain_iterations

log = print


# -- overrides -------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Derived:
    """An override computed from the BASE configuration (the scale's, before any override), for
    values that depend on the scale: 'as many demonstrations as the base run has trajectories'."""
    what: str
    fn: Callable[[RunConfig], Any]

    def __repr__(self) -> str:
        return self.what


def multiple_of(members: int) -> Derived:
    """episodes_per_ssp rounded up to a multiple of `members` (each member practises an equal share)."""
    return Derived(f"episodes_per_ssp rounded up to a multiple of {members}",
                   lambda base: -(-base.episodes_per_ssp // members) * members)


def goalseye_updates(base: RunConfig) -> int:
    """Gradient updates of the base GoalsEye run: pretraining and one S per practice round."""
    return (pretrain_iterations(base) + practice_iterations(base)) * base.steps_between_ssp


def per_round(ratio: float) -> Derived:
    """episodes_per_ssp (M) giving `ratio` gradient updates per practice trajectory at the base's
    steps_between_ssp (S), rounded to a multiple of the members."""
    def m(base: RunConfig) -> int:
        members = base.train.members
        return max(members, round(base.steps_between_ssp / ratio / members) * members)
    return Derived(f"steps_between_ssp / {ratio} episodes, a multiple of the members", m)


def checkpoint_cadence(ratio: float) -> Derived:
    """checkpoint_every scaled with the round (`per_round`), so a cell saves as often per episode
    as its base run (a pool saved every 5 rounds of 200 would be saved 20x as often)."""
    return Derived("the base's checkpoint cadence in episodes",
                   lambda base: max(1, round(base.checkpoint_every * base.episodes_per_ssp
                                             / per_round(ratio).fn(base))))


ALL_TRAJECTORIES = Derived("the base run's total_trajectories", lambda base: base.total_trajectories)
GOALSEYE_UPDATES = Derived("the base GoalsEye run's gradient updates", goalseye_updates)


def replace_fields(obj, fields: dict):
    """obj with `fields` ({'train.members': 3, 'demos': 10}) replaced through nested dataclasses,
    each dataclass rebuilt once (so its checks see all of its new values together)."""
    direct, nested = {}, {}
    for key, value in fields.items():
        head, _, rest = key.partition(".")
        if head not in {f.name for f in dataclasses.fields(obj)}:
            raise ValueError(f"{type(obj).__name__} has no field {head!r}")
        (nested.setdefault(head, {}).__setitem__(rest, value) if rest else direct.__setitem__(head, value))
    for head, sub in nested.items():
        direct[head] = replace_fields(getattr(obj, head), sub)
    return dataclasses.replace(obj, **direct)


def apply(base: RunConfig, overrides: dict) -> RunConfig:
    """The base configuration with a variant's overrides (Derived values computed from `base`)."""
    return replace_fields(base, {k: v.fn(base) if isinstance(v, Derived) else v for k, v in overrides.items()})


# Fields every cell sets itself: given as a run-configuration flag, refused with what to write.
CELL_FIELDS = {"seed": "the cells' seeds are 0..N-1 (--seeds N)",
               "run_dir": "each cell runs in OUT/runs/<cell> (--out OUT)",
               "total_trajectories": "write --trajectories, the cells' budget",
               "preset": "the cells' base is the scale's (--scale)"}


def cell_overrides(base: RunConfig, cfg: RunConfig, taken: tuple = ()) -> dict:
    """{dotted field: value} the run-configuration flags changed (`cfg`, parsed from `base`), for
    every cell; `taken`: fields the command reads itself (baseline's first --seed, --devices).
    ValueError naming the flag, for a field each cell sets itself (CELL_FIELDS)."""
    changed = overrides.changed_fields(base, cfg)
    for name, instead in CELL_FIELDS.items():
        if name in changed and name not in taken:
            raise ValueError(f"--{name.replace('_', '-')} {changed[name]}: {instead}")
    return {k: v for k, v in changed.items() if k not in taken}


def command_line(name: str, scale: str, seeds: int, cells: str | None, trajectories: int | None,
                 out: str | None, changed: dict, devices: int | None) -> str:
    """The `ttmjx ablate` command that rebuilds this table (summary.json's 'command'), in a fixed
    order: the ablation, --scale, --seeds, --cells, --trajectories, --out, the run-configuration
    flags (field order), --devices."""
    return " ".join(["ttmjx ablate", name, "--scale", scale, "--seeds", str(seeds)]
                    + (["--cells", cells] if cells else [])
                    + (["--trajectories", str(trajectories)] if trajectories else [])
                    + (["--out", out] if out else []) + overrides.flags_of(changed)
                    + (["--devices", str(devices)] if devices else []))


def check_choices(obj, where: str = "") -> None:
    """ValueError for a field whose type is a Literal and whose value is none of its choices
    (dataclasses do not check annotations, and a bad demo_source would fail deep in a run)."""
    hints = typing.get_type_hints(type(obj))
    for f in dataclasses.fields(obj):
        value, hint = getattr(obj, f.name), hints[f.name]
        if typing.get_origin(hint) is Literal and value not in typing.get_args(hint):
            raise ValueError(f"{where}{f.name}={value!r}; expected one of {typing.get_args(hint)}")
        if dataclasses.is_dataclass(value):
            check_choices(value, f"{where}{f.name}.")


# -- scales ----------------------------------------------------------------------------------
class Scale(NamedTuple):
    what: str
    base: Callable[[str], RunConfig]      # setting ('sim' or 'new') -> the base configuration


# Trajectories per cell at full scale: what fits one ~10-minute device call with its pretraining,
# demonstrations, evaluations and compilation (docs/BENCHMARKS.md); --trajectories 120000 runs
# the paper's budget.
FULL_TRAJECTORIES = 60_000


def full_base(setting: str) -> RunConfig:
    base = runconfig.paper_sim() if setting == "sim" else runconfig.paper_sim_new()
    return dataclasses.replace(base, total_trajectories=FULL_TRAJECTORIES)


SCALES: dict[str, Scale] = {
    "tiny": Scale("the tiny preset (seconds to a minute per cell on 2 CPU cores; for tests)",
                  lambda setting: runconfig.tiny()),
    "cpu": Scale("the CPU default preset: narrow throws, frame stack 2x256, 2 members, 7k trajectories "
                 "(~10-20 min per cell on 2 CPU cores)", lambda setting: runconfig.preset("cpu")),
    "full": Scale(f"paper-sim (setting 'sim': LSTM 2x1024, 1 member) or paper-sim-new (setting 'new': "
                  f"frame stack, 10 members), any-ball throws, {FULL_TRAJECTORIES:,} trajectories "
                  f"(~6-8 min per cell on one H100)", full_base),
}
SCALE_NAMES = tuple(SCALES)


def resolve_scale(scale: str) -> str:
    """'auto': full on an accelerator, cpu otherwise."""
    if scale != "auto":
        return scale
    from ttmjx.world.backends import on_accelerator
    return "full" if on_accelerator() else "cpu"


# -- the ablations ---------------------------------------------------------------------------
class Ablation(NamedTuple):
    what: str                  # one line: what is compared (the table's subtitle)
    setting: str               # the scale's base: 'sim' (the paper's main run) or 'new' ("New Results")
    variants: dict             # name -> {dotted field: value or Derived}
    x: str = "trajectories"    # the learning curves' x axis: trajectories or updates


ABLATIONS: dict[str, Ablation] = {
    # The paper's Figure 6: 0, 10, 100, 1000 demonstrations, then practice to the same total.
    # (At the tiny scale 1000 exceeds the run's 328 trajectories: that variant practises nothing.)
    "demos": Ablation(
        "bootstrap demonstrations before practice, to the same total trajectories (0 = GCSL)", "sim",
        {"d0": {"demos": 0, "pretrain_steps": 0}, "d10": {"demos": 10}, "d100": {"demos": 100},
         "d1000": {"demos": 1000}}),
    # "New Results": the paper's b is unpublished; it reports 20% -> 40% within 30 cm with noise.
    # paper-bX is the paper's form as written (a + z on every executed target, z held for the
    # episode); bX is this project's own method (the same z as a calibration offset the policy
    # cannot see, models.policy.with_action_noise).
    "noise": Ablation(
        "action noise during practice, z ~ U(-b a_std, b a_std) drawn once per episode: paper-bX the "
        "paper's a + z; bX our own method, z as a hidden calibration offset", "new",
        {"off": {"train.action_noise": 0.0},
         **{f"paper-b{b}": {"train.action_noise": b, "train.action_noise_form": "integrating"}
            for b in (0.05, 0.1, 0.2)},
         **{f"b{b}": {"train.action_noise": b, "train.action_noise_form": "offset"} for b in (0.05, 0.1, 0.2)}}),
    # "New Results": N models practising into one shared pool (paper: 20% -> 35% with N = 10).
    "ensembles": Ablation(
        "data ensembling: members practising into one pool", "new",
        {f"n{n}": {"train.members": n, "episodes_per_ssp": multiple_of(n)} for n in (1, 3, 5, 10)}),
    # The paper's simulated policy sees 16 values (ball velocity included) with an LSTM; its
    # "New Results" stack 8 frames of the robot's 13 (no velocity) into an MLP.
    # On the 'sim' base (one member): ten LSTM 2x1024 members would not fit a cell's 10 minutes.
    "inputs": Ablation(
        "observation (13 values: positions; 16: with ball velocity) and network (frame stack or LSTM)", "sim",
        {f"{kind}-{n}": {"policy.kind": kind, "policy.obs_size": n, "world.ball_velocity_obs": n == 16}
         for kind in ("framestack", "lstm") for n in (13, 16)}),
    # The bootstrap demonstrators: `paper` is the paper's procedure, built for narrow throws
    # only; `striker` the narrow scripted striker.
    "bootstrap": Ablation(
        "bootstrap demonstrator (paper: ES, shift, expand, 4 joints perturbed; striker: narrow scripted returner; "
        "es; oracle: goal-directed)", "sim",
        {src: {"demo_source": src} for src in ("paper", "striker", "es", "oracle")}),
    # LFP is GCBC on the demonstrations alone. Equal updates: same demonstrations and schedule,
    # practice rounds replaced by train-only rounds. Equal data: as many demonstrations as
    # GoalsEye sees trajectories (demonstrations + practice), and GoalsEye's updates.
    # lfp-r0.2-updates: LFP with the updates of GoalsEye at 0.2 updates per practice trajectory
    # (the ratio ablation's r0.2: the same rounds, each train-only). goalseye-paper-pool: GoalsEye
    # as the paper trains it (the pool sampled uniformly, no exploration noise), against this
    # project's pool and noise (training.runconfig.PRACTICE_POOL); lane data of one program.
    "practice": Ablation(
        "self-supervised practice (ours; the paper's uniform pool without noise) against LFP at equal gradient "
        "updates, at equal data and at the updates of 0.2 updates per practice trajectory", "sim",
        {"goalseye": {}, "goalseye-paper-pool": {"train.demo_fraction": 0.0, "train.action_noise": 0.0},
         "lfp-equal-updates": {"practice": False},
         "lfp-equal-data": {"practice": False, "demos": ALL_TRAJECTORIES, "pretrain_steps": GOALSEYE_UPDATES},
         "lfp-r0.2-updates": {"practice": False, "episodes_per_ssp": per_round(0.2),
                              "checkpoint_every": checkpoint_cadence(0.2)}},
        x="updates"),
    # The paper publishes neither S (updates per practice round) nor M (episodes per round); the
    # presets' 200 per 4,000 (0.05 updates per practice trajectory) is this project's. The sweep
    # changes M at the base's S, so pretraining (rounds of S updates) is the same in every cell.
    "ratio": Ablation(
        "gradient updates per practice trajectory (S / M: M changed, S the base's)", "sim",
        {f"r{r}": {"episodes_per_ssp": per_round(r), "checkpoint_every": checkpoint_cadence(r)}
         for r in (0.05, 0.2, 1)}),
}
ABLATION_NAMES = tuple(ABLATIONS)


# -- cells -----------------------------------------------------------------------------------
def default_out(name: str, scale: str) -> str:
    return os.path.join("ablations", f"{name}-{scale}")


def cell_order(name: str, seeds: int) -> list[tuple[str, int]]:
    """(variant, seed) of every cell, seed-major."""
    return [(v, s) for s in range(seeds) for v in ABLATIONS[name].variants]


def select(name: str, order: list[tuple[str, int]], spec: str | None) -> list[tuple[str, int]]:
    """The cells `spec` names: comma-separated indices (3), ranges (0:3, 4:) or variant names
    (all their seeds); None: every cell. In plan order, each once."""
    if spec is None:
        return order
    chosen: set[int] = set()
    for item in (i.strip() for i in spec.split(",")):
        chosen |= set(_indices(name, order, item))
    if not chosen:
        raise ValueError(f"--cells {spec!r} selects no cell")
    return [c for i, c in enumerate(order) if i in chosen]


def _indices(name: str, order: list, item: str) -> range | list[int]:
    n, variants = len(order), list(ABLATIONS[name].variants)
    if item in variants:
        return [i for i, (v, _) in enumerate(order) if v == item]
    m = re.fullmatch(r"(\d*)(:?)(\d*)", item)
    if m and item not in ("", ":"):
        lo = int(m.group(1) or 0)
        hi = (int(m.group(3)) if m.group(3) else n) if m.group(2) else lo + 1
        if lo < hi <= n:
            return range(lo, hi)
        raise ValueError(f"--cells {item!r}: out of range or empty; this plan has cells 0..{n - 1} "
                         f"({len(variants)} variants x seeds)")
    raise ValueError(f"--cells {item!r}: expected a cell index (0..{n - 1}), a range like 0:3, or a "
                     f"variant of {name} ({', '.join(variants)})")


def base_config(name: str, scale: str) -> RunConfig:
    """The configuration every cell of ablation `name` at `scale` starts from (before the
    run-configuration flags, the cell's seed, run directory and budget, and its variant)."""
    return SCALES[scale].base(ABLATIONS[name].setting)


def cell_base(base: RunConfig, seed: int, run_dir: str, trajectories: int | None = None) -> RunConfig:
    """A scale's base configuration for one table cell: its seed, its run directory and, if
    given, its trajectory budget (ablations and baselines alike)."""
    if trajectories is not None:
        base = dataclasses.replace(base, total_trajectories=trajectories)
    return dataclasses.replace(base, seed=seed, run_dir=run_dir)


def variant_config(name: str, variant: str, scale: str, seed: int, run_dir: str,
                   trajectories: int | None = None, changed: dict | None = None) -> RunConfig:
    """The resolved configuration of one cell: the scale's base, `changed` ({dotted field:
    value}, the run-configuration flags, for every cell: cell_overrides) and the variant's own
    fields on top; ValueError naming the variant if it is invalid."""
    ab = ABLATIONS[name]
    base = replace_fields(cell_base(base_config(name, scale), seed, run_dir, trajectories), changed or {})
    try:
        cfg = apply(base, ab.variants[variant])
        check_choices(cfg)
    except (ValueError, TypeError) as e:
        raise ValueError(f"ablation {name}, variant {variant} at scale {scale}: {e}") from None
    return cfg


def plan(name: str, scale: str, seeds: int, out: str, spec: str | None = None,
         trajectories: int | None = None, changed: dict | None = None, devices: int | None = None) -> list[table_cells.Cell]:
    """The selected cells with their configurations, checked before anything is written: every
    variant config valid, every finished result computed with the config asked for now.
    `devices`: the devices each program's lanes are laid over (None: every local device)."""
    cells = table_cells.planned_cells(out, select(name, cell_order(name, seeds), spec),
                                      lambda v, seed, run_dir: dataclasses.replace(
                                          variant_config(name, v, scale, seed, run_dir, trajectories, changed),
                                          devices=devices))
    practising = [c.config for c in cells if c.config.practice]
    if practising and all(practice_iterations(c) == 0 for c in practising):
        # a table of practice that practises nowhere measures nothing it names
        least = min(c.demos for c in practising)
        raise ValueError(f"--trajectories {practising[0].total_trajectories}: no cell of {name} would practise (each "
                         f"has at least {least} demonstrations); expected more than {least}")
    return cells


def status(out: str, name: str, seeds: int) -> list[str]:
    """`--plan`: one line per cell: index, name, finished / partial / to do."""
    lines = []
    for i, (v, s) in enumerate(cell_order(name, seeds)):
        cell = f"{v}-seed{s}"
        if os.path.exists(os.path.join(out, "results", cell + ".json")):
            state = "finished"
        elif os.path.isdir(os.path.join(out, "runs", cell, "checkpoints")):
            state = "partial (resumes from its checkpoint)"
        else:
            state = "to do"
        lines.append(f"{i:3d}  {cell:24s}  {state}")
    return lines


# -- running and reporting ---------------------------------------------------------------------
def run(name: str, scale: str, seeds: int, out: str, spec: str | None = None, trajectories: int | None = None,
        progress: bool = True, trainer: table_cells.Trainer = table_cells.goalseye, command: str = "",
        changed: dict | None = None, devices: int | None = None) -> dict:
    """Train the selected cells that are not finished, then rebuild the outputs. The summary has
    'stopped_by_signal' set when a signal cut a cell short (its run resumes next time). The cells
    that one program can train (training.seeds.program_key: the seeds of a variant, and variants
    that differ only in the lane knobs or their demonstrations) train together, their lanes laid
    over `devices` devices (None: all)."""
    cells = plan(name, scale, seeds, out, spec, trajectories, changed, devices)
    for c in cells:
        if c.config.practice and practice_iterations(c.config) == 0:
            log(f"[ablate] note: {c.name} practises nothing: its {c.config.total_trajectories} trajectories do not "
                f"exceed its {c.config.demos} demonstrations", file=sys.stderr)
    # GoalsEye's seeds of a variant train together as one program (training/seeds.py).
    batch = table_cells.goalseye_seeds if trainer is table_cells.goalseye else None
    stopped = table_cells.run_cells(cells, os.path.join(out, "results"), trainer, progress,
                                    f"ablate {name} {scale}", log=lambda m: log(m, file=sys.stderr), batch=batch)
    return table_cells.finish(cells, out, stopped, lambda: build_report(name, scale, out, command))


def load_results(out: str) -> list[dict]:
    d = os.path.join(out, "results")
    names = sorted(f for f in os.listdir(d) if f.endswith(".json")) if os.path.isdir(d) else []
    return [table_cells.load_result(os.path.join(d, f)) for f in names]


def bootstrap_of(results: list[dict]) -> str:
    """The demonstrator(s) behind the results, for the table's header."""
    sources = sorted({r["config"]["demo_source"] for r in results if r["config"].get("demos", 0) > 0})
    zero = any(r["config"].get("demos", 0) == 0 for r in results)
    text = ", ".join(sources) if sources else ""
    return (text + (" (and none: GCSL)" if sources else "none (GCSL)")) if zero else text


def build_report(name: str, scale: str, out: str, command: str = "") -> dict:
    """table.md, curves.png, landings/*.png and summary.json from the results in `out`."""
    results = load_results(out)
    if not results:
        raise ValueError(f"no finished cells in {os.path.join(out, 'results')}; run "
                         f"`ttmjx ablate {name} --scale {scale}` first")
    ab = ABLATIONS[name]
    trajectories = sorted({r["config"]["total_trajectories"] for r in results})
    goals = sorted({r["config"]["eval_goals"] for r in results})
    header = {"ablation": name, "scale": scale, "command": command, "bootstrap": bootstrap_of(results),
              "title": f"ablate {name} ({scale}; bootstrap: {bootstrap_of(results)})",
              "subtitle": f"{ab.what}. Bootstrap: {bootstrap_of(results)}. Scale {scale}: {SCALES[scale].what}; "
                          f"{'/'.join(f'{t:,}' for t in trajectories)} trajectories per cell. Final evaluation of "
                          f"each cell: {'/'.join(map(str, goals))} uniform goals, seed {table_cells.FINAL_EVAL_SEED} "
                          f"(the same goals and throws for every cell).",
              "variants_overrides": {v: {k: repr(x) if isinstance(x, Derived) else x for k, x in o.items()}
                                     for v, o in ab.variants.items()}}
    return tables.write_report(out, results, list(ab.variants), header, ab.x)
