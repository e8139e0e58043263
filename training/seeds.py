"""Several seeds of one configuration trained as one program: a batch of runs.

A run is a function of (config, key); S runs that differ only in their seed (or, with the same
schedule, in the demonstrations they start from: `program_key`) stack every array of
their state (weights, optimizer states, moving averages, caches, keys, counters) on a leading
[S] axis, and each compiled piece of training (the practice round, the update loop, the throw
sampler, the evaluation rollout) is the one-run piece vmapped over that axis (training.practice
with `seeds`, Backend.rollout_seeds). So seed k of a batch is the same experiment as seed k run
alone: the same demonstrations, throws, goals, initial weights and random draws
(tests/test_seeds.py compares them).

Each seed keeps its own run directory (config.json, metrics.jsonl, curves, Orbax checkpoints)
written by the ordinary `Run` bookkeeping, so `ttmjx eval`, `ttmjx export` and a resume treat
a seed's directory like any run's. The batch's directory holds them and `seeds.json`:

    RUN/seeds.json        {"seeds": [s0, s1, ...], "run_dirs": ["seed<s0>", ...]}
    RUN/seed<s>/          one run per seed

The batch runs on one device: its seeds are the parallel axis (an ensemble inside each seed is
vmapped as usual).
"""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from training import budget, mesh, runlog
from training.checkpoint import Checkpointed, Counters
from training.practice import Practice, stats_row
from training.runconfig import RunConfig, to_json
from training.trainer import (SEEDS_FILE, NonFiniteError, Run, finite_flags, install_stop_signals, is_eval_iteration,
                              phase, practice_iterations, pretrain_iterations, restore_signals, round_episodes,
                              total_iterations, _now)
from training.update import acting_params
from ttmjx.world import files
from ttmjx.world.backends import Backend, resolve_backend

# evaluate(params [S, ...], backend, keys [S]) -> [metrics per seed]: eval.evaluate.training_evaluation_seeds
EvaluateSeeds = Callable[..., list]

# Fields in which the runs of one batch may differ: they change the runs' data (keys, starting
# pools), not the program that trains them. `demos` and `demo_source` only where every run has
# demonstrations and the same schedule (`program_key`): the demonstrations ablation's arms.
PER_SEED = ("seed", "run_dir")
PER_RUN_DATA = ("demos", "demo_source", "demo_dir")


def seed_configs(cfg: RunConfig, seeds: int) -> list[RunConfig]:
    """The runs of `ttmjx train --seeds N`: seeds cfg.seed .. cfg.seed + N - 1, each in
    cfg.run_dir/seed<s>."""
    if seeds < 1:
        raise ValueError(f"--seeds {seeds}: expected >= 1")
    last = cfg.seed + seeds - 1
    if last > 2 ** 32 - 1:
        raise ValueError(f"--seed {cfg.seed} --seeds {seeds}: the last seed {last} is beyond 2**32 - 1")
    return [dataclasses.replace(cfg, seed=s, run_dir=os.path.join(cfg.run_dir, f"seed{s}"))
            for s in range(cfg.seed, cfg.seed + seeds)]


def program_key(cfg: RunConfig) -> str:
    """What one program must share: the configuration without the per-run fields, and the
    schedule (pretraining chunks, practice rounds). Runs with equal keys can train together."""
    d = {k: v for k, v in to_json(cfg).items() if k not in PER_SEED + PER_RUN_DATA}
    d["has_demos"] = cfg.demos > 0
    d["schedule"] = (pretrain_iterations(cfg), practice_iterations(cfg))
    return json.dumps(d, sort_keys=True)


def check_one_batch(cfgs: list[RunConfig]) -> None:
    """ValueError unless the configurations can be one program: they differ only in seed, run
    directory and (with demonstrations and the same schedule) which demonstrations they start from."""
    if not cfgs:
        raise ValueError("a batch of seeds needs at least one configuration")
    first, key = to_json(cfgs[0]), program_key(cfgs[0])
    for c in cfgs[1:]:
        diff = sorted(k for k, v in to_json(c).items() if k not in PER_SEED and first.get(k) != v)
        if diff and (program_key(c) != key or set(diff) - set(PER_RUN_DATA)):
            raise ValueError(f"runs batched as seeds must share their configuration; {c.run_dir} differs in {diff}"
                             + (" (and in its schedule or in having demonstrations)"
                                if not set(diff) - set(PER_RUN_DATA) else ""))
    dirs = [os.path.abspath(c.run_dir) for c in cfgs]
    if len(set(dirs)) < len(dirs):
        raise ValueError(f"runs batched as seeds need a directory each; got {[c.run_dir for c in cfgs]}")


