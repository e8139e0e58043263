"""Training windows: sub-sequences of k steps that always contain the hit."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ttmjx.world import observation
from training.cache import Cache


class Batch(NamedTuple):
    frames: jnp.ndarray     # [B, k, S, O] raw network inputs (S frames per step, oldest first)
    actions: jnp.ndarray    # [B, k, 8] commanded joint targets
    mask: jnp.ndarray       # [B, k] bool, the step is a valid step of its episode
    episode: jnp.ndarray    # [B] int32 cache row
    start: jnp.ndarray      # [B] int32 first step of the window


def window_starts(key, length, hit_step, k: int):
    """[B] int32 uniform start s with s <= hit < s + k, the window inside the episode if it fits.

    length [B] valid steps per episode, hit_step [B] (clipped into [0, length-1]). Episodes
    shorter than k start at 0 and are padded past their end.
    """
    hit = jnp.clip(hit_step, 0, jnp.maximum(length - 1, 0))
    lo = jnp.maximum(hit - k + 1, 0)
    hi = jnp.maximum(jnp.minimum(hit, length - k), lo)   # inclusive
    return jax.random.randint(key, hit.shape, lo, hi + 1).astype(jnp.int32)


def nth_true(mask, n):
    """[B] int32 index of the n-th (0-based) True entry of mask [C], for n [B] < mask.sum()."""
    return jnp.searchsorted(jnp.cumsum(mask), n + 1, side="left").astype(jnp.int32)


def sample_episodes(key, cache: Cache, batch_size: int, demo_fraction: float = 0.0):
    """[B] int32 cache rows to train on (jit-compatible).

    demo_fraction = 0: uniform over the cache's `size` rows (the paper). demo_fraction = f > 0:
    each row is a demonstration with probability max(f, share of demonstrations in the cache),
    uniform within its group, so practice adds to the pool without drowning the demonstrations
    (practice episodes are the policy's own, less precise strokes). Falls back to uniform while
    either group is empty.
    """
    k_all, k_grp, k_idx = jax.random.split(key, 3)
    size = jnp.maximum(cache.size, 1)
    uniform = jax.random.randint(k_all, (batch_size,), 0, size)
    if demo_fraction == 0.0:
        return uniform
    filled = jnp.arange(cache.capacity) < cache.size
    demo, prac = filled & cache.demo, filled & ~cache.demo
    n_demo, n_prac = demo.sum(), prac.sum()
    p_demo = jnp.maximum(demo_fraction, n_demo / size)
    from_demo = jax.random.uniform(k_grp, (batch_size,)) < p_demo
    u = jax.random.uniform(k_idx, (batch_size,))
    n_grp = jnp.where(from_demo, n_demo, n_prac)
    r = jnp.minimum((u * n_grp).astype(jnp.int32), jnp.maximum(n_grp - 1, 0))
    row = jnp.where(from_demo, nth_true(demo, r), nth_true(prac, r))
    return jnp.where((n_demo > 0) & (n_prac > 0), row, uniform).astype(jnp.int32)


def sample_subsequences(key, cache: Cache, k: int, batch_size: int,
                        frame_stack: int = 1, obs_size: int = 13, demo_fraction: float = 0.0) -> Batch:
    """`batch_size` windows of k steps from the cache's first `cache.size` rows (jit-compatible).

    Episodes are drawn by `sample_episodes`; each window contains the episode's hit step. Each step's
    input is the last `frame_stack` frames, padded at the episode start by repeating the first
    frame (as `ttmjx.world.record.frame_stack`). Steps past the episode end (or past T) are padding
    with mask False. The cache must not be empty (size 0 samples row 0).
    """
    t = cache.horizon
    k_ep, k_start = jax.random.split(key)
    ep = sample_episodes(k_ep, cache, batch_size, demo_fraction)
    valid = cache.valid[ep]                                        # [B, T]
    start = window_starts(k_start, valid.sum(-1), cache.hit_step[ep], k)
    steps = start[:, None] + jnp.arange(k)                          # [B, k]
    mask = (steps < t) & jnp.take_along_axis(valid, jnp.minimum(steps, t - 1), axis=1)
    idx = jnp.clip(steps[..., None] - (frame_stack - 1) + jnp.arange(frame_stack), 0, t - 1)
    rows = ep[:, None, None]
    frames = observation.to_width(cache.obs[rows, idx], obs_size, cache.ball_vel[rows, idx], xp=jnp)
    actions = cache.actions[ep[:, None], jnp.minimum(steps, t - 1)]
    return Batch(frames, actions, mask, ep.astype(jnp.int32), start)
