"""The imitation loss on held-out demonstrations, a diagnostic of `ttmjx report`: demonstrations
of the run's own source (cfg.demo_source) that never enter its pool (another seed than the
run's, training.pool.load_demos), relabelled with where each ball landed as the pool relabels,
scored with the update's loss (training.loss.policy_loss) on a fixed sample of windows, so two
evaluations of the same parameters give the same number.

A run's evaluation callback gets it from `with_heldout_loss` (one run, or the lanes of a batch:
each lane its own held-out set, from its own seed): metrics `heldout_loss` (the mean over the
members, as the training loss is) and, for an ensemble, `member<i>_heldout_loss`. The
demonstrations are collected at the first evaluation and kept in memory and in the run directory
(RUN/heldout_demos, a dataset of ttmjx.world.record, written atomically), so a resumed run does not
collect them again. A run without demonstrations (GCSL, demos = 0) has none to hold out: no key.
"""
from __future__ import annotations

import functools
import os
import shutil

import jax
import numpy as np

from models.config import PolicyConfig
from training import pool
from training.cache import empty_cache
from training.loss import policy_loss
from training.runconfig import RunConfig
from training.sampler import Batch, sample_subsequences
from ttmjx.tools import demos
from ttmjx.world import files, record
from ttmjx.world.backends import resolve_backend

HELDOUT_DEMOS = 64            # held-out demonstrations per run: a diagnostic, a few % of a run's own
HELDOUT_SEED_OFFSET = 20_000  # the run's own demonstrations are drawn at seed + 10_000 (training.pool)
HELDOUT_WINDOWS = 256         # windows scored per evaluation, ~4 per kept demonstration
HELDOUT_DIR = "heldout_demos"


def heldout_seed(cfg: RunConfig) -> int:
    """The seed the held-out demonstrations of `cfg` are collected with."""
    return cfg.seed + HELDOUT_SEED_OFFSET


def heldout_meta(cfg: RunConfig) -> dict:
    """What identifies a run's held-out set: a cached set that differs in any of it is collected again."""
    return {"source": cfg.demo_source, "source_version": demos.SOURCE_VERSION,
            "distribution": cfg.world.throws.name, "seed": heldout_seed(cfg), "n": HELDOUT_DEMOS,
            "horizon": cfg.world.horizon}


def heldout_sets(cfgs: list[RunConfig]) -> list:
    """Each run's held-out demonstrations ([HELDOUT_DEMOS, T, ...] of cfg.demo_source at
    heldout_seed(cfg); None without demonstrations): read from RUN/heldout_demos, or collected and
    written there, the sets not on disk collected together, a source at a time (demos.collect_lanes: the records of each
    seed's own collection), so a batch of lanes does not collect its sets one after another."""
    out = [cached_demos(os.path.join(c.run_dir, HELDOUT_DIR), heldout_meta(c)) if c.demos else None for c in cfgs]
    todo: dict = {}
    for i, c in enumerate(cfgs):
        if c.demos and out[i] is None:
            todo.setdefault((c.world, c.demo_source, resolve_backend(c.backend)), {}).setdefault(c.run_dir, []).append(i)
    for (world, source, backend), runs in todo.items():
        firsts = [idx[0] for idx in runs.values()]   # padded lanes repeat a run: collected once
        trajs = demos.collect_lanes(world, source, HELDOUT_DEMOS, [heldout_seed(cfgs[i]) for i in firsts], backend)
        for idx, traj in zip(runs.values(), trajs):
            write_demos(os.path.join(cfgs[idx[0]].run_dir, HELDOUT_DIR), traj, cfgs[idx[0]])
            for i in idx:
                out[i] = traj
    return out


def cached_demos(path: str, meta: dict) -> record.Trajectories | None:
    """The held-out set in `path` if it is whole and was collected as `meta` says, else None: a
    cache, which a damaged or stale file only makes collect again."""
    if not os.path.exists(os.path.join(path, "trajectories.npz")):
        return None
    try:
        traj, saved = record.load(path)
    except record.RecordError:
        return None
    return traj if all(saved.get(k) == v for k, v in meta.items()) else None


