"""A batch of runs as one program's lanes: which configurations can share a program, the seeds
of `ttmjx train --seeds N`, and the helpers of the lane axis (stacking, one lane's slice, the
spread over seeds). The loop that trains the lanes is training.trainer.Run.

A batch of seeds lives in one directory, each seed in its own run directory:

    RUN/seeds.json        {"seeds": [s0, s1, ...], "run_dirs": ["seed<s0>", ...]}
    RUN/seed<s>/          one run per seed
"""
from __future__ import annotations

import dataclasses
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from training.rundir import SEEDS_FILE
from training.runconfig import RunConfig, to_json
from training.schedule import practice_iterations, pretrain_iterations

# Fields in which the runs of one batch may differ: they change the runs' data (keys, starting
# pools), not the program that trains them. `demos` and `demo_source` only where every run has
# demonstrations and the same schedule (`program_key`): the demonstrations ablation's arms.
PER_SEED = ("seed", "run_dir", "devices")
PER_RUN_DATA = ("demos", "demo_source", "demo_dir")
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
