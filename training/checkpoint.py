"""Checkpoints with Orbax: a run's state (train state, cache, PRNG key, counters) plus its config
as JSON, one numbered step per save, the newest `keep` kept; and the ONE way to open a
checkpoint (`load_checkpoint`), used by resume, evaluation and export.

Restore is exact (bit-for-bit, same dtypes). The structure to restore into is built from the
configuration saved WITH the checkpoint, never guessed from array shapes. Nothing is pickled.
A checkpoint holds whole arrays, not the devices that saved them: `load_checkpoint` restores
onto one device (the template's), and a run places the state on its own mesh (`sharding`), so
a run saved on 4 devices resumes on 1 and the other way round.
"""
from __future__ import annotations

import contextlib
import errno
import io
import json
import logging
import os
import re
import shutil
import sys
import threading
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import orbax.checkpoint as ocp

from models.normalizer import identity_normalizer
from models.policy import PolicyParams
from training.cache import Cache, empty_cache
from training.runconfig import RunConfig, from_json
from training.update import TrainState, acting_params, init_train_state
from ttmjx.world import files

CHECKSUMS = "ttmjx_checksums.json"   # {file: sha256} of a step's files, written after Orbax commits it
FORMAT = 1                           # saved in the config item; 0 (absent): before checksums existed


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
    skipped: tuple = ()       # newer steps skipped because their files failed their checksums

    @property
    def params(self) -> PolicyParams:
        """The acting (moving-average) parameters; leaves [N, ...] over ensemble members."""
        return acting_params(self.ck.state)


def zero_counters(trajectories: int = 0) -> Counters:
    return Counters(jnp.int32(0), jnp.int32(trajectories), jnp.int32(0))


# A checkpoint keeps the pool's filled rows only (rounded up to a block, so that a run's saves
# take few shapes): early in a run the pool is mostly empty, and writing its empty rows was most
# of a save (a paper-sim pool is 2 GiB; 15 lanes' saves took ~40 s on an H200 host).
CACHE_ROW_BLOCK = 4096
ROW_FIELDS = ("obs", "ball_vel", "actions", "valid", "hit_step", "goal", "demo")


