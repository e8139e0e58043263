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


# Landing-balanced sampling (TrainConfig.balance) counts the pool's relabelled goals in square
# cells of this side (m), over this window of the table frame (landings outside fall into the
# border cells). The side is of the order of the success radii (0.2-0.3 m), so a cell is "one
# place to aim at"; the window holds the opponent's half and 1 m around it.
BALANCE_CELL = 0.15
BALANCE_WINDOW = ((-1.0, 2.4), (-1.8, 1.8))


def landing_cells(goal):
    """[C] int32 cell index of each relabelled goal [C, 2] on the BALANCE_CELL grid."""
    (x0, x1), (y0, y1) = BALANCE_WINDOW
    nx, ny = int(round((x1 - x0) / BALANCE_CELL)), int(round((y1 - y0) / BALANCE_CELL))
    ix = jnp.clip(jnp.floor((goal[:, 0] - x0) / BALANCE_CELL), 0, nx - 1).astype(jnp.int32)
    iy = jnp.clip(jnp.floor((goal[:, 1] - y0) / BALANCE_CELL), 0, ny - 1).astype(jnp.int32)
    return jnp.where(jnp.all(jnp.isfinite(goal), -1), ix * ny + iy, 0), nx * ny


def balanced_weights(cache: Cache, balance: float):
    """[C] float32 sampling weight of each row: count(cell of its landing) ** -balance over the
    filled rows, 0 elsewhere. balance = 1: every occupied cell is drawn equally often, whatever
    how many episodes landed there (Skew-Fit's density reweighting with a histogram density);
    0: uniform over rows."""
    filled = jnp.arange(cache.capacity) < cache.size
    cell, n_cells = landing_cells(cache.goal)
    counts = jax.ops.segment_sum(filled.astype(jnp.float32), cell, num_segments=n_cells)
    return jnp.where(filled, jnp.maximum(counts[cell], 1.0) ** -balance, 0.0)


def draw_rows(key, weights, n: int):
    """[n] int32 rows drawn with probability proportional to weights [C] (>= 0, not all 0), by
    inverting the cumulative sum (O(C + n log C), not n draws over C categories)."""
    cdf = jnp.cumsum(weights)
    u = jax.random.uniform(key, (n,)) * cdf[-1]
    return jnp.minimum(jnp.searchsorted(cdf, u, side="right"), weights.shape[0] - 1).astype(jnp.int32)


def sample_balanced(key, cache: Cache, batch_size: int, demo_fraction: float, balance: float):
    """[B] rows drawn by balanced_weights; with demo_fraction f, a row comes from the
    demonstrations with probability max(f, their share of the weight), balanced within each group."""
    w = balanced_weights(cache, balance)
    k_grp, k_demo, k_prac = jax.random.split(key, 3)
    if is_zero(demo_fraction):
        return draw_rows(k_prac, w, batch_size)
    w_demo, w_prac = jnp.where(cache.demo, w, 0.0), jnp.where(cache.demo, 0.0, w)
    s_demo, s_prac = w_demo.sum(), w_prac.sum()
    p_demo = jnp.maximum(demo_fraction, s_demo / jnp.maximum(s_demo + s_prac, 1e-30))
    from_demo = jax.random.uniform(k_grp, (batch_size,)) < p_demo
    row = jnp.where(from_demo, draw_rows(k_demo, w_demo, batch_size), draw_rows(k_prac, w_prac, batch_size))
    # a lane's f = 0 (an array in a batch of lanes) draws exactly what the branch above draws
    return jnp.where((s_demo > 0) & (s_prac > 0) & (demo_fraction > 0), row, draw_rows(k_prac, w, batch_size))


def is_zero(demo_fraction) -> bool:
    """Whether demo_fraction is the constant 0 (one run's config); a lane's array is data."""
    return isinstance(demo_fraction, (int, float)) and demo_fraction == 0.0


def sample_episodes(key, cache: Cache, batch_size: int, demo_fraction: float = 0.0, balance: float = 0.0):
    """[B] int32 cache rows to train on (jit-compatible).

    demo_fraction (a float, or a lane's [] array: training.update.Knobs) = 0: uniform over the
    cache's `size` rows (the paper). demo_fraction = f > 0:
    each row is a demonstration with probability max(f, share of demonstrations in the cache),
    uniform within its group, so practice adds to the pool without drowning the demonstrations
    (practice episodes are the policy's own, less precise strokes). Falls back to uniform while
    either group is empty.

    balance = a > 0: rows are drawn with weight count(cell of the landing) ** -a instead of
    uniformly (sample_balanced), so the policy's own landings, piling up where it already lands,
    do not crowd out the places few episodes reached.
    """
    if balance > 0.0:
        return sample_balanced(key, cache, batch_size, demo_fraction, balance)
    k_all, k_grp, k_idx = jax.random.split(key, 3)
    size = jnp.maximum(cache.size, 1)
    uniform = jax.random.randint(k_all, (batch_size,), 0, size)
    if is_zero(demo_fraction):
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
    return jnp.where((n_demo > 0) & (n_prac > 0) & (demo_fraction > 0), row, uniform).astype(jnp.int32)


def sample_subsequences(key, cache: Cache, k: int, batch_size: int,
                        frame_stack: int = 1, obs_size: int = 13, demo_fraction: float = 0.0,
                        balance: float = 0.0) -> Batch:
    """`batch_size` windows of k steps from the cache's first `cache.size` rows (jit-compatible).

    Episodes are drawn by `sample_episodes`; each window contains the episode's hit step. Each step's
    input is the last `frame_stack` frames, padded at the episode start by repeating the first
    frame (as `ttmjx.world.record.frame_stack`). Steps past the episode end (or past T) are padding
    with mask False. The cache must not be empty (size 0 samples row 0).
    """
    t = cache.horizon
    k_ep, k_start = jax.random.split(key)
    ep = sample_episodes(k_ep, cache, batch_size, demo_fraction, balance)
    valid = cache.valid[ep]                                        # [B, T]
    start = window_starts(k_start, valid.sum(-1), cache.hit_step[ep], k)
    steps = start[:, None] + jnp.arange(k)                          # [B, k]
    mask = (steps < t) & jnp.take_along_axis(valid, jnp.minimum(steps, t - 1), axis=1)
    idx = jnp.clip(steps[..., None] - (frame_stack - 1) + jnp.arange(frame_stack), 0, t - 1)
    rows = ep[:, None, None]
    frames = observation.to_width(cache.obs[rows, idx], obs_size, cache.ball_vel[rows, idx], xp=jnp)
    actions = cache.actions[ep[:, None], jnp.minimum(steps, t - 1)]
    return Batch(frames, actions, mask, ep.astype(jnp.int32), start)
