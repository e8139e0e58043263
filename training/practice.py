"""Self-supervised practice (Algorithm 1): roll the current policies out toward random goals,
relabel every hit with where the ball landed, append to the one shared cache, train S steps.

Practice goals are uniform over the opponent's half extended TrainConfig.practice_goal_margin
beyond the table's edges, with TrainConfig.practice_goals="frontier" a share of them moved to the
pool's frontier (training.frontier); which episodes join the cache is TrainConfig.practice_keep
(every hit, as the paper, by default). The round's statistics use the world's one strict goal
metric.

`practice_round` is the round, written once. On MJX all of it is pure and `Practice` compiles it
as ONE jit-compiled function; on a CPU the rollouts step MuJoCo C on the host, so the same
round runs eagerly around the compiled pieces (goals, append, the S updates).

`Practice` runs the round of L lanes (training.trainer): on MJX the one-run round vmapped over
the lanes, each device playing its block of lanes whole (nothing passes between lanes); on
MuJoCo C the compiled pieces vmapped over the lanes and one host rollout for every lane's throws.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from models.config import PolicyConfig
from models.policy import (NoisyParams, make_policy, with_action_noise, with_integrating_action_noise,
                           with_lane_action_noise)
from training.cache import Cache, add_episodes
from training.config import TrainConfig
from training.frontier import with_frontier
from training.loss import lstm_kernel
from training.mesh import Layout, lane_layout
from training.update import Knobs, TrainState, acting_params, lane_knobs, train_loop_fn
from ttmjx.world import thrower
from ttmjx.world.backends import Backend, backend_kind
from ttmjx.world.config import Table, World
from ttmjx.world.env import uniform_goals
from ttmjx.world.goals import goal_stats, member_success, region_success
from ttmjx.world.record import Trajectories


class PracticeStats(NamedTuple):
    """Scalars of one practice round (with exploration noise, toward uniform goals)."""
    hit_rate: jax.Array
    on_table_rate: jax.Array  # first bounce after the hit on the opponent's half
    within_30cm: jax.Array
    within_20cm: jax.Array
    kept: jax.Array          # episodes appended to the cache
    # within 30 cm over the goals in each region (ttmjx.world.goals.GOAL_REGIONS; NaN if none)
    near_30cm: jax.Array
    middle_30cm: jax.Array
    far_30cm: jax.Array
    edges_30cm: jax.Array
    members_30cm: jax.Array  # [N] within 30 cm of each member over the episodes it played


class RoundParts(NamedTuple):
    """The steps of a round, compiled or not as the backend allows."""
    goals: Callable      # key -> [M, 2], the uniform draw
    rollout: Callable    # (params, key, throws [M], goals [M, 2]) -> Trajectories
    append: Callable     # (cache, traj, counted) -> cache
    train: Callable      # (state, cache, key, knobs) -> (state, loss [N])
    block: int = 0       # episodes each ensemble member plays (M / N; 0: one policy)
    noisy: bool = False  # the rollout policy reads its noise scale from NoisyParams (Knobs.action_noise)
    # (key, cache, goals [M, 2]) -> [M, 2]: a share of the drawn goals moved to the pool's
    # frontier (training.frontier); None: the draw as it is, bit for bit. A step of its own, not
    # part of `goals`, which subclasses replace with key -> [M, 2] (training.bootstrap_paper).
    frontier: Callable | None = None


def practice_policy(pcfg: PolicyConfig, tcfg: TrainConfig, lane_noise: bool = False):
    """The rollout policy of practice: the member's policy plus held-per-episode action noise
    (TrainConfig.action_noise_form); lane_noise: its scale read from the parameters
    (NoisyParams), for lanes whose scale differs."""
    base = make_policy(pcfg)
    if lane_noise:
        return with_lane_action_noise(base, tcfg.action_noise_form)
    if tcfg.action_noise <= 0:
        return base
    noisy = with_action_noise if tcfg.action_noise_form == "offset" else with_integrating_action_noise
    return noisy(base, tcfg.action_noise)


def practice_stats(traj: Trajectories, kept_before, kept_after, counted, table: Table, members: int = 1) -> PracticeStats:
    """Statistics over the round's first `counted` episodes (those within the run's budget): the
    totals, by goal region and by ensemble member (each plays an equal block of the round)."""
    first = jnp.arange(traj.hit.shape[0]) < counted
    outcome = (traj.landing, traj.goal, traj.hit, traj.on_opponent)
    s = goal_stats(*outcome, xp=jnp, counted=first)
    regions = region_success(*outcome, table, xp=jnp, counted=first)
    return PracticeStats(s["hit_rate"], s["on_table_rate"], s["within_30cm"], s["within_20cm"],
                         (kept_after - kept_before).astype(jnp.int32), *regions,
                         member_success(*outcome, members, xp=jnp, counted=first))


def stats_row(stats: dict) -> dict:
    """One run's PracticeStats (host arrays by field name) as the metrics row's `practice_*`
    columns; the per-member success becomes practice_member<i>_30cm."""
    row = {}
    for k, v in stats.items():
        v = np.asarray(v)
        if k == "members_30cm":
            row.update({f"practice_member{i}_30cm": float(x) for i, x in enumerate(v.reshape(-1))})
        else:
            row[f"practice_{k}"] = float(v)
    return row


def round_keys(key):
    """Named keys of one SSP round, split once at the top: (goals, rollouts, training)."""
    k_goal, k_roll, k_train = jax.random.split(key, 3)
    return k_goal, k_roll, k_train


def practice_round(parts: RoundParts, state: TrainState, cache: Cache, key, throws: thrower.Throw,
                   counted, table: Table, seeds: bool = False, knobs: Knobs | None = None):
    """One round of Algorithm 1 -> (state, cache, loss [N], PracticeStats): goals, rollouts of the
    acting (moving-average) policies on `throws` [M], relabel + append, S updates.

    counted (int32 scalar, traced): the first `counted` of the M episodes join the cache and the
    statistics; fewer than M only in a run's last round, so that a budget is met exactly with
    one compiled round (the rest are played and dropped).

    seeds=True: every argument and the `parts` carry a leading axis of independent runs (the
    host round of several seeds; on MJX the whole round is vmapped instead).
    knobs: the lane's TrainConfig settings as data (training.update.Knobs); None: the config's."""
    over = jax.vmap if seeds else (lambda f: f)
    k_goal, k_roll, k_train = over(round_keys)(key)
    played = acting_params(state)
    if parts.noisy:   # every member of a lane explores with the lane's b
        b = jnp.asarray(knobs.action_noise)
        members = jax.tree.leaves(played)[0].shape[b.ndim]
        played = NoisyParams(played, jnp.broadcast_to(b[..., None], b.shape + (members,)))
    goals = parts.goals(k_goal)
    if parts.frontier is not None:
        goals = parts.frontier(k_goal, cache, goals)
    traj = parts.rollout(played, k_roll, throws, goals)
    new = parts.append(cache, traj, counted)
    members = traj.hit.shape[-1] // parts.block if parts.block else 1
    stats = over(lambda *a: practice_stats(*a, table, members))(jax.tree.map(jnp.asarray, traj), cache.count,
                                                               new.count, counted)
    state, loss = parts.train(state, new, k_train, knobs)
    return state, new, loss, stats


# Throws are solved for this many rounds at once. Solving launch velocities is a sequential loop
# through the flight (ttmjx.world.thrower): on a GPU it takes about as long for 16k throws as for
# 1k (docs/BENCHMARKS.md, scripts/dev/profile_practice.py).
THROW_BLOCK = 16
THROW_STREAM = 0x7E40   # fold-in tag that separates the throw keys from the per-round keys


def over_seeds(fn, backend: str, devices: int = 1):
    """fn(state, cache, key, knobs) of one run -> the same over a leading lane axis. On an
    accelerator, or over several devices, a vmap (one wider program, which jit's partitioner
    splits into each device's block of lanes). On MuJoCo C's CPU with one device a loop over the
    lanes inside the program: the updates already keep the cores busy, and XLA:CPU's batched
    matrix products were slower than the seeds one after another (docs/BENCHMARKS.md); a loop
    over lanes split across devices would make XLA gather every lane onto every device."""
    if backend_kind(backend).traceable or devices > 1:
        return jax.vmap(fn)
    return lambda *args: jax.lax.map(lambda a: fn(*a), args)


def over_lanes(fn, layout: Layout):
    """jit of fn, a function of arrays that all carry the leading lane axis [L] (and return only
    such arrays), its inputs and outputs split along that axis over the lane layout's devices:
    XLA's partitioner gives each device its block of lanes, and nothing passes between lanes
    (the vmapped lanes share no operand). shard_map would say the same by hand; on 4 H200s its
    MJX practice round ended in a segmentation fault inside XLA (docs/SCALING.md)."""
    if layout.mesh.size == 1:
        return jax.jit(fn)
    return jax.jit(fn, in_shardings=layout.lanes, out_shardings=layout.lanes)


class Practice:
    """Practice rounds and train-only rounds of L lanes of one configuration (training.trainer:
    one seed is a lane of one). Every state, cache, key and throw carries a leading [L] axis,
    each compiled piece is the one-run piece vmapped over it, and the lane layout
    (training.mesh.lane_layout) gives each device a block of lanes. The compiled functions are
    built once here (the jit boundaries of training) and reused every round."""

    def __init__(self, world: World, pcfg: PolicyConfig, tcfg: TrainConfig, backend: Backend,
                 episodes: int, train_steps: int, layout: Layout | None = None, seeds: int = 1,
                 lane_noise: bool = False):
        if episodes % tcfg.members:
            raise ValueError(f"episodes_per_ssp={episodes} must be a multiple of members={tcfg.members} "
                             f"(every member practises an equal share)")
        self.world, self.tcfg, self.backend, self.episodes, self.seeds = world, tcfg, backend, episodes, seeds
        self.layout = layout or lane_layout(seeds)
        # lane_noise: the lanes' practice noise scale is read from their knobs (it may differ)
        self.lane_noise = lane_noise
        self.train_loop, self._train_one = None, None
        if train_steps > 0:
            # the LSTM's kernel for this program's lanes (auto: cuDNN for one member of one lane)
            kernel = dataclasses.replace(tcfg, lstm_kernel=lstm_kernel(pcfg, tcfg, seeds))
            self._train_one = train_loop_fn(pcfg, kernel, train_steps)   # one run, pure
            self.train_loop = self.lanes(over_seeds(self._train_one, backend.name, self.layout.mesh.size))
        sample = lambda k: thrower.sample_throws(k, world, THROW_BLOCK * episodes)  # noqa: E731
        self._sample_throws = self.lanes(jax.vmap(sample))
        self._bank = (None, None)
        policy = practice_policy(pcfg, tcfg, self.lane_noise)
        pure = self._pure_parts(backend.rollout_fn(policy, members=tcfg.members)) if backend.kind.traceable else None
        self._round = self._compiled_round(pure) if pure else self._host_round(policy)

    def lanes(self, fn):
        """fn over the lanes, compiled, on the lane layout's devices (over_lanes)."""
        return over_lanes(fn, self.layout)

    def _pure_parts(self, rollout) -> RoundParts:
        """One run's round: practice goals beyond the table by practice_goal_margin, some at the
        pool's frontier by practice_goals; kept episodes by practice_keep."""
        world, m, tcfg = self.world, self.episodes, self.tcfg
        goal_margin, keep_margin = tcfg.practice_goal_margin, tcfg.practice_keep_margin
        return RoundParts(goals=lambda k: uniform_goals(k, m, world.table, goal_margin), rollout=rollout,
                          append=lambda c, t, n: add_episodes(c, t, world.table, keep_margin, counted=n),
                          train=self.train_one, block=m // tcfg.members, noisy=self.lane_noise,
                          frontier=self._frontier())

    def _frontier(self) -> Callable | None:
        """RoundParts.frontier of the config: None for uniform practice goals."""
        tcfg, table = self.tcfg, self.world.table
        if tcfg.practice_goals != "frontier":
            return None
        return lambda k, c, g: with_frontier(k, c, g, tcfg.frontier_fraction, table, tcfg.practice_goal_margin)

    def _compiled_round(self, pure: RoundParts):
        """MJX: the whole round of one run vmapped over the lanes, in one jit; each device plays
        its block of lanes whole."""
        return self.lanes(jax.vmap(lambda s, c, k, th, n, kn: practice_round(pure, s, c, k, th, n, self.world.table,
                                                                             knobs=kn)))

    def _host_round(self, policy):
        """MuJoCo C: the round runs on the host around its compiled pieces (goals, append and
        updates, each over the lanes); the host physics plays every lane's throws in one rollout."""
        backend, members = self.backend, self.tcfg.members
        pure = self._pure_parts(None)
        parts = pure._replace(
            goals=self.lanes(jax.vmap(pure.goals)), append=self.lanes(jax.vmap(pure.append)), train=self.train,
            frontier=pure.frontier and self.lanes(jax.vmap(pure.frontier)),
            rollout=lambda p, k, th, g: backend.rollout(policy, p, k, th, g, members=members))
        return lambda s, c, k, th, n, kn: practice_round(parts, s, c, k, th, n, self.world.table, seeds=True,
                                                         knobs=kn)

    def round_throws(self, base_key, it: int) -> thrower.Throw:
        """The M throws [L, M, ...] of practice round `it` per lane, a function of (base_key [L],
        it) only (so a resumed run replays them), drawn THROW_BLOCK rounds at a time."""
        block, i = divmod(int(it), THROW_BLOCK)
        if self._bank[0] != block:
            fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
            k = fold(fold(np.asarray(base_key), THROW_STREAM), block)
            self._bank = (block, self._sample_throws(k))
        m = self.episodes
        return jax.tree.map(lambda x: x[..., i * m:(i + 1) * m, :], self._bank[1])   # [L, M, 3 or 2]

    def train(self, state: TrainState, cache: Cache, key, knobs: Knobs | None = None):
        """S training steps of every lane -> (state, mean loss per member [L, N]); knobs [L]
        (Knobs), None: the config's."""
        if self.train_loop is None:
            return state, jnp.zeros((self.seeds, self.tcfg.members))
        state, loss = self.train_loop(state, cache, key, self.knobs if knobs is None else knobs)
        return state, loss.mean(-2)   # over the steps

    def train_one(self, state: TrainState, cache: Cache, key, knobs: Knobs | None = None):
        """`train` of one lane, uncompiled (inside the vmapped round of the lanes)."""
        if self._train_one is None:
            return state, jnp.zeros(self.tcfg.members)
        state, loss = self._train_one(state, cache, key, knobs)
        return state, loss.mean(0)

    @property
    def knobs(self) -> Knobs:
        """Every lane's knobs as this Practice's config has them ([L] arrays)."""
        return lane_knobs([self.tcfg] * self.seeds)

    def iteration(self, state: TrainState, cache: Cache, key, throws: thrower.Throw | None = None,
                  counted=None, knobs: Knobs | None = None):
        """One iteration of every lane -> (state, cache, loss [L, N], PracticeStats [L] or None);
        every argument and result has the leading [L] axis. With `throws` [L, M] (`round_throws`)
        a practice round, of which the first `counted` episodes (one count or [L]; None: all M)
        join each pool; 0 for a lane that does not practise: it plays the round and keeps nothing,
        so it trains exactly as a train-only round. Without, S updates only (pretraining, LFP).
        `knobs` [L] are the lanes' settings (None: the config's)."""
        knobs = self.knobs if knobs is None else knobs
        if throws is not None:
            n = self.episodes if counted is None else counted
            n = jnp.asarray(np.broadcast_to(np.asarray(n, np.int32), (self.seeds,)))
            return self._round(state, cache, key, throws, n, knobs)
        state, loss = self.train(state, cache, jax.vmap(round_keys)(key)[2], knobs)
        return state, cache, loss, None
