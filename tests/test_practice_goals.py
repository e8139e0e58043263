"""Frontier practice goals (training/frontier.py, TrainConfig.practice_goals="frontier"): inside
the practice goal region, away from where the pool's landings crowd, uniform on an empty pool,
under jit and vmap over lanes, and the uniform option unchanged."""
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models import PolicyConfig
from training import TrainConfig, empty_cache, mesh
from training.frontier import with_frontier
from training.practice import Practice, practice_round
from ttmjx.world.backends import Backend
from ttmjx.world.config import World
from ttmjx.world.env import uniform_goals

WORLD = World()
TABLE = WORLD.table
MARGIN = 0.2
CLUSTER = (1.0, 0.0)   # m: where most of the clustered pool landed (the far middle of the half)
M = 400


def pool(landings, capacity: int = 4096):
    """A cache whose first len(landings) rows hold these relabelled goals [K, 2] (the other
    fields are not read by the goal draw)."""
    n = len(landings)
    goal = jnp.zeros((capacity, 2)).at[:n].set(jnp.asarray(landings, jnp.float32))
    return empty_cache(capacity, 1)._replace(goal=goal, size=jnp.int32(n), count=jnp.int32(n))


def clustered(seed: int = 0, n: int = 2000) -> np.ndarray:
    """[n, 2] landings: 90% within ~6 cm of CLUSTER, the rest over the half and up to 0.6 m
    beyond its edges (outside the goal region too, as kept practice hits are)."""
    rng = np.random.default_rng(seed)
    k = n // 10
    spread = np.stack([rng.uniform(-0.3, TABLE.half_length + 0.6, k), rng.uniform(-1.4, 1.4, k)], 1)
    return np.concatenate([rng.normal(CLUSTER, 0.06, (n - k, 2)), spread]).astype(np.float32)


def frontier(fraction: float = 1.0):
    return jax.jit(lambda k, c, g: with_frontier(k, c, g, fraction, TABLE, MARGIN))


def pool_share(goals, landings, radius: float = 0.15) -> float:
    """Mean share of the pool's landings within `radius` of each goal: its density there."""
    d = np.linalg.norm(np.asarray(goals)[:, None] - landings[None], axis=2)
    return float((d < radius).mean())


def practice(tcfg: TrainConfig, seeds: int | None = None) -> Practice:
    """A round of 8 goals on MuJoCo C, of one run or of `seeds` lanes."""
    return Practice(WORLD, PolicyConfig(), tcfg, Backend(WORLD, "c"), episodes=8, train_steps=0,
                    layout=mesh.lane_layout(seeds or 1), seeds=seeds or 1)


def practice_parts(tcfg: TrainConfig, seeds: int | None = None):
    return practice(tcfg, seeds)._pure_parts(None)


def test_frontier_goals_stay_in_the_goal_region():
    key, landings = jax.random.PRNGKey(0), clustered()
    g = np.asarray(frontier()(key, pool(landings), uniform_goals(key, M, TABLE, MARGIN)))
    assert (g[:, 0] >= 0).all() and (g[:, 0] <= TABLE.half_length + MARGIN).all()
    assert (np.abs(g[:, 1]) <= TABLE.half_width + MARGIN).all()


def test_frontier_goals_fall_away_from_where_the_pool_crowds():
    key, landings = jax.random.PRNGKey(1), clustered()
    u = uniform_goals(key, M, TABLE, MARGIN)
    g = np.asarray(frontier()(key, pool(landings), u))
    # Measured: 3.2% of the pool within 15 cm of a uniform goal, 0.4% of a frontier goal.
    assert pool_share(g, landings) < 0.3 * pool_share(u, landings)
    # The cluster's own frontier is its rim: no goal at its core (uniform: ~1% of goals).
    assert (np.linalg.norm(g - CLUSTER, axis=1) < 0.08).mean() < 0.002
    assert len(np.unique(g.round(3), axis=0)) > 0.9 * M, "frontier goals should be many places, not a few"


