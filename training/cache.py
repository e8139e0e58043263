"""The training cache: a fixed-capacity pool of relabeled episodes that lives on the device.

Demonstrations and kept practice episodes go in through `append` (jit-compatible, no host
round trip); every member samples its windows from this one cache. Beyond `capacity` the oldest
episodes are overwritten (FIFO). On several devices every device holds a whole copy, so sampling
never reads another device (training.mesh; docs/SCALING.md says why not split along capacity).
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from training.data import keep_for_training, relabel
from ttmjx.world.config import Table
from ttmjx.world.record import Trajectories


class Cache(NamedTuple):
    obs: jnp.ndarray        # [C, T, 13] relabeled: goal columns = landing point
    ball_vel: jnp.ndarray   # [C, T, 3]
    actions: jnp.ndarray    # [C, T, 8]
    valid: jnp.ndarray      # [C, T] bool, a prefix of each row
    hit_step: jnp.ndarray   # [C] int32
    goal: jnp.ndarray       # [C, 2] relabeled goal
    demo: jnp.ndarray       # [C] bool, the row holds a bootstrap demonstration (robot logs and practice: False)
    size: jnp.ndarray       # [] int32, rows holding episodes: min(count, C)
    count: jnp.ndarray      # [] int32, episodes ever written; the next row is count % C

    @property
    def capacity(self) -> int:
        return int(self.obs.shape[0])

    @property
    def horizon(self) -> int:
        return int(self.obs.shape[1])


def empty_cache(capacity: int, horizon: int) -> Cache:
    """A cache of `capacity` rows of `horizon` control steps, all zeros, size 0."""
    if capacity < 1 or horizon < 1:
        raise ValueError(f"empty_cache: capacity={capacity} and horizon={horizon} must be >= 1")
    z = lambda *s, dt=jnp.float32: jnp.zeros((capacity, *s), dt)  # noqa: E731
    return Cache(z(horizon, 13), z(horizon, 3), z(horizon, 8), z(horizon, dt=bool),
                 z(dt=jnp.int32), z(2), z(dt=bool), jnp.int32(0), jnp.int32(0))


def append(cache: Cache, traj: Trajectories, keep, demo: bool = False) -> Cache:
    """Write the episodes of `traj` [B, T, ...] where keep [B] is set; others are skipped.

    Kept episodes fill rows count % C, count+1 % C, ... in order. If one call keeps more than C
    episodes only the last C are written. Shapes must match the cache (checked at trace time).
    `demo` marks the rows as demonstrations (the sampler's demo_fraction draws from them).
    """
    b = traj.obs.shape[0]
    if tuple(traj.obs.shape[1:]) != tuple(cache.obs.shape[1:]):
        raise ValueError(f"append: traj.obs has shape {tuple(traj.obs.shape)}, expected "
                         f"[B, {cache.horizon}, 13] to match the cache")
    if tuple(keep.shape) != (b,):
        raise ValueError(f"append: keep has shape {tuple(keep.shape)}, expected ({b},)")
    keep = jnp.asarray(keep, bool)
    rank = jnp.cumsum(keep) - 1                        # [B] order among the kept
    n_new = keep.sum(dtype=jnp.int32)
    write = keep & (rank >= n_new - cache.capacity)    # only the last C kept of this call
    row = jnp.where(write, (cache.count + rank) % cache.capacity, cache.capacity)  # C: dropped

    def put(buf, x):
        return buf.at[row].set(jnp.asarray(x, buf.dtype), mode="drop")

    count = cache.count + n_new
    return Cache(put(cache.obs, traj.obs), put(cache.ball_vel, traj.ball_vel),
                 put(cache.actions, traj.actions), put(cache.valid, traj.valid),
                 put(cache.hit_step, traj.hit_step), put(cache.goal, traj.goal), put(cache.demo, jnp.full(b, demo)),
                 jnp.minimum(count, cache.capacity).astype(jnp.int32), count.astype(jnp.int32))


def add_episodes(cache: Cache, traj: Trajectories, table: Table, margin: float, demo: bool = False,
                 counted=None) -> Cache:
    """Relabel `traj` and append the episodes worth training on (hit, landing within margin);
    with `counted` (an int), only among the first `counted` of them (a run's last, partial
    round: the rest were played but are not part of its trajectory budget)."""
    keep = keep_for_training(traj, table, margin)
    if counted is not None:
        keep = keep & (jnp.arange(keep.shape[0]) < counted)
    return append(cache, relabel(traj), keep, demo)
