"""Training windows: sub-sequences of k steps that always contain the hit."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from models.policy import observation_vector
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


def sample_subsequences(key, cache: Cache, k: int, batch_size: int,
                        frame_stack: int = 1, obs_size: int = 13) -> Batch:
    """`batch_size` windows of k steps from the cache's first `cache.size` rows (jit-compatible).

    Episodes are drawn uniformly; each window contains the episode's hit step. Each step's
    input is the last `frame_stack` frames, padded at the episode start by repeating the first
    frame (as `ttmjx.record.frame_stack`). Steps past the episode end (or past T) are padding
    with mask False. The cache must not be empty (size 0 samples row 0).
    """
    t = cache.horizon
    k_ep, k_start = jax.random.split(key)
    ep = jax.random.randint(k_ep, (batch_size,), 0, jnp.maximum(cache.size, 1))
    valid = cache.valid[ep]                                        # [B, T]
    start = window_starts(k_start, valid.sum(-1), cache.hit_step[ep], k)
    steps = start[:, None] + jnp.arange(k)                          # [B, k]
    mask = (steps < t) & jnp.take_along_axis(valid, jnp.minimum(steps, t - 1), axis=1)
    idx = jnp.clip(steps[..., None] - (frame_stack - 1) + jnp.arange(frame_stack), 0, t - 1)
    rows = ep[:, None, None]
    frames = observation_vector(cache.obs[rows, idx], cache.ball_vel[rows, idx], obs_size)
    actions = cache.actions[ep[:, None], jnp.minimum(steps, t - 1)]
    return Batch(frames, actions, mask, ep.astype(jnp.int32), start)