def saved_rows(cache: Cache) -> int:
    """Rows of `cache` a checkpoint keeps: its filled rows rounded up to CACHE_ROW_BLOCK."""
    return min(cache.capacity, -(-max(int(cache.size), 1) // CACHE_ROW_BLOCK) * CACHE_ROW_BLOCK)


def first_rows(cache: Cache, rows: int) -> Cache:
    """The cache's first `rows` rows (works on ShapeDtypeStructs too)."""
    cut = lambda x: jax.ShapeDtypeStruct((rows,) + x.shape[1:], x.dtype) if isinstance(x, jax.ShapeDtypeStruct) \
        else x[:rows]  # noqa: E731
    return cache._replace(**{f: cut(getattr(cache, f)) for f in ROW_FIELDS})


def padded_rows(cache: Cache, capacity: int) -> Cache:
    """A cache cut to its first rows, back to `capacity` rows (the rest empty, as never written)."""
    pad = lambda x: jnp.concatenate([x, jnp.zeros((capacity - x.shape[0],) + x.shape[1:], x.dtype)])  # noqa: E731
    return cache._replace(**{f: pad(getattr(cache, f)) for f in ROW_FIELDS})


def template(cfg: RunConfig) -> Checkpointed:
    """Shapes and dtypes of a checkpoint of `cfg` (values unused)."""
    norm = identity_normalizer(cfg.policy.obs_size)
    state = init_train_state(jax.random.PRNGKey(0), cfg.policy, cfg.train, norm)
    return Checkpointed(state, empty_cache(cfg.train.capacity, cfg.world.horizon),
                        jnp.zeros(2, jnp.uint32), zero_counters())


def _is_key(x) -> bool:
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def _savable(tree):
    """Typed PRNG keys -> their uint32 data; every leaf -> a jax array (jax.ShapeDtypeStructs,
    a structure to restore into, stay)."""
    return jax.tree.map(lambda x: x if isinstance(x, jax.ShapeDtypeStruct) else
                        jax.random.key_data(x) if _is_key(x) else jnp.asarray(x), tree)


class _ReadOnlyNotices(logging.Filter):
    """Drops the two warnings Orbax logs whenever a manager is opened read-only, as every restore,
    evaluation and export does: they say what was asked for, and a user's evaluation printed them
    once per checkpoint it read."""
    NOTICES = ("CheckpointManagerOptions.read_only=True", "Given directory is read only")

    def filter(self, record):
        return not str(record.getMessage()).startswith(self.NOTICES)


def _manager(directory: str, keep: int | None = None, read_only: bool = False) -> ocp.CheckpointManager:
    logger, quiet = logging.getLogger("absl"), _ReadOnlyNotices()
    if read_only:
        logger.addFilter(quiet)
    try:
        options = ocp.CheckpointManagerOptions(max_to_keep=keep, create=not read_only, read_only=read_only,
                                               enable_async_checkpointing=False)
        return ocp.CheckpointManager(os.path.abspath(directory), options=options, item_names=("state", "config"))
    finally:
        logger.removeFilter(quiet)


def save(directory: str, step: int, tree, config: dict, keep: int = 3) -> None:
    """Write `tree` and `config` (JSON-ready dict) as checkpoint `step`, then the checksums of its
    files; delete all but the newest `keep`. An existing step is an error."""
    if keep < 1:
        raise ValueError(f"checkpoint.save: keep={keep}, expected >= 1")
    if isinstance(tree, Checkpointed) and saved_rows(tree.cache) < tree.cache.capacity:
        rows = saved_rows(tree.cache)
        tree, config = tree._replace(cache=first_rows(tree.cache, rows)), {**config, "cache_rows": rows}
    with _disk_errors(directory, int(step)):
        with _manager(directory, keep) as mngr:
            mngr.save(int(step), args=ocp.args.Composite(state=ocp.args.StandardSave(_savable(tree)),
                                                          config=ocp.args.JsonSave({**config, "checkpoint_format": FORMAT})))
    step_dir = os.path.join(os.path.abspath(directory), str(int(step)))
    files.write_json(os.path.join(step_dir, CHECKSUMS), files.tree_checksums(step_dir, exclude=(CHECKSUMS,)))


# Errors of the machine while Orbax (tensorstore) writes: a full disk, a file-size limit, a quota.
# Tensorstore reports them as a ValueError whose text holds the OS error code and the file.
DISK_ERRNOS = {errno.ENOSPC: "No space left on device", errno.EFBIG: "File too large",
               errno.EDQUOT: "Disk quota exceeded"}


def disk_error(e: BaseException) -> tuple[int, str | None] | None:
    """(errno, file or None) if `e` (or an exception it chains) is a full disk, a file-size limit
    or a quota; None otherwise."""
    seen = 0
    while e is not None and seen < 10:
        if isinstance(e, OSError) and e.errno in DISK_ERRNOS:
            return e.errno, e.filename
        text = str(e)
        m = re.search(r"os_error_code='(\d+)'", text)
        code = int(m.group(1)) if m else next((n for n, msg in DISK_ERRNOS.items() if msg in text), None)
        if code in DISK_ERRNOS:
            f = re.search(r'Failed writing: "([^"]+)"', text) or re.search(r'local file "([^"]+)"', text)
            return code, f.group(1) if f else None
        e, seen = e.__cause__ or e.__context__, seen + 1
    return None


class _Held(logging.Filter):
    """Holds the records of a logger (Orbax logs a failed write's traceback once per thread)."""
    def __init__(self):
        super().__init__()
        self.records = []

    def filter(self, record):
        self.records.append(record)
        return False


class MainThreadStderr:
    """stderr after a save failed for want of space: the failed save's threads go on finishing
    after the OSError (tensorstore's callbacks onto Orbax's closed event loop) and print
    tracebacks behind the command's one line; only the main thread's writes pass."""
    def __init__(self, stream):
        self.stream = stream

    def write(self, text: str) -> int:
        if threading.current_thread() is threading.main_thread():
            return self.stream.write(text)
        return len(text)

    def __getattr__(self, name):
        return getattr(self.stream, name)


# Output held while saves run. The lanes of a batch save from several threads at once
# (training.seeds), so the swap of sys.stderr is shared: the first save in installs it, the last
# one out restores it (a save that restored it while another still held it would leave stderr
# pointing at a buffer nobody reads).
_HOLD_LOCK = threading.Lock()
_hold: dict = {"depth": 0}


@contextlib.contextmanager
def _held_output():
    """Orbax's logged records and what its threads print, held until the last overlapping save
    ends, then shown unless a save failed for want of space (then stderr passes only the main
    thread's writes: MainThreadStderr). Yields the shared state (set "full" on such a failure)."""
    logger = logging.getLogger("absl")
    with _HOLD_LOCK:
        if _hold["depth"] == 0:
            _hold.update(real=sys.stderr, err=io.StringIO(), held=_Held(), full=False)
            logger.addFilter(_hold["held"])
            sys.stderr = _hold["err"]
        _hold["depth"] += 1
    try:
        yield _hold
    finally:
        with _HOLD_LOCK:
            _hold["depth"] -= 1
            if _hold["depth"] == 0:
                real, held = _hold["real"], _hold["held"]
                logger.removeFilter(held)
                sys.stderr = MainThreadStderr(real) if _hold["full"] else real
                if not _hold["full"]:
                    real.write(_hold["err"].getvalue())
                    for r in held.records:
                        logger.handle(r)


@contextlib.contextmanager
def _disk_errors(directory: str, step: int):
    """A full disk (or a file-size limit, a quota) while Orbax saves step `step` becomes one
    OSError naming the file and the checkpoint: its partial step directory is removed, the
    newest complete checkpoint stays. Orbax's output is held while it saves (_held_output)."""
    with _held_output() as hold:
        try:
            yield
        except Exception as e:   # noqa: BLE001 (tensorstore's errors are ValueErrors)
            full = disk_error(e)
            if full is None:
                raise
            hold["full"] = True
            code, path = full
            tmp = [os.path.join(os.path.abspath(directory), n) for n in os.listdir(directory)
                   if n.startswith(f"{step}.") and n.endswith("-tmp")] if os.path.isdir(directory) else []
            for t in tmp:
                shutil.rmtree(t, ignore_errors=True)
            raise OSError(code, f"{DISK_ERRNOS[code]} while saving checkpoint {step} in {os.path.abspath(directory)} "
                                f"(not saved; the newest complete checkpoint stays: free space and run the same "
                                f"command)", path or os.path.abspath(directory)) from None


def discard(directory: str, damaged) -> None:
    """Delete the damaged checkpoints a resume skipped (the run redoes them under the same
    numbers)."""
    import shutil
    for s in damaged:
        shutil.rmtree(os.path.join(os.path.abspath(directory), str(s)))


def damage(directory: str, step: int) -> str | None:
    """Why checkpoint `step` cannot be trusted ('file: reason'), or None if its files match the
    checksums written after it was saved."""
    step_dir = os.path.join(os.path.abspath(directory), str(int(step)))
    path = os.path.join(step_dir, CHECKSUMS)
    if not os.path.exists(path):
        return f"{path}: missing (the save did not finish)"
    try:
        expected = json.load(open(path))
    except (OSError, ValueError) as e:
        return f"{path}: unreadable ({e})"
    return files.first_mismatch(step_dir, expected)


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
    dtypes (its values are unused; jax.eval_shape's ShapeDtypeStructs will do, for trees without
    typed keys); leaves come back as jax arrays, typed keys as typed keys."""
    step = _existing_step(directory, step)
    # A structure without placement restores onto this process's first device (not the devices
    # that saved it, which another process may not have).
    here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    abstract = jax.tree.map(lambda x: (x if x.sharding is not None else jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=here))
                            if isinstance(x, jax.ShapeDtypeStruct) else ocp.utils.to_shape_dtype_struct(x),
                            _savable(like))
    with _manager(directory, read_only=True) as mngr:
        out = mngr.restore(step, args=ocp.args.Composite(state=ocp.args.StandardRestore(abstract),
                                                         config=ocp.args.JsonRestore()))
    tree = jax.tree.map(lambda r, t: jax.random.wrap_key_data(r, impl=jax.random.key_impl(t))
                        if _is_key(t) else r, out.state, like)
    return tree, {k: v for k, v in out.config.items() if k != "checkpoint_format"}


def checkpoints_dir(path: str) -> str:
    """The checkpoints directory of `path`: a run directory or its checkpoints/ directory."""
    path = os.path.normpath(path)
    ckpt = path if os.path.basename(path) == "checkpoints" else os.path.join(path, "checkpoints")
    if not os.path.isdir(ckpt):
        kind = "does not exist" if not os.path.exists(path) else "is neither a run directory nor a checkpoints directory"
        raise FileNotFoundError(f"{path!r} {kind} (no {ckpt})")
    return ckpt


DAMAGED = " is damaged: "


class DamagedCheckpoint(ValueError):
    """A checkpoint whose files fail their checksums, or whose save did not finish."""


class NoIntactCheckpoint(ValueError):
    """Every checkpoint failed its checksums (interrupted or corrupted saves); `skipped`: their steps."""

    def __init__(self, msg: str, skipped: tuple):
        super().__init__(msg)
        self.skipped = skipped


def _warn(msg: str) -> None:
    print(msg, file=sys.stderr)


def load_checkpoint(path: str, step: int | None = None, warn: Callable[[str], None] = _warn) -> Loaded:
    """Open checkpoint `step` of a run directory or checkpoints directory: read the configuration
    saved with it, build the structure from that configuration, restore.

    Without `step`, the newest INTACT checkpoint: a damaged newer one is skipped, saying so
    through `warn`. A checkpoint that cannot be read raises ValueError naming the file and the
    reason (FileNotFoundError when there is none)."""
    ckpt = checkpoints_dir(path)
    if step is not None:
        return _load_step(ckpt, _existing_step(ckpt, step))
    saved = steps(ckpt)
    if not saved:
        raise FileNotFoundError(f"no checkpoint in {ckpt!r}")
    problems, skipped = [], []
    for s in reversed(saved):
        try:
            loaded = _load_step(ckpt, s)
        except DamagedCheckpoint as e:      # any other failure stops: it is not the files' fault
            problems.append(str(e))
            skipped.append(s)
            continue
        if problems:
            warn(f"[ttmjx] skipped damaged checkpoint(s): {'; '.join(problems)}; using checkpoint {s}")
        return loaded._replace(skipped=tuple(skipped))
    raise NoIntactCheckpoint(f"no intact checkpoint in {ckpt}: {'; '.join(problems)}", skipped=tuple(skipped))


def _load_step(ckpt: str, step: int) -> Loaded:
    where = os.path.join(ckpt, str(step))
    has_sums = os.path.exists(os.path.join(where, CHECKSUMS))
    bad = damage(ckpt, step) if has_sums else None    # hashes every file once
    if bad:
        raise DamagedCheckpoint(f"checkpoint {step}{DAMAGED}{bad}")
    try:
        saved = restore_config(ckpt, step)
    except Exception as e:  # orbax raises several types for a missing or corrupt JSON item
        raise ValueError(f"{where}: cannot read the saved configuration ({type(e).__name__}: {e})") from e
    # Written by a version with checksums but without them: the save did not finish. Checkpoints
    # from before checksums existed (no checkpoint_format) are read unchecked.
    if not has_sums and saved.get("checkpoint_format", 0) >= 1:
        raise DamagedCheckpoint(f"checkpoint {step}{DAMAGED}{os.path.join(where, CHECKSUMS)}: missing "
                                f"(the save did not finish)")
    try:
        cfg = from_json(saved)
    except (TypeError, ValueError, KeyError) as e:
        raise ValueError(f"{where}: the saved configuration is not a RunConfig this version reads ({e})") from e
    rows = saved.get("cache_rows")   # absent: the whole pool was saved
    try:
        like = jax.eval_shape(lambda: template(cfg))   # shapes only: no pool or weights allocated
        ck, _ = restore(ckpt, like if rows is None else like._replace(cache=first_rows(like.cache, rows)), step)
        if rows is not None:
            ck = ck._replace(cache=padded_rows(ck.cache, cfg.train.capacity))
    except Exception as e:
        raise ValueError(f"{where}: cannot restore the arrays for the saved configuration "
                         f"({type(e).__name__}: {e})") from e
    return Loaded(cfg, ck, saved, step, ckpt)