def write_demos(path: str, traj: record.Trajectories, cfg: RunConfig) -> None:
    """`traj` as the dataset `path`, replacing whatever stale set was there: the stale one is
    removed first and the new one staged, so a kill leaves no set or the whole new one (a missing
    set is collected again)."""
    shutil.rmtree(path, ignore_errors=True)
    meta = {k: v for k, v in heldout_meta(cfg).items() if k not in ("n", "horizon")}    # record.save writes both
    with files.staged_dir(path) as stage:
        record.save(stage, traj, {**meta, "purpose": "held out: never in the run's pool (eval.heldout)"})


def heldout_batch(cfg: RunConfig, traj: record.Trajectories) -> Batch | None:
    """Windows [HELDOUT_WINDOWS, k, S, O] of the demonstrations the pool would keep, relabelled as
    it relabels (training.pool.append_record) and drawn by the update's sampler with a fixed key;
    None if none of them would be kept (no ball hit and landed near the opponent's half)."""
    cache = pool.append_record(empty_cache(traj.size, cfg.world.horizon), traj, cfg, demo=True)
    if int(cache.size) == 0:
        return None
    batch = sample_subsequences(jax.random.PRNGKey(0), cache, cfg.train.window, HELDOUT_WINDOWS,
                                cfg.policy.input_frames, cfg.policy.obs_size)
    return jax.tree.map(np.asarray, batch)


@functools.lru_cache(maxsize=8)
def lane_losses_fn(pcfg: PolicyConfig):
    """jit of (params [L, N, ...], batches [L, W, ...]) -> [L, N] each lane's members' loss on its batch."""
    one = jax.vmap(lambda params, batch: policy_loss(pcfg, params, batch), in_axes=(0, None))    # over members
    return jax.jit(jax.vmap(one))                                                              # over lanes


def lane_losses(pcfg: PolicyConfig, params, batches: list[Batch | None]) -> list[np.ndarray | None]:
    """[N] member losses per lane of params [L, N, ...] on batches[l] (len <= L: the rest are a
    program's padding lanes); None for a lane without a batch."""
    some = next((b for b in batches if b is not None), None)
    if some is None:
        return [None] * len(batches)
    lanes = jax.tree.leaves(params)[0].shape[0]
    filled = [some if b is None else b for b in batches]
    filled += [filled[-1]] * (lanes - len(filled))
    losses = np.asarray(lane_losses_fn(pcfg)(params, jax.tree.map(lambda *x: np.stack(x), *filled)))
    return [None if b is None else losses[i] for i, b in enumerate(batches)]


def loss_metrics(losses: np.ndarray | None) -> dict:
    """{"heldout_loss": mean over the members, "member<i>_heldout_loss": each (an ensemble)} of
    member losses [N]; NaN when nothing held out was kept (losses None)."""
    if losses is None:
        return {"heldout_loss": float("nan")}
    out = {"heldout_loss": float(np.mean(losses))}
    if len(losses) > 1:
        out.update({f"member{i}_heldout_loss": float(v) for i, v in enumerate(losses)})
    return out


class HeldOut:
    """The held-out windows of some runs (the lanes of one program, or one run), made at the
    first call and kept. `metrics(params [L, N, ...])` -> [metrics] per run, {} for a run without
    demonstrations."""

    def __init__(self, cfgs: list[RunConfig]):
        self.cfgs, self.batches = cfgs, None

    def metrics(self, params) -> list[dict]:
        if self.batches is None:
            self.batches = [heldout_batch(c, t) if t is not None else None
                            for c, t in zip(self.cfgs, heldout_sets(self.cfgs))]
        losses = lane_losses(self.cfgs[0].policy, params, self.batches)
        return [loss_metrics(loss) if c.demos else {} for c, loss in zip(self.cfgs, losses)]


def with_heldout_loss(cfgs: list[RunConfig], evaluate):
    """The evaluation of a batch's lanes (params [L, N, ...], backend, keys [L]) -> [metrics] per
    run, plus each run's held-out loss on its own held-out set (cfgs: the batch's runs, in lane order)."""
    if not any(c.demos for c in cfgs):
        return evaluate
    held = HeldOut(list(cfgs))

    def evaluated(params, backend, keys) -> list[dict]:
        return [{**m, **h} for m, h in zip(evaluate(params, backend, keys), held.metrics(params))]
    return evaluated
