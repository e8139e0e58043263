"""Checkpoints with Orbax: any pytree of arrays (train state, cache, PRNG key, counters) plus the
run's config as JSON, one numbered step per save, the newest `keep` kept.

Restore is exact (bit-for-bit, same dtypes) and needs a template pytree of the same structure,
e.g. a freshly initialized state built from `restore_config`. Nothing is pickled.
"""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _savable(tree):
    """Typed PRNG keys -> their uint32 data; every leaf -> a jax array."""
    return jax.tree.map(lambda x: jax.random.key_data(x) if _is_key(x) else jnp.asarray(x), tree)


def _manager(directory: str, keep: int | None = None, read_only: bool = False) -> ocp.CheckpointManager:
    options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=not read_only, read_only=read_only,
                                           enable_async_checkpointing=False)
    return ocp.CheckpointManager(os.path.abspath(directory), options=options,
                                 item_names=("state", "config"))


def save(directory: str, step: int, tree, config: dict, keep: int = 3) -> None:
    """Write `tree` and `config` (JSON-ready dict) as checkpoint `step`; delete all but the
    newest `keep`. An existing step is an error."""
    if keep < 1:
        raise ValueError(f"checkpoint.save: keep={keep}, expected >= 1")
    with _manager(directory, keep) as mngr:
        mngr.save(int(step), args=ocp.args.Composite(state=ocp.args.StandardSave(_savable(tree)),
                                                      config=ocp.args.JsonSave(config)))


def steps(directory: str) -> list[int]:
    """Saved steps, oldest first ([] if none or no directory)."""
    if not os.path.isdir(directory):
        return []
    with _manager(directory, read_only=True) as mngr:
        return sorted(mngr.all_steps())


def _existing_step(directory: str, step: int | None) -> int:
    saved = steps(directory)
    if not saved:
        raise FileNotFoundError(f"no checkpoint in {directory!r}")
    if step is None:
        return saved[-1]
    if step not in saved:
        raise FileNotFoundError(f"no checkpoint step {step} in {directory!r}; saved steps: {saved}")
    return step


def restore_config(directory: str, step: int | None = None) -> dict:
    """The config dict saved with `step` (default: the newest)."""
    step = _existing_step(directory, step)
    with _manager(directory, read_only=True) as mngr:
        return mngr.restore(step, args=ocp.args.Composite(config=ocp.args.JsonRestore())).config


def restore(directory: str, template, step: int | None = None):
    """(tree, config) of `step` (default: the newest). `template` gives the structure, shapes and
    dtypes (its values are unused); leaves come back as jax arrays, typed keys as typed keys."""
    step = _existing_step(directory, step)
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _savable(template))
    with _manager(directory, read_only=True) as mngr:
        out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                         config=ocp.args.JsonRestore()))
    tree = jax.tree.map(lambda r, t: jax.random.wrap_key_data(r, impl=jax.random.key_impl(t))
                        if _is_key(t) else r, out.state, template)
    return tree, out.config
