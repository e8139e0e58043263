"""One cell of an experiment table (a table cell; the robot cell is deploy/robot/drivers/): a
training run with one configuration and one seed, reduced
to a small JSON result (final metrics, the learning curve, the landings of the final evaluation,
the wall time and the resolved configuration).

The seam for other tables (`ttmjx ablate`, `ttmjx baseline METHOD`): a `Trainer` is any
function (config, progress) -> Outcome. `goalseye` is the one for this project's trainer;
another method (brax's PPO, SAC, ES: eval/baselines.py rl_trainer) supplies its own and reuses everything else here:
skipping finished cells, resuming, atomic results, the report (eval/tables.py).
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Any, Callable, NamedTuple

import jax
import numpy as np

from eval.evaluate import training_evaluation, uniform_runs
from training.checkpoint import load_checkpoint
from training.runlog import MetricsLog
from training.seeds import program_key
from training.trainer import Run
from ttmjx.world import files
from ttmjx.world.backends import Backend, lane, lane_of_one, resolve_backend

# The final evaluation of every cell uses this key: the same goals and throws for every
# variant and seed, so differences between cells are the policies', not the draws'.
FINAL_EVAL_SEED = 1234


class Outcome(NamedTuple):
    """What a trainer hands back for one cell."""
    finished: bool            # False: stopped early (a signal); the cell is redone/resumed later
    stopped_by_signal: int    # the signal that stopped it (0: none)
    final: dict               # metrics of the final evaluation (goal_metrics keys)
    curve: list               # [{trajectories, updates, cache_size, <metric>: ...}] per evaluation
    landings: dict            # final evaluation per episode: goal [G, 2], landing [G, 2], hit, on_opponent


Trainer = Callable[[Any, bool], Outcome]   # (config with seed and run_dir set, progress) -> Outcome
# (configs that differ only in seed and run_dir, progress) -> one Outcome per config
BatchTrainer = Callable[[list, bool], list]


@dataclasses.dataclass(frozen=True)
class Cell:
    """(variant, seed) of an experiment, its resolved config and where its run lives."""
    variant: str
    seed: int
    config: Any               # a frozen dataclass (RunConfig for GoalsEye)
    run_dir: str

    @property
    def name(self) -> str:
        return f"{self.variant}-seed{self.seed}"


def config_json(cfg) -> dict:
    """A config dataclass as plain JSON values (tuples as lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def result_path(results_dir: str, cell: Cell) -> str:
    return os.path.join(results_dir, f"{cell.name}.json")


def load_result(path: str) -> dict:
    with open(path) as f:
        return json.load(f)


def check_result_matches(path: str, cell: Cell) -> None:
    """ValueError if the finished result at `path` was computed with another configuration (a
    skipped cell must be the cell this command asks for)."""
    saved, mine = load_result(path).get("config", {}), config_json(cell.config)
    # the run directory and the devices (where it ran) do not change what a cell computes
    diff = sorted(k for k in set(saved) | set(mine) if k not in ("run_dir", "devices") and saved.get(k) != mine.get(k))
    if diff:
        raise ValueError(f"{path} holds a result computed with a different config (fields {diff}); "
                         f"delete it or choose another --out")


def check_run_matches(cell: Cell) -> None:
    """ValueError (the trainer's own, training.trainer.check_same_config) if the cell's
    unfinished run directory was started with another configuration: refused by the plan as
    its training would refuse it. An unreadable config.json is the trainer's to judge."""
    path = os.path.join(cell.run_dir, "config.json")
    from training.runconfig import RunConfig
    if not isinstance(cell.config, RunConfig) or not os.path.isfile(path):     # RL cells: their own state
        return
    try:
        saved = load_result(path)
    except (OSError, ValueError):
        return
    if isinstance(saved, dict):
        from training.rundir import check_same_config
        try:
            check_same_config(cell.config, saved)
        except ValueError as e:
            raise ValueError(f"{str(e).split(';')[0]}: cell {cell.name} of this command cannot resume it; delete "
                             f"{cell.run_dir} or choose another --out") from None


TABLE_ENTRIES = ("runs", "results", "table.md", "curves.png", "landings", "summary.json")


def check_table_dir(out: str) -> None:
    """ValueError naming `out` and what it holds if it is neither new, empty nor a table's
    directory (runs/, results/, the report): a training run, an export, a dataset or other files
    would be mixed with (and mistaken for) the table's cells."""
    if not os.path.isdir(out):
        return
    names = sorted(os.listdir(out))
    foreign = [n for n in names if n not in TABLE_ENTRIES and not n.startswith(".")]
    if not foreign:
        return
    raise ValueError(f"--out {out!r} holds {files.what_it_holds(out, foreign)}, not a table's "
                     f"runs/ and results/; choose a new or empty directory")


def planned_cells(out: str, entries, make_config) -> list[Cell]:
    """The cells of an ablation or baseline table under `out`: one per (variant, seed) of
    entries, configured by make_config(variant, seed, run_dir); every finished result checked
    against the configuration asked for now (ValueError), before anything is written."""
    if os.path.isfile(out):
        raise ValueError(f"--out {out!r} is a file; expected a directory")
    check_table_dir(out)
    chosen = []
    for variant, seed in entries:
        run_dir = os.path.join(out, "runs", f"{variant}-seed{seed}")
        cell = Cell(variant, seed, make_config(variant, seed, run_dir), run_dir)
        done = result_path(os.path.join(out, "results"), cell)
        if os.path.exists(done):
            check_result_matches(done, cell)
        else:
            check_run_matches(cell)
        chosen.append(cell)
    return chosen


def run_cell(cell: Cell, results_dir: str, trainer: Trainer, progress: bool = True, log=print) -> dict:
    """The cell's result: read if it is finished, else trained (resuming its run directory) and
    written atomically. {'stopped_by_signal': N} if a signal stopped the trainer early (nothing
    written; the same call resumes it)."""
    path = result_path(results_dir, cell)
    if os.path.exists(path):
        log(f"[ablate] {cell.name}: finished earlier ({path}), skipped")
        return load_result(path)
    os.makedirs(cell.run_dir, exist_ok=True)
    t0 = time.perf_counter()
    out = trainer(cell.config, progress)
    wall = add_wall_time(cell.run_dir, time.perf_counter() - t0)
    if not out.finished:
        return {"stopped_by_signal": out.stopped_by_signal}
    result = {"variant": cell.variant, "seed": cell.seed, "run_dir": cell.run_dir, "final": out.final,
              "curve": out.curve, "landings": out.landings, "wall_s": wall["wall_s"], "attempts": wall["attempts"],
              "config": config_json(cell.config)}
    os.makedirs(results_dir, exist_ok=True)
    files.write_json(path, result, indent=None)
    return result


def run_cells(cells: list, results_dir: str, trainer: Trainer, progress: bool, tag: str, log,
              batch: BatchTrainer | None = None) -> int:
    """run_cell over `cells` in order, logging each (`[tag] ...`); stops at the first cell a
    signal cut short. Returns that signal (0: every cell finished).

    With `batch`, the unfinished cells of one variant (its seeds) train together as one
    program (`batch(configs, progress)`), the variants one after another in this process."""
    groups = seed_groups(cells, results_dir) if batch else [[c] for c in cells]
    done = 0
    for group in groups:
        names = ", ".join(c.name for c in group)
        log(f"[{tag}] cell{'s' if len(group) > 1 else ''} {done + 1}"
            f"{'-' + str(done + len(group)) if len(group) > 1 else ''}/{len(cells)} {names}")
        if len(group) == 1:
            results = [run_cell(group[0], results_dir, trainer, progress, log=log)]
        else:
            results = run_group(group, results_dir, batch, progress)
        done += len(group)
        for cell, result in zip(group, results):
            if "final" not in result:
                return result["stopped_by_signal"]
            f = result["final"]
            log(f"[{tag}] {cell.name}: <=30cm {f['within_30cm']:.1%} <=20cm {f['within_20cm']:.1%} "
                f"hit {f['hit_rate']:.1%} in {result['wall_s']:.0f} s")
    return 0


def finish(cells: list, out: str, stopped: int, build_report: Callable[[], dict]) -> dict:
    """The summary of a table command after run_cells: the report rebuilt from the finished
    results (none yet after a signal that cut the first cell short: no report, not an error),
    the cells run, the signal that stopped them (0: none) and, after one, the unfinished cells'
    run directories (each resumes from its checkpoint when the same command runs again)."""
    results_dir = os.path.join(out, "results")
    finished = os.path.isdir(results_dir) and any(f.endswith(".json") for f in os.listdir(results_dir))
    summary = build_report() if finished or not stopped else {"outputs": {}}
    unfinished = [c.run_dir for c in cells if not os.path.exists(result_path(results_dir, c))]
    return {**summary, "cells_run": [c.name for c in cells], "stopped_by_signal": stopped,
            **({"unfinished": unfinished} if stopped else {})}


def seed_groups(cells: list, results_dir: str) -> list[list]:
    """The cells in groups that one program can train (training.seeds.program_key): the
    unfinished seeds of each variant together, and of several variants where they differ only in
    their data (the demonstrations ablation's d10/d100/d1000), in first-appearance order;
    finished cells alone (they are only read)."""
    groups: dict = {}
    for c in cells:
        finished = os.path.exists(result_path(results_dir, c))
        key = getattr(c.config, "program_key", None)   # a configuration that says what its programs share
        key = (key() if key else program_key(c.config)) if not finished else (c.variant, c.seed, "done")
        groups.setdefault(key, []).append(c)
    return list(groups.values())


def run_group(group: list, results_dir: str, batch: BatchTrainer, progress: bool) -> list[dict]:
    """The results of the seeds of one variant trained together (written atomically per cell);
    [{'stopped_by_signal': N}, ...] if a signal stopped them (the same call resumes them)."""
    made = [c.run_dir for c in group if not os.path.isdir(c.run_dir)]
    for c in group:
        os.makedirs(c.run_dir, exist_ok=True)
    t0 = time.perf_counter()
    try:
        outs = batch([c.config for c in group], progress)
    except ValueError:
        # Refused before training (a program too big for the device, a bad setting): the run
        # directories this call made stay empty, so they go, and the table holds nothing half.
        for d in made:
            if os.path.isdir(d) and not os.listdir(d):
                os.rmdir(d)
        raise
    per_cell = (time.perf_counter() - t0) / len(group)   # the program's time, shared by its seeds
    results = []
    for cell, out in zip(group, outs):
        wall = add_wall_time(cell.run_dir, per_cell)
        if not out.finished:
            results.append({"stopped_by_signal": out.stopped_by_signal})
            continue
        result = {"variant": cell.variant, "seed": cell.seed, "run_dir": cell.run_dir, "final": out.final,
                  "curve": out.curve, "landings": out.landings, "wall_s": wall["wall_s"],
                  "attempts": wall["attempts"], "config": config_json(cell.config), "seeds_in_program": len(group)}
        os.makedirs(results_dir, exist_ok=True)
        files.write_json(result_path(results_dir, cell), result, indent=None)
        results.append(result)
    return results


def add_wall_time(run_dir: str, seconds: float) -> dict:
    """Wall time summed over the calls that worked on a cell (a resumed cell spans several; a
    call killed outright is not counted)."""
    path = os.path.join(run_dir, "wall_time.json")
    prev = load_result(path) if os.path.exists(path) else {"wall_s": 0.0, "attempts": 0}
    now = {"wall_s": prev["wall_s"] + seconds, "attempts": prev["attempts"] + 1}
    files.write_json(path, now)
    return now


# -- the GoalsEye trainer ---------------------------------------------------------------------
def goalseye(cfg, progress: bool = True) -> Outcome:
    """Train (or resume) cfg.run_dir, a batch of one, then evaluate its final policy."""
    return goalseye_seeds([cfg], progress)[0]


def goalseye_seeds(cfgs: list, progress: bool = True) -> list[Outcome]:
    """Train (or resume) the runs of one program together (training.trainer.Run), then evaluate
    each one's final policy."""
    out = Run(cfgs, training_evaluation, progress=progress).run()
    if not out["finished"]:
        return [Outcome(False, out["stopped_by_signal"], {}, [], {}) for _ in cfgs]
    return [_finished(c.run_dir) for c in cfgs]


def _finished(run_dir: str) -> Outcome:
    final, landings = final_evaluation(run_dir)
    return Outcome(True, 0, final, curve(run_dir), landings)


def curve(run_dir: str) -> list[dict]:
    """The run's evaluations from metrics.jsonl, in order: x values and metrics (eval_ dropped)."""
    return [{"trajectories": r["trajectories"], "updates": r["updates"], "cache_size": r["cache_size"],
             **{k.removeprefix("eval_"): v for k, v in r.items() if k.startswith("eval_")}}
            for r in MetricsLog(run_dir).rows() if any(k.startswith("eval_") for k in r)]


def final_evaluation(run_dir: str) -> tuple[dict, dict]:
    """(metrics, landings) of the newest checkpoint's acting policy on cfg.eval_goals uniform goals
    drawn from FINAL_EVAL_SEED (the whole ensemble playing, as during training)."""
    loaded = load_checkpoint(run_dir)
    cfg = loaded.cfg
    backend = Backend(cfg.world, resolve_backend(cfg.backend))
    metrics, tr = uniform_runs(cfg.world, cfg.policy, lane_of_one(loaded.params), backend,
                               lane_of_one(jax.random.PRNGKey(FINAL_EVAL_SEED)), cfg.eval_goals, cfg.train.members)
    metrics, tr = metrics[0], lane(tr)     # a lane of one
    landings = {"goal": np.asarray(tr.goal, np.float64).round(4).tolist(),
                "landing": np.asarray(tr.landing, np.float64).round(4).tolist(),
                "hit": np.asarray(tr.hit, bool).tolist(), "on_opponent": np.asarray(tr.on_opponent, bool).tolist()}
    return metrics, landings