def stacked(trees: list):
    """Trees with the same structure -> one tree with a leading [S] axis."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def seed_slice(tree, s: int):
    """Seed s of a stacked tree."""
    return jax.tree.map(lambda x: x[s], tree)


class SeedRuns:
    """S runs of one configuration (differing in seed and run directory) trained together.
    `evaluate` (params [S], backend, keys [S]) -> [metrics] is called at the evaluation
    iterations; None skips evaluation. `parent` (optional): the batch's directory, where
    seeds.json is written."""

    def __init__(self, cfgs: list[RunConfig], evaluate: EvaluateSeeds | None = None, progress: bool = True,
                 log=print, parent: str | None = None):
        check_one_batch(cfgs)
        cfg = self.cfg = cfgs[0]
        if cfg.devices not in (None, 1):
            raise ValueError(f"--devices {cfg.devices}: a batch of seeds runs on one device (its seeds are the "
                             f"parallel axis); leave --devices unset or train the seeds one at a time")
        if jax.process_count() > 1:
            raise ValueError("a batch of seeds runs in one process")
        self.seeds, self.evaluate, self.progress, self.log, self.parent = len(cfgs), evaluate, progress, log, parent
        budget.check_fits(cfg, seeds=self.seeds)   # refused with the estimate before anything is compiled
        layout = mesh.single_device()
        self.backend = Backend(cfg.world, resolve_backend(cfg.backend))
        self.runs = [Run(c, None, progress, log, shared=(self.backend, layout)) for c in cfgs]
        self.practice = Practice(cfg.world, cfg.policy, cfg.train, self.backend, cfg.episodes_per_ssp,
                                 cfg.steps_between_ssp, layout, seeds=self.seeds)
        self._stop = 0

    # -- state ----------------------------------------------------------------------------
    def start(self) -> Checkpointed:
        """Every seed fresh or resumed, stacked; seeds a crash left at different iterations are
        taken back to the oldest one's."""
        if self.parent:
            os.makedirs(self.parent, exist_ok=True)
            files.write_json(os.path.join(self.parent, SEEDS_FILE),
                             {"seeds": [r.cfg.seed for r in self.runs],
                              "run_dirs": [os.path.relpath(r.cfg.run_dir, self.parent) for r in self.runs]})
        cks = [r.start() for r in self.runs]
        its = [int(c.counters.iteration) for c in cks]
        low = min(its)
        cks = [c if i == low else r.rewind(low) for r, c, i in zip(self.runs, cks, its)]
        return stacked(cks)

    def save(self, ck: Checkpointed):
        for s, r in enumerate(self.runs):
            r.save(seed_slice(ck, s))

    # -- one iteration ----------------------------------------------------------------------
    def step(self, ck: Checkpointed, it: int) -> tuple[Checkpointed, list[dict]]:
        """Iteration `it` of every seed -> (state, one metrics row per seed)."""
        cfg, t0 = self.cfg, _now()
        practise = phase(cfg, it) == "practice"
        base = np.asarray(ck.key)                                    # [S, 2], as each run's own key
        fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
        throws = self.practice.round_throws(base, it) if practise else None
        new_traj = round_episodes(cfg, it)
        state, cache, loss, stats = self.practice.iteration(ck.state, ck.cache, fold(base, it), throws, new_traj)
        self.check_finite(state, loss, it)
        new_upd = cfg.steps_between_ssp if self.practice.train_loop else 0
        c = ck.counters
        ck = Checkpointed(state, cache, ck.key, Counters(c.iteration + 1, c.trajectories + new_traj, c.updates + new_upd))
        loss, sizes = np.asarray(loss), np.asarray(cache.size)
        rows = [{"iteration": it, "phase": phase(cfg, it), "trajectories": int(ck.counters.trajectories[s]),
                 "updates": int(ck.counters.updates[s]), "cache_size": int(sizes[s]), "loss": float(np.mean(loss[s])),
                 "seconds": _now() - t0, "seeds_in_program": self.seeds} for s in range(self.seeds)]
        if stats is not None:
            host = {k: np.asarray(v) for k, v in stats._asdict().items()}
            for s, row in enumerate(rows):
                row.update(stats_row({k: v[s] for k, v in host.items()}))
        if self.evaluate is not None and is_eval_iteration(cfg, it):
            metrics = self.evaluate(acting_params(state), self.backend, fold(base, 10**6 + it))
            for row, m in zip(rows, metrics):
                row.update({f"eval_{k}": v for k, v in m.items()})
        return ck, rows

    def check_finite(self, state, loss, it: int):
        """NonFiniteError naming the seeds whose loss or parameters are not finite."""
        ok = np.asarray(jax.vmap(finite_flags)(loss, state.params.net, state.ema.net))   # [S, 3]
        bad = [f"seed {r.cfg.seed}" for r, fine in zip(self.runs, ok) if not fine.all()]
        if bad:
            raise NonFiniteError(f"iteration {it}: non-finite loss or parameters in {', '.join(bad)} (learning rate "
                                 f"too high, or non-finite data?); stopped without saving: the last good checkpoints "
                                 f"are iteration {self.runs[0].saved_at}")

    # -- the loop ----------------------------------------------------------------------------
    def run(self, max_iterations: int | None = None) -> dict:
        """Train every seed to the end (or `max_iterations` more iterations) -> a summary with
        each seed's `Run.run`-style result under "runs"."""
        cfg = self.cfg
        ck = self.start()
        n_tot = total_iterations(cfg)
        start = int(ck.counters.iteration[0])
        stop_at = n_tot if max_iterations is None else min(n_tot, start + max_iterations)
        total = sum(c.total_trajectories if c.practice else max(c.demos, 1) for c in (r.cfg for r in self.runs))
        bar = runlog.progress_bar(total, int(np.sum(ck.counters.trajectories)), self.progress)
        last: list[dict] = [{} for _ in self.runs]
        install_stop_signals(self)
        try:
            for it in range(start, stop_at):
                before = int(np.sum(ck.counters.trajectories))
                ck, rows = self.step(ck, it)
                for s, (r, row) in enumerate(zip(self.runs, rows)):
                    r.metrics.write(row)
                    if any(k.startswith("eval_") for k in row):
                        last[s] = row
                if (it + 1) % cfg.checkpoint_every == 0 or it + 1 == stop_at or self._stop:
                    self.save(ck)
                bar.update(int(np.sum(ck.counters.trajectories)) - before)
                bar.set_postfix_str(runlog.postfix(mean_row(rows)))
                if self._stop:
                    self.log(f"[ttmjx] saved the checkpoints of {self.seeds} seeds at iteration {it + 1}")
                    break
        finally:
            bar.close()
            restore_signals(self)
            for r in self.runs:
                r.metrics.close()
        for r in self.runs:
            runlog.plot_curves(r.metrics.path, os.path.join(r.log_dir, "learning_curve.png"))
        it = int(ck.counters.iteration[0])
        runs = [{"run_dir": r.cfg.run_dir, "seed": r.cfg.seed, "iteration": it,
                 "trajectories": int(ck.counters.trajectories[s]),
                 **{k: v for k, v in last[s].items() if k.startswith("eval_")}} for s, r in enumerate(self.runs)]
        return {"run_dir": self.parent or os.path.commonpath([r.cfg.run_dir for r in self.runs]),
                "seeds": [r.cfg.seed for r in self.runs], "iteration": it,
                "trajectories": int(np.max(ck.counters.trajectories)), "finished": it >= n_tot,
                "stopped_by_signal": self._stop, **seed_spread(runs), "runs": runs}


