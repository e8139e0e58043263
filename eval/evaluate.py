"""Evaluation of trained policies: 200 uniform goals or the five-goal protocol, no exploration
noise; an ensemble plays the goals in equal blocks, one block per member."""
from __future__ import annotations

import math

import jax
import numpy as np

from eval.metrics import five_goals, goal_metrics, per_goal_metrics, uniform_goals
from models.config import PolicyConfig
from models.policy import ensemble_size, make_policy
from ttmjx.world import thrower
from ttmjx.world.backends import Backend
from ttmjx.world.config import World


def rollout_goals(world: World, pcfg: PolicyConfig, params, backend: Backend, key, goals, members=None):
    """Trajectories of the policy toward goals [G, 2] (G a multiple of members)."""
    k_throw, k_roll = jax.random.split(key)
    th = thrower.sample_throws(k_throw, world, len(goals))
    return backend.rollout(make_policy(pcfg), params, k_roll, th, goals, members=members)


def _padded(goals: np.ndarray, members: int | None) -> np.ndarray:
    """Repeat goals cyclically up to a multiple of the ensemble size."""
    n = members or 1
    g = len(goals)
    total = math.ceil(g / n) * n
    return goals[np.arange(total) % g]


def evaluate_params(world: World, pcfg: PolicyConfig, params, backend: Backend, key, n_goals: int = 200,
                    members: int | None = None) -> dict:
    """goal_metrics over n_goals uniform goals on the opponent's half."""
    members = members or (ensemble_size(params) if _has_member_axis(params, pcfg) else None)
    k_goal, k_run = jax.random.split(key)
    goals = _padded(uniform_goals(k_goal, n_goals, world.table), members)
    tr = rollout_goals(world, pcfg, params, backend, k_run, goals, members)
    return goal_metrics(tr.landing, goals, tr.hit)


def evaluate_five(world: World, pcfg: PolicyConfig, params, backend: Backend, key, per_goal: int = 40,
                  members: int | None = None) -> dict:
    """The five-goal protocol: per_goal attempts at each of goals A-E; totals plus per goal."""
    goals, names = five_goals(per_goal)
    idx = np.arange(len(goals))
    idx = _padded(idx, members)
    tr = rollout_goals(world, pcfg, params, backend, key, goals[idx], members)
    out = goal_metrics(tr.landing, goals[idx], tr.hit)
    out["per_goal"] = per_goal_metrics(tr.landing, goals[idx], tr.hit, [names[i] for i in idx])
    return out


def _has_member_axis(params, pcfg) -> bool:
    # Ensemble params carry one more leading axis than a single member's.
    from models.normalizer import identity_normalizer
    from models.policy import init_params
    one = jax.eval_shape(lambda: init_params(jax.random.PRNGKey(0), pcfg, identity_normalizer(pcfg.obs_size)))
    a = jax.tree.leaves(one)[0]
    b = jax.tree.leaves(params)[0]
    return np.ndim(b) == np.ndim(a) + 1
