"""The outer loop of an RL cell whose whole state lives outside the trainer's call (ES: es.py, PPO:
ppo.py): epochs until the budget, the learning curve's policies where brax's loop hands them
out, and an Orbax checkpoint (training/checkpoint.py: checksums, a full disk as one line) of the
state and the curve so far under RUN/<method>_state/, so that a stopped cell resumes where it
stopped and ends bit-for-bit where the uninterrupted cell ends."""
from __future__ import annotations

import dataclasses
import functools
import os
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from training import checkpoint


# The vmapped axis of a seeds-together program (over_seeds).
SEED_AXIS = "seeds"


def any_seed(pred):
    """pred (a bool [], one per seed under the seeds' vmap) -> whether it holds for some seed,
    unbatched. A lax.cond whose predicate is batched by vmap becomes a select that runs BOTH
    branches at every call (here a throw solve and a reset of every environment at every step);
    with this predicate the branch runs only when some seed needs it, and the branch itself
    must keep each seed's state unchanged where its own predicate is False. Outside the seeds'
    vmap: pred itself."""
    try:
        return jax.lax.pmax(pred, SEED_AXIS)
    except NameError:   # no seeds axis is bound
        return pred


def seeds_queue(replay_buffers):
    """brax 0.14.2's UniformSamplingQueue (SAC's and QT-Opt's replay buffer) whose insert rolls
    the buffer under a predicate shared by the seeds (any_seed): brax's lax.cond on the insert
    position would become a select under the seeds' vmap, rolling every seed's whole buffer at
    every step. A seed whose
    roll is 0 keeps its data as it is, so each seed inserts exactly as brax's queue does."""

    class SeedsQueue(replay_buffers.UniformSamplingQueue):
        def insert_internal(self, buffer_state, samples):
            if buffer_state.data.shape != self._data_shape:
                raise ValueError(f"replay buffer data shape {buffer_state.data.shape}; expected {self._data_shape}")
            update = self._flatten_fn(samples)
            data, position = buffer_state.data, buffer_state.insert_position
            roll = jnp.minimum(0, len(data) - position - len(update))
            data = jax.lax.cond(any_seed(roll != 0), lambda: jnp.roll(data, roll, axis=0), lambda: data)
            position = position + roll
            data = jax.lax.dynamic_update_slice_in_dim(data, update, position, axis=0)
            return buffer_state.replace(data=data, insert_position=(position + len(update)) % (len(data) + 1),
                                        sample_position=jnp.maximum(0, buffer_state.sample_position + roll))
    return SeedsQueue


@functools.lru_cache(maxsize=16)
def over_seeds(fn: Callable) -> Callable:
    """fn on one seed's state -> jitted fn on the seeds' states stacked on a leading axis. One per
    fn (the methods' parts are cached per configuration), so that a later call of the same seeds
    (a resumed group) finds its program compiled."""
    return jax.jit(jax.vmap(fn, axis_name=SEED_AXIS))


@dataclasses.dataclass(frozen=True)
class Loop:
    """One method's epoch and how to read its state."""
    epoch: Callable[[Any], tuple[Any, dict]]   # state -> (state, metrics), jitted
    steps: Callable[[Any], int]                # environment steps run so far
    acting: Callable[[Any], tuple[Any, Any]]   # state -> (normalizer, policy params): a curve point
    unit: int                                  # environment steps per epoch
    program: Callable | None = None            # seeds stacked: the jitted epoch whose memory bounds the seeds


@dataclasses.dataclass(frozen=True)
class Schedule:
    """A method's loop and where brax hands its policy out."""
    loop: Loop
    thresholds: list              # env steps: a curve point after the first epoch reaching each
    point_at_zero: bool           # a curve point before training
    checkpoint_every: int = 1     # epochs between checkpoints (and at every point)


def seedless(cfg):
    """A baseline configuration without its seed and run directory: what a method's compiled
    epoch depends on (its cache key), and what seeds trained together must share."""
    return dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, seed=0, run_dir=""))


