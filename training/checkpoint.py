"""Checkpoints with Orbax: a run's state (train state, cache, PRNG key, counters) plus its config
as JSON, one numbered step per save, the newest `keep` kept; and the ONE way to open a
checkpoint (`load_checkpoint`), used by resume, evaluation and export.

Restore is exact (bit-for-bit, same dtypes). The structure to restore into is built from the
configuration saved WITH the checkpoint, never guessed from array shapes. Nothing is pickled.
"""
from __future__ import annotations

import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from models.normalizer import identity_normalizer
from models.policy import PolicyParams
from training.cache import Cache, empty_cache
from training.runconfig import RunConfig, from_json
from training.update import TrainState, acting_params, init_train_state


class Counters(NamedTuple):
    iteration: jax.Array      # [] int32 iterations finished (pretraining chunks + practice rounds)
    trajectories: jax.Array   # [] int32 demonstrations + practice episodes seen
    updates: jax.Array        # [] int32 optimizer steps


class Checkpointed(NamedTuple):
    """Everything a run needs to continue exactly."""
    state: TrainState
    cache: Cache
    key: jax.Array            # [2] uint32 the run's base key
    counters: Counters


class Loaded(NamedTuple):
    """A checkpoint opened with the configuration saved beside it."""
    cfg: RunConfig
    ck: Checkpointed
    meta: dict                # the saved config dict, with run bookkeeping (absorbed_data)
    step: int
    directory: str            # the checkpoints directory

    @property
    def params(self) -> PolicyParams:
        """The acting (moving-average) parameters; leaves [N, ...] over ensemble members."""
        return acting_params(self.ck.state)


def zero_counters(trajectories: int = 0) -> Counters:
    return Counters(jnp.int32(0), jnp.int32(trajectories), jnp.int32(0))


def template(cfg: RunConfig) -> Checkpointed:
    """Shapes and dtypes of a checkpoint of `cfg` (values unused)."""
    norm = identity_normalizer(cfg.policy.obs_size)
    state = init_train_state(jax.random.PRNGKey(0), cfg.policy, cfg.train, norm)
    return Checkpointed(state, empty_cache(cfg.train.capacity, cfg.world.horizon),
                        jnp.zeros(2, jnp.uint32), zero_counters())


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


def restore(directory: str, like, step: int | None = None):
    """(tree, config) of `step` (default: the newest). `like` gives the structure, shapes and
    dtypes (its values are unused); leaves come back as jax arrays, typed keys as typed keys."""
    step = _existing_step(directory, step)
    abstract = jax.tree.map(ocp.utils.to_shape_dtype_struct, _savable(like))
    with _manager(directory, read_only=True) as mngr:
        out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                         config=ocp.args.JsonRestore()))
    tree = jax.tree.map(lambda r, t: jax.random.wrap_key_data(r, impl=jax.random.key_impl(t))
                        if _is_key(t) else r, out.state, like)
    return tree, out.config


def checkpoints_dir(path: str) -> str:
    """The checkpoints directory of `path`: a run directory or its checkpoints/ directory."""
    path = os.path.normpath(path)
    ckpt = path if os.path.basename(path) == "checkpoints" else os.path.join(path, "checkpoints")
    if not os.path.isdir(ckpt):
        kind = "does not exist" if not os.path.exists(path) else "is neither a run directory nor a checkpoints directory"
        raise FileNotFoundError(f"{path!r} {kind} (no {ckpt})")
    return ckpt


def load_checkpoint(path: str, step: int | None = None) -> Loaded:
    """Open checkpoint `step` (default: the newest) of a run directory or checkpoints directory:
    read the configuration saved with it, build the structure from that configuration, restore.
    A checkpoint that cannot be read raises ValueError naming the file and the reason."""
    ckpt = checkpoints_dir(path)
    step = _existing_step(ckpt, step)
    where = os.path.join(ckpt, str(step))
    try:
        saved = restore_config(ckpt, step)
    except Exception as e:  # orbax raises several types for a missing or corrupt JSON item
        raise ValueError(f"{where}: cannot read the saved configuration ({type(e).__name__}: {e})") from e
    try:
        cfg = from_json(saved)
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"{where}: the saved configuration is not a RunConfig this version reads ({e})") from e
    try:
        ck, _ = restore(ckpt, template(cfg), step)
    except Exception as e:
        raise ValueError(f"{where}: cannot restore the arrays for the saved configuration "
                         f"({type(e).__name__}: {e})") from e
    return Loaded(cfg, ck, saved, step, ckpt)
