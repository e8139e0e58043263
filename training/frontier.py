"""Frontier practice goals (MEGA: Pitis et al. 2020, "Maximum Entropy Gain Exploration for
Long Horizon Multi-goal Reinforcement Learning", arXiv 2007.02832): goals at the least dense of
the places the policy's balls (and the demonstrations') have landed, just beyond what it reaches.

The density is a Gaussian kernel estimate over a subsample of the pool's relabelled goals (its
landings, Cache.goal); each frontier goal is the least dense of a few achieved landings drawn
from the pool and jittered by the kernel's width, among those inside the practice goal region
(the opponent's half extended by TrainConfig.practice_goal_margin). Achieved landings are
reachable by construction, so unlike a uniform draw over the least dense cells this never aims
where no stroke has ever gone. Pure JAX, for one run: the practice round vmaps it over lanes.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from training.cache import Cache
from ttmjx.world.config import Table

# Kernel width (m): about a ball's success radius (30 cm) halved, so the density resolves the
# thirds of the half (46 cm deep) and the side bands (20 cm) that the diagnostics report.
BANDWIDTH = 0.12
# Pool landings the density is estimated from: the rarest region worth aiming at (the third next
# to the net, ~3-5% of landings, docs/RESULTS.md) still holds ~20 of them, and the [K, R]
# distances stay small with thousands of goals per round.
REFERENCES = 512
# Achieved landings each frontier goal is the least dense of (MEGA's candidate set, per goal):
# with 16, a region holding 4% of the pool offers a candidate to ~half the frontier goals.
CANDIDATES = 16
FRONTIER_STREAM = 0x6F6E   # fold-in tag: the frontier's draws apart from the uniform draw's key
FAR = 1e3                  # where a non-finite reference landing is put: out of every kernel's reach


def in_goal_region(goals, table: Table, margin: float):
    """[...] bool: goals [..., 2] inside the practice goal region, the opponent's half extended
    `margin` beyond its end line and side lines (ttmjx.world.goals.goals_from_unit's region)."""
    x, y = goals[..., 0], goals[..., 1]
    return (x >= 0) & (x <= table.half_length + margin) & (jnp.abs(y) <= table.half_width + margin)


def log_density(points, refs, bandwidth: float = BANDWIDTH):
    """[K] log of the Gaussian kernel density of the landings refs [R, 2] at points [K, 2], up
    to a constant (logsumexp: no ties at an underflowed zero far from every landing)."""
    d2 = jnp.sum((points[:, None, :] - refs[None, :, :]) ** 2, -1)
    return jax.nn.logsumexp(-d2 / (2 * bandwidth ** 2), axis=1)


def pool_landings(key, cache: Cache, n: int = REFERENCES):
    """[n, 2] relabelled goals drawn with replacement from the pool's rows < cache.size (rows
    of an empty pool: zeros, to be ignored by the caller)."""
    rows = jax.random.randint(key, (n,), 0, jnp.maximum(cache.size, 1))
    g = cache.goal[rows]
    return jnp.where(jnp.isfinite(g), g, FAR)


def frontier_goals(key, cache: Cache, n: int, table: Table, margin: float):
    """([n, 2] goals, [n] bool found): each the least dense (over the pool's landings) of
    CANDIDATES achieved landings jittered by BANDWIDTH, among those inside the goal region;
    found is False where none was (an empty pool: every one), and that goal is meaningless."""
    k_ref, k_cand, k_jit = jax.random.split(key, 3)
    refs = pool_landings(k_ref, cache)
    cand = pool_landings(k_cand, cache, n * CANDIDATES).reshape(n, CANDIDATES, 2)
    cand = cand + BANDWIDTH * jax.random.normal(k_jit, cand.shape)
    ok = (cache.size > 0) & in_goal_region(cand, table, margin)
    dens = jnp.where(ok, log_density(cand.reshape(-1, 2), refs).reshape(n, CANDIDATES), jnp.inf)
    pick = jnp.argmin(dens, axis=1)
    return jnp.take_along_axis(cand, pick[:, None, None], axis=1)[:, 0], ok.any(1)


def frontier_count(m: int, fraction: float) -> int:
    """How many of a round's m goals go to the frontier (static)."""
    return int(round(fraction * m))


def with_frontier(key, cache: Cache, goals, fraction: float, table: Table, margin: float):
    """goals [M, 2] (the round's uniform draw) with frontier_count(M, fraction) of them, at
    random places in the round, replaced by frontier goals of the pool; where no frontier goal
    was found (an empty pool) the uniform goal stays. The round's members play contiguous blocks
    of it, so the random places give every member its share of the frontier."""
    m = goals.shape[0]
    n = frontier_count(m, fraction)
    if n == 0:
        return goals
    k_where, k_draw = jax.random.split(jax.random.fold_in(key, FRONTIER_STREAM))
    where = jax.random.permutation(k_where, m)[:n]
    g, found = frontier_goals(k_draw, cache, n, table, margin)
    return goals.at[where].set(jnp.where(found[:, None], g, goals[where]))