def first_int(steps, seeds: bool) -> int:
    """A step counter (int32 or brax's UInt64) as an int; of seed 0 if `seeds` (stacked)."""
    return int(jax.tree.map(lambda x: x[0], steps) if seeds else steps)


def state_dir(run_dir: str, method: str) -> str:
    return os.path.join(run_dir, f"{method}_state")


def _tree(state, points: list) -> dict:
    return {"state": state, "points": {str(i): {"steps": jnp.int32(s), "normalizer": n, "policy": p}
                                       for i, (s, n, p) in enumerate(points)}}


def save(directory: str, step: int, state, points: list, cfg_json: dict) -> None:
    """The state and the curve's (steps, normalizer, policy) so far as checkpoint `step`."""
    checkpoint.save(directory, step, _tree(state, points), {**cfg_json, "curve_points": len(points)}, keep=2)


def good_steps(directory: str) -> list[int]:
    """Saved steps whose files match their checksums, oldest first; damaged ones are removed
    (the run redoes them)."""
    saved = checkpoint.steps(directory)
    damaged = [s for s in saved if checkpoint.damage(directory, s)]
    if damaged:
        checkpoint.discard(directory, damaged)
    return [s for s in saved if s not in damaged]


def resume(directory: str, like, like_point, cfg_json: dict, step: int | None = None) -> tuple[Any, list] | None:
    """(state, points) of checkpoint `step` (default: the newest whose files match their
    checksums), or None if there is none. `like` and `like_point`: the structure of the state
    and of one point (jax.ShapeDtypeStructs will do). ValueError if it was saved with another
    configuration than `cfg_json`."""
    good = good_steps(directory)
    if not good:
        return None
    step = good[-1] if step is None else step
    saved_cfg = checkpoint.restore_config(directory, step)
    n = saved_cfg.pop("curve_points")
    saved_cfg.pop("checkpoint_format", None)
    if saved_cfg != cfg_json:
        diff = sorted(k for k in set(saved_cfg) | set(cfg_json) if saved_cfg.get(k) != cfg_json.get(k))
        raise ValueError(f"{directory} holds a state of another configuration (differs in {', '.join(diff)}); "
                         f"run with the same settings to resume it, or another --out")
    tree, _ = checkpoint.restore(directory, _tree(like, [(0, *like_point)] * n), step)
    tree = uncommitted(tree)
    points = [(int(tree["points"][str(i)]["steps"]), tree["points"][str(i)]["normalizer"],
               tree["points"][str(i)]["policy"]) for i in range(n)]
    return tree["state"], points


def resume_seeds(directories: list[str], like, like_point, cfg_jsons: list[dict]) -> tuple[list, list] | None:
    """([state per seed], [points per seed]) of the newest step every seed's directory holds (a
    stop between two seeds' saves leaves some one epoch ahead; two steps are kept), or None if
    none holds any. ValueError if some do and no step is common to all."""
    held = [set(good_steps(d)) for d in directories]
    if not any(held):
        return None
    common = set.intersection(*held)
    if not common:
        raise ValueError(f"the seeds' states are at different steps ({', '.join(f'{d}: {sorted(h)}' for d, h in zip(directories, held))}); "
                         f"resume them one by one (--seed S --seeds 1) or delete their *_state directories")
    found = [resume(d, like, like_point, c, max(common)) for d, c in zip(directories, cfg_jsons)]
    return [f[0] for f in found], [f[1] for f in found]


def run(sched: Schedule, directory: str, cfg_json: dict, fresh: Callable[[], Any], num_timesteps: int,
        point, progress=None, timing: dict | None = None):
    """Epochs of sched.loop from the newest checkpoint in `directory` (or from fresh()) until
    num_timesteps environment steps, unbatched (as brax runs one seed): run_seeds of one seed.
    point(steps, normalizer, policy). Returns the final state."""
    return run_seeds(sched, [directory], [cfg_json], [fresh], num_timesteps, lambda _, *a: point(*a), progress,
                     timing, stacked=False)