def mean_row(rows: list[dict]) -> dict:
    """The numbers of one iteration's rows averaged over seeds (for the progress bar)."""
    return {k: float(np.mean([r[k] for r in rows])) if isinstance(v, (int, float)) else v
            for k, v in rows[0].items()}


def seed_spread(runs: list[dict]) -> dict:
    """eval_<metric>_mean and _std over the seeds that have the metric."""
    keys = sorted({k for r in runs for k in r if k.startswith("eval_") and isinstance(r[k], (int, float))})
    out = {}
    for k in keys:
        v = np.array([r[k] for r in runs if k in r], np.float64)
        out[f"{k}_mean"], out[f"{k}_std"] = float(v.mean()), float(v.std(ddof=1) if len(v) > 1 else 0.0)
    return out


def seed_run_dirs(path: str) -> list[str] | None:
    """The run directories of the batch of seeds in `path` (None: `path` is not one)."""
    f = os.path.join(path, SEEDS_FILE)
    if not os.path.exists(f):
        return None
    with open(f) as fh:
        meta = json.load(fh)
    return [os.path.join(path, d) for d in meta["run_dirs"]]


def pick_seed(path: str, index: int | None) -> str:
    """The run directory `ttmjx eval/export PATH --seed-index K` means: PATH itself for a single
    run (K must be unset or 0), seed K's for a batch of seeds."""
    dirs = seed_run_dirs(path)
    if dirs is None:
        if index not in (None, 0):
            raise ValueError(f"--seed-index {index}: {path} holds a single run (only index 0)")
        return path
    if index is None:
        raise ValueError(f"{path} holds {len(dirs)} seeds ({', '.join(os.path.basename(d) for d in dirs)}): "
                         f"choose one with --seed-index 0..{len(dirs) - 1}")
    if not 0 <= index < len(dirs):
        raise ValueError(f"--seed-index {index}: {path} holds {len(dirs)} seeds; expected 0..{len(dirs) - 1}")
    return dirs[index]
