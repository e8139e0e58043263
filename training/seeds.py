"""Several runs trained as one program: a batch of lanes.

A run is a function of (config, key); L runs (lanes) that differ only in their seed, in the
settings an ablation varies as data (LANE_KNOBS: practice on or off, learning rate, moving
average, the practice noise's scale, the demonstrations' share of a batch; training.update.Knobs) and, with the same schedule, in the demonstrations they start
from (`program_key`), stack every array of their state (weights, optimizer states, moving
averages, caches, keys, counters) on a leading [L] axis, and each compiled piece of training
(the practice round, the update loop, the throw sampler, the evaluation rollout) is the one-run
piece vmapped over that axis (training.practice with `seeds`, Backend.rollout_seeds). So lane k
of a batch is the same experiment as that run alone: the same demonstrations, throws, goals,
initial weights and random draws (tests/test_seeds.py, tests/test_lanes.py compare them). A lane
that does not practise plays each round and keeps nothing, so it trains as LFP's train-only
rounds do.

The lanes are laid over the devices (training.mesh.lane_layout: a `lane` mesh axis, every
local device unless cfg.devices says fewer): each device computes a block of lanes (jit's
partitioner splits the lane axis; training.practice.over_lanes), nothing passes between lanes,
and a lane count that the devices do not divide is padded with
copies of the last lane that are computed and never written.

Each seed keeps its own run directory (config.json, metrics.jsonl, curves, Orbax checkpoints)
written by the ordinary `Run` bookkeeping, so `ttmjx eval`, `ttmjx export` and a resume treat
a seed's directory like any run's. The batch's directory holds them and `seeds.json`:

    RUN/seeds.json        {"seeds": [s0, s1, ...], "run_dirs": ["seed<s0>", ...]}
    RUN/seed<s>/          one run per seed

An ensemble inside each lane is vmapped as usual.
"""
from __future__ import annotations

import dataclasses
import json
import os
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from training import budget, mesh, pool, runlog
from training.checkpoint import Checkpointed, Counters
from training.practice import Practice, stats_row
from training.runconfig import RunConfig, to_json
from training.trainer import (SEEDS_FILE, NonFiniteError, Run, finite_flags, is_checkpoint_iteration,
                              is_eval_iteration, phase, practice_iterations, pretrain_iterations, round_episodes,
                              total_iterations, _now)
from training.update import acting_params, lane_knobs
from ttmjx.commandline import install_stop_signals, restore_signals
from ttmjx.world import files
from ttmjx.world.backends import Backend, resolve_backend

# evaluate(params [S, ...], backend, keys [S]) -> [metrics per seed]: eval.evaluate.training_evaluation_seeds
EvaluateSeeds = Callable[..., list]

# Fields in which the runs of one batch may differ: they change the runs' data (keys, starting
# pools), not the program that trains them. `demos` and `demo_source` only where every run has
# demonstrations and the same schedule (`program_key`): the demonstrations ablation's arms.
PER_SEED = ("seed", "run_dir", "devices")
PER_RUN_DATA = ("demos", "demo_source", "demo_dir")
# Lanes whose checkpoints are written at once (each save's compression is multi-threaded too).
SAVE_THREADS = 8
# Settings that are data of a lane (dotted config fields): the lanes of one program may differ in them.
LANE_KNOBS = ("practice", "train.learning_rate", "train.ema_decay", "train.action_noise", "train.demo_fraction")


def program_fields(cfg: RunConfig) -> dict:
    """cfg's JSON without the per-lane fields (PER_SEED and LANE_KNOBS)."""
    d = {k: v for k, v in to_json(cfg).items() if k not in PER_SEED}
    for dotted in LANE_KNOBS:
        head, _, rest = dotted.partition(".")
        if rest:
            d[head] = {k: v for k, v in d[head].items() if k != rest}
        else:
            d.pop(head, None)
    return d


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
    d = {k: v for k, v in program_fields(cfg).items() if k not in PER_RUN_DATA}
    d["has_demos"] = cfg.demos > 0
    d["schedule"] = (pretrain_iterations(cfg), practice_iterations(cfg))
    return json.dumps(d, sort_keys=True)


