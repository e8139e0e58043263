"""Self-supervised practice (Algorithm 1): roll the current policies out toward random goals,
drop episodes where the ball was not hit, relabel with the landing point, append to the one
shared cache, train S steps.

On MJX one SSP iteration (goal and throw sampling, rollouts, filtering, relabeling, appending,
S training steps) is ONE jit-compiled function. On a CPU the rollouts run on the MuJoCo C
backend (host loop over control steps) and the append and the S training steps stay
jit-compiled.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from models.config import PolicyConfig
from models.policy import make_policy, with_action_noise
from training.cache import Cache, add_episodes
from training.config import TrainConfig
from training.update import TrainState, acting_params, make_train_loop
from ttmjx.world import thrower
from ttmjx.world.backends import Backend
from ttmjx.world.env import uniform_goals
from ttmjx.world.config import World
from ttmjx.world.record import Trajectories


class PracticeStats(NamedTuple):
    """Scalars of one practice round (with exploration noise, toward uniform goals)."""
    hit_rate: jax.Array
    within_30cm: jax.Array
    within_20cm: jax.Array
    kept: jax.Array          # episodes appended to the cache


def practice_policy(pcfg: PolicyConfig, tcfg: TrainConfig):
    """The rollout policy of practice: the member's policy plus held-per-episode action noise."""
    base = make_policy(pcfg)
    return with_action_noise(base, tcfg.action_noise) if tcfg.action_noise > 0 else base


def practice_stats(traj: Trajectories, kept_before, kept_after) -> PracticeStats:
    dist = jnp.linalg.norm(traj.landing - traj.goal, axis=-1)
    ok = traj.hit & jnp.isfinite(dist)
    d = jnp.where(ok, dist, jnp.inf)
    return PracticeStats(jnp.mean(traj.hit), jnp.mean(d <= 0.3), jnp.mean(d <= 0.2),
                         (kept_after - kept_before).astype(jnp.int32))


def round_keys(key):
    """Named keys of one SSP round, split once at the top."""
    k_goal, k_roll, k_train = jax.random.split(key, 3)
    return k_goal, k_roll, k_train


# Throws are solved for this many rounds at once. Solving launch velocities is a sequential loop
# through the flight (ttmjx.world.thrower): on a GPU it takes as long for 16k throws as for 1k
# (0.57 s for 1,000 and 0.82 s for 16,000 on an H100, scripts/profile_practice.py).
THROW_BLOCK = 16
THROW_STREAM = 0x7E40   # fold-in tag that separates the throw keys from the per-round keys


class Practice:
    """SSP iterations for one configuration; compiled functions built once and reused."""

    def __init__(self, world: World, pcfg: PolicyConfig, tcfg: TrainConfig, backend: Backend,
                 episodes: int, train_steps: int):
        if episodes % tcfg.members:
            raise ValueError(f"episodes_per_ssp={episodes} must be a multiple of members={tcfg.members} "
                             f"(every member practises an equal share)")
        self.world, self.pcfg, self.tcfg, self.backend = world, pcfg, tcfg, backend
        self.episodes, self.train_steps = episodes, train_steps
        self.policy = practice_policy(pcfg, tcfg)
        self.train_loop = make_train_loop(pcfg, tcfg, train_steps) if train_steps > 0 else None
        self._append = jax.jit(lambda cache, traj: add_episodes(cache, traj, world.table, tcfg.goal_margin))
        self._goals = jax.jit(uniform_goals, static_argnums=(1, 2))  # (key, n, table)
        self._sample_throws = jax.jit(lambda k: thrower.sample_throws(k, world, THROW_BLOCK * episodes))
        self._bank = (None, None)
        self._fused = None

    def round_throws(self, base_key, it: int) -> thrower.Throw:
        """The M throws [M, ...] of practice round `it`, a function of (base_key, it) only (so a
        resumed run replays them), drawn THROW_BLOCK rounds at a time."""
        block, i = divmod(int(it), THROW_BLOCK)
        if self._bank[0] != block:
            k = jax.random.fold_in(jax.random.fold_in(base_key, THROW_STREAM), block)
            self._bank = (block, self._sample_throws(k))
        m = self.episodes
        return jax.tree.map(lambda x: x[i * m:(i + 1) * m], self._bank[1])

    # -- the pieces ---------------------------------------------------------------------
    def rollouts(self, params, key, throws: thrower.Throw) -> Trajectories:
        """M practice episodes of the ensemble (members play equal blocks) on `throws` [M]
        toward uniform goals."""
        k_goal, k_roll, _ = round_keys(key)
        goals = self._goals(k_goal, self.episodes, self.world.table)
        return self.backend.rollout(self.policy, params, k_roll, throws, goals, members=self.tcfg.members)

    def absorb(self, cache: Cache, traj: Trajectories) -> tuple[Cache, PracticeStats]:
        """Filter, relabel and append practice episodes."""
        new = self._append(cache, traj)
        return new, practice_stats(jax.tree.map(jnp.asarray, traj), cache.count, new.count)

    def train(self, state: TrainState, cache: Cache, key):
        """S training steps -> (state, mean loss per member [N])."""
        if self.train_loop is None:
            return state, jnp.zeros(self.tcfg.members)
        state, loss = self.train_loop(state, cache, key)
        return state, loss.mean(0)

    # -- one iteration ---------------------------------------------------------------------
    def iteration(self, state: TrainState, cache: Cache, key, throws: thrower.Throw | None = None):
        """One SSP iteration -> (state, cache, loss [N], PracticeStats or None). With `throws`
        [M] (`round_throws`) the round practises on them; without, it only trains."""
        if throws is not None and self.backend.name == "mjx":
            if self._fused is None:
                self._fused = jax.jit(self._fused_iteration())
            return self._fused(state, cache, key, throws)
        stats = None
        if throws is not None:
            cache, stats = self.absorb(cache, self.rollouts(acting_params(state), key, throws))
        k_train = round_keys(key)[2]
        state, loss = self.train(state, cache, k_train)
        return state, cache, loss, stats

    def _fused_iteration(self):
        """The whole SSP iteration as one pure function (MJX)."""
        rollout = self.backend.rollout_fn(self.policy, members=self.tcfg.members)
        world, episodes = self.world, self.episodes

        def fused(state, cache, key, throws):
            k_goal, k_roll, k_train = round_keys(key)
            goals = uniform_goals(k_goal, episodes, world.table)
            traj = rollout(acting_params(state), k_roll, throws, goals)
            new = add_episodes(cache, traj, world.table, self.tcfg.goal_margin)
            stats = practice_stats(traj, cache.count, new.count)
            if self.train_loop is None:
                return state, new, jnp.zeros(self.tcfg.members), stats
            state, loss = self.train_loop(state, new, k_train)
            return state, new, loss.mean(0), stats
        return fused