def uncommitted(tree):
    """tree with every leaf an array placed as a freshly computed one is (not committed to a
    device). Orbax restores committed arrays, and jit keys its compiled programs on that too:
    without this a resumed state compiles the epoch again in a process that has compiled it for a
    fresh state (a group of seeds retried in halves, a test), and misses JAX's persistent cache.
    The states hold brax's raw uint32 keys, no typed keys. A host copy: done once per resume."""
    return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)


def strongly_typed(tree):
    """tree with every leaf a strongly typed array: a fresh state's Python floats are weakly
    typed, the epoch's outputs are not, so without this the epoch compiles twice (once for the
    fresh state, once for its own output), as a restored state's epoch does not."""
    return jax.tree.map(lambda x: jax.lax.convert_element_type(x, jnp.result_type(x)), tree)


def run_seeds(sched: Schedule, directories: list[str], cfg_jsons: list[dict], fresh: list[Callable[[], Any]],
              num_timesteps: int, point, progress=None, timing: dict | None = None, stacked: bool = True):
    """Epochs of sched.loop from the newest checkpoint every seed's directory holds (or from
    fresh()) until num_timesteps environment steps. With `stacked`, the seeds train as one
    program: sched.loop works on their states stacked on a leading axis (its epoch vmapped;
    steps read from seed 0: every seed runs the same schedule), each seed's slice checkpointed
    in its own directory; without, one seed's state as it is.

    point(i, steps, normalizer, policy) for seed i at 0 (point_at_zero) and after the first
    epoch that reaches each of the thresholds (brax's next_eval_step: one point per epoch at
    most), replayed from the checkpoint for the points before it. A checkpoint at 0, at every
    point, every `checkpoint_every` epochs and at the end. progress(steps, metrics) after every
    epoch (brax's training/sps, training/walltime and the epoch's metrics, means over seeds);
    timing['epochs'] gets the same. Returns the final (stacked) state."""
    loop, thresholds, point_at_zero, checkpoint_every = (sched.loop, sched.thresholds, sched.point_at_zero,
                                                         sched.checkpoint_every)
    timing = {} if timing is None else timing
    n = len(directories)
    if stacked:
        stack, seed = (lambda xs: jax.tree.map(lambda *x: jnp.stack(x), *xs)), (lambda t, i: jax.tree.map(lambda x: x[i], t))
    else:
        stack, seed = (lambda xs: xs[0]), (lambda t, i: t)
    like = jax.eval_shape(fresh[0])
    found = resume_seeds(directories, like, jax.eval_shape(loop.acting, like), cfg_jsons)
    states, points = found if found else ([strongly_typed(f()) for f in fresh], [[] for _ in range(n)])
    state = stack(states)

    def save_all(steps):
        for i in range(n):
            save(directories[i], steps, seed(state, i), points[i], cfg_jsons[i])

    def add_point(steps):
        normalizer, policy = loop.acting(state)
        for i in range(n):
            points[i].append((steps, seed(normalizer, i), seed(policy, i)))
            point(i, steps, *points[i][-1][1:])

    for i in range(n):
        for s, nm, p in points[i]:
            point(i, s, nm, p)
    if not found:
        if point_at_zero:
            add_point(0)
        save_all(0)
    evaluated = len(points[0]) - point_at_zero     # thresholds already passed
    walltime, epochs = 0.0, 0
    while loop.steps(state) < num_timesteps:
        t = time.perf_counter()
        state, metrics = loop.epoch(state)
        metrics = jax.device_get(metrics)
        dt = time.perf_counter() - t
        walltime, epochs, steps = walltime + dt, epochs + 1, loop.steps(state)
        row = {"training/sps": n * loop.unit / dt, "training/walltime": walltime,
               **{f"training/{k}": float(jnp.mean(v)) for k, v in metrics.items()}}
        timing.setdefault("epochs", []).append({"env_steps": steps, "sps": row["training/sps"], "walltime": walltime})
        if progress is not None:
            progress(steps, row)
        due = evaluated < len(thresholds) and steps >= thresholds[evaluated]
        if due:
            evaluated += 1
            add_point(steps)
        if due or epochs % checkpoint_every == 0 or steps >= num_timesteps:
            save_all(steps)
    return state