def check_one_batch(cfgs: list[RunConfig]) -> None:
    """ValueError unless the configurations can be one program: they differ only in seed, run
    directory, the lane knobs (LANE_KNOBS) and (with demonstrations and the same schedule) which
    demonstrations they start from."""
    if not cfgs:
        raise ValueError("a batch of seeds needs at least one configuration")
    first, key = program_fields(cfgs[0]), program_key(cfgs[0])
    for c in cfgs[1:]:
        diff = sorted(k for k, v in program_fields(c).items() if first.get(k) != v)
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
    """Seed s of a stacked tree, taken from the device that holds it: a slice of the one shard
    whose block of lanes contains s, an operation on that device alone (slicing the global array
    is a program over every device, and such programs started from several threads at once
    deadlock in their collectives)."""
    return jax.tree.map(lambda x: _lane(x, s), tree)


def _lane(x, s: int):
    shards = getattr(x, "addressable_shards", None)
    if not shards:
        return x[s]
    for sh in shards:
        lo, hi, _ = sh.index[0].indices(x.shape[0])
        if lo <= s < hi:
            return sh.data[s - lo]
    raise ValueError(f"lane {s} is on no local device (lane axis {x.shape[0]})")


class SeedRuns:
    """S runs of one program (differing in seed, run directory and the lane knobs) trained
    together, over the lane layout's devices. `evaluate` (params [L], backend, keys [L]) ->
    [metrics] is called at the evaluation iterations; None skips evaluation. `parent`
    (optional): the batch's directory, where seeds.json is written."""

    def __init__(self, cfgs: list[RunConfig], evaluate: EvaluateSeeds | None = None, progress: bool = True,
                 log=print, parent: str | None = None):
        check_one_batch(cfgs)
        cfg = self.cfg = cfgs[0]
        if jax.process_count() > 1:
            raise ValueError("a batch of seeds runs in one process")
        self.seeds, self.evaluate, self.progress, self.log, self.parent = len(cfgs), evaluate, progress, log, parent
        self.layout = mesh.lane_layout(self.seeds, cfg.devices)
        self.devices = self.layout.mesh.size
        self.lanes = mesh.padded_lanes(self.seeds, self.devices)   # computed lanes, padding included
        # refused with the estimate before anything is compiled: each device holds its block of lanes
        budget.check_fits(cfg, seeds=self.lanes // self.devices, devices=self.devices)
        self.backend = Backend(cfg.world, resolve_backend(cfg.backend))
        # each lane's Run makes its own state on the device of its block, where `assemble` stacks
        # the block, so the lanes are never gathered on one device (a resumed lane is read onto
        # the first device, one at a time, then moved to its block's)
        self.per_device = self.lanes // self.devices
        self.runs = [Run(c, None, progress, log, shared=(self.backend, mesh.one_device(self.device_of(i))))
                     for i, c in enumerate(cfgs)]
        self.cfgs = cfgs + [cfgs[-1]] * (self.lanes - self.seeds)
        self.knobs = lane_knobs([c.train for c in self.cfgs])
        self.practice = Practice(cfg.world, cfg.policy, cfg.train, self.backend, cfg.episodes_per_ssp,
                                 cfg.steps_between_ssp, self.layout, seeds=self.lanes,
                                 lane_noise=any(c.train.action_noise > 0 for c in cfgs))
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
        # the lanes that start afresh collect their demonstrations together, one rollout per chunk
        pool.collect_for_lanes([r.cfg for r in self.runs], self.progress, self.place, self.devices)
        cks = [r.start() for r in self.runs]
        its = [int(c.counters.iteration) for c in cks]
        low = min(its)
        cks = [c if i == low else r.rewind(low) for r, c, i in zip(self.runs, cks, its)]
        return self.assemble(cks)

    def device_of(self, lane: int):
        """The device that computes `lane` (lanes are laid in blocks of `per_device`)."""
        return self.layout.mesh.devices.flat[lane // self.per_device]

    def assemble(self, cks: list[Checkpointed]) -> Checkpointed:
        """The lanes' states, each on its block's device, -> one stacked tree [L, ...] split over
        the lane mesh (padded with copies of the last lane): each block is stacked on its own
        device, so setting up many lanes never gathers them all on one."""
        cks = cks + [cks[-1]] * (self.lanes - len(cks))
        blocks = []
        for d in range(self.devices):
            dev = self.layout.mesh.devices.flat[d]
            block = cks[d * self.per_device:(d + 1) * self.per_device]
            blocks.append(stacked([jax.device_put(c, dev) for c in block]))
        sharding = self.layout.sharding(mesh.LANE)
        return jax.tree.map(lambda *xs: jax.make_array_from_single_device_arrays(
            (self.lanes,) + xs[0].shape[1:], sharding, list(xs)), *blocks)

    def place(self, tree):
        """A stacked tree [L, ...] split over the lane layout's devices, a block of lanes each."""
        return jax.device_put(tree, self.layout.sharding(mesh.LANE))

    def save(self, ck: Checkpointed):
        """Every lane's checkpoint in its own run directory, several at once: Orbax spends most
        of a save compressing the pool on the host (a paper-sim pool is 2 GiB), which threads do
        side by side."""
        with ThreadPoolExecutor(min(self.seeds, SAVE_THREADS)) as ex:
            list(ex.map(lambda s: self.runs[s].save(seed_slice(ck, s)), range(self.seeds)))

    # -- one iteration ----------------------------------------------------------------------
    def step(self, ck: Checkpointed, it: int) -> tuple[Checkpointed, list[dict]]:
        """Iteration `it` of every lane -> (state, one metrics row per real lane). If any lane
        practises, every lane plays the round; the others keep none of it (counted 0)."""
        cfg, t0 = self.cfg, _now()
        practising = [phase(c, it) == "practice" for c in self.cfgs]
        base = np.asarray(ck.key)                                    # [L, 2], as each run's own key
        fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
        throws = self.practice.round_throws(base, it) if any(practising) else None
        new_traj = np.array([round_episodes(c, it) for c in self.cfgs], np.int32)
        state, cache, loss, stats = self.practice.iteration(ck.state, ck.cache, self.place(fold(base, it)), throws,
                                                            new_traj, self.knobs)
        self.check_finite(state, loss, it)
        new_upd = cfg.steps_between_ssp if self.practice.train_loop else 0
        c = ck.counters
        counters = self.place(Counters(c.iteration + 1, c.trajectories + new_traj, c.updates + new_upd))
        ck = Checkpointed(state, cache, ck.key, counters)
        loss, sizes = np.asarray(loss), np.asarray(cache.size)
        trajs, upds = np.asarray(counters.trajectories), np.asarray(counters.updates)
        rows = [{"iteration": it, "phase": phase(self.cfgs[s], it), "trajectories": int(trajs[s]),
                 "updates": int(upds[s]), "cache_size": int(sizes[s]), "loss": float(np.mean(loss[s])),
                 "seconds": _now() - t0, "seeds_in_program": self.seeds} for s in range(self.seeds)]
        if stats is not None:
            host = {k: np.asarray(v) for k, v in stats._asdict().items()}
            for s, row in enumerate(rows):
                if practising[s]:
                    row.update(stats_row({k: v[s] for k, v in host.items()}))
        if self.evaluate is not None and is_eval_iteration(cfg, it):
            metrics = self.evaluate(acting_params(state), self.backend, fold(base, 10**6 + it))[:self.seeds]
            for row, m in zip(rows, metrics):
                row.update({f"eval_{k}": v for k, v in m.items()})
        return ck, rows

    def check_finite(self, state, loss, it: int):
        """NonFiniteError naming the seeds whose loss or parameters are not finite."""
        ok = np.asarray(jax.vmap(finite_flags)(loss, state.params.net, state.ema.net))[:self.seeds]   # [S, 3]
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
                if is_checkpoint_iteration(cfg, it, stop_at) or self._stop:
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
    """The numbers of one iteration's rows averaged over the lanes that have them (for the
    progress bar)."""
    keys = dict.fromkeys(k for r in rows for k in r)   # lanes that do not practise lack its columns
    return {k: float(np.mean([r[k] for r in rows if k in r])) if isinstance(first(rows, k), (int, float))
            else first(rows, k) for k in keys}


def first(rows: list[dict], key: str):
    """The first row's value of `key` among those that have it."""
    return next(r[key] for r in rows if key in r)


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