def test_a_fraction_of_the_round_goes_to_the_frontier_in_every_members_block():
    key = jax.random.PRNGKey(2)
    u = uniform_goals(key, M, TABLE, MARGIN)
    moved = np.asarray((frontier(0.25)(key, pool(clustered()), u) != u).any(1))
    assert moved.sum() == M // 4
    assert all(0 < b.sum() < M // 4 for b in np.split(moved, 4)), "each member plays a contiguous quarter"
    np.testing.assert_array_equal(frontier(0.0)(key, pool(clustered()), u), u)


def test_an_empty_pool_leaves_the_uniform_draw():
    key = jax.random.PRNGKey(3)
    u = uniform_goals(key, M, TABLE, MARGIN)
    np.testing.assert_array_equal(frontier()(key, empty_cache(64, 1), u), u)


def test_lanes_vmapped_compute_what_each_lane_computes_alone():
    """Two lanes, one with a clustered pool and one empty, through the lanes' compiled piece."""
    prac = practice(TrainConfig(practice_goals="frontier", frontier_fraction=0.5), seeds=2)
    parts = prac._pure_parts(None)
    lanes = prac.lanes(jax.vmap(parts.frontier))
    keys = jax.random.split(jax.random.PRNGKey(4), 2)
    caches = [pool(clustered()), pool(np.zeros((0, 2)))]
    goals = jax.vmap(parts.goals)(keys)
    both = lanes(keys, jax.tree.map(lambda *x: jnp.stack(x), *caches), goals)
    for i in range(2):
        np.testing.assert_allclose(both[i], jax.jit(parts.frontier)(keys[i], caches[i], goals[i]), atol=1e-6)
    np.testing.assert_array_equal(both[1], goals[1])
    assert (np.asarray(both[0]) != np.asarray(goals[0])).any(1).sum() == 4


class Played(Exception):
    """Stops a practice round at its rollout, carrying the goals it was given."""


def played_goals(parts, cache, key, seeds: bool):
    """The goals [(L,) M, 2] practice_round hands the rollout (stopped there)."""
    def rollout(params, k, throws, goals):
        raise Played(goals)
    parts = parts._replace(rollout=rollout)
    with pytest.raises(Played) as e:
        practice_round(parts, SimpleNamespace(ema=None), cache, key, None, 8, TABLE, seeds=seeds)
    return np.asarray(e.value.args[0])


@pytest.mark.parametrize("seeds", [False, True])
def test_the_round_plays_frontier_goals_and_uniform_ones_as_before(seeds):
    key, c = jax.random.PRNGKey(5), pool(clustered())
    if seeds:
        key, c = jax.random.split(key, 2), jax.tree.map(lambda x: jnp.stack([x, x]), c)
    wrap = (lambda f: jax.jit(jax.vmap(f))) if seeds else jax.jit
    uniform = practice_parts(TrainConfig(), 2 if seeds else None)
    assert uniform.frontier is None
    uniform = uniform._replace(goals=wrap(uniform.goals))
    before = played_goals(uniform, c, key, seeds)
    k_goal = (jax.vmap(lambda k: jax.random.split(k, 3)[0]) if seeds else lambda k: jax.random.split(k, 3)[0])(key)
    np.testing.assert_array_equal(before, (jax.vmap if seeds else lambda f: f)(
        lambda k: uniform_goals(k, 8, TABLE, TrainConfig().practice_goal_margin))(k_goal))
    parts = practice_parts(TrainConfig(practice_goals="frontier", frontier_fraction=0.5), 2 if seeds else None)
    parts = parts._replace(goals=wrap(parts.goals), frontier=wrap(parts.frontier))
    after = played_goals(parts, c, key, seeds)
    moved = (after != before).any(-1)
    assert (moved.sum(-1) == 4).all(), moved


@pytest.mark.parametrize("field,value,match", [
    ("practice_goals", "edges", r"practice_goals='edges', expected one of \('uniform', 'frontier'\)"),
    ("frontier_fraction", 1.5, r"frontier_fraction=1.5, expected the share"),
    ("frontier_fraction", float("nan"), r"frontier_fraction=nan")])
def test_bad_practice_goal_options_are_refused(field, value, match):
    with pytest.raises(ValueError, match=match):
        TrainConfig(**{field: value})
