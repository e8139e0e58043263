"""From rollouts to training data: hindsight relabeling, which episodes to keep, statistics."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from models.normalizer import Normalizer, normalizer_from_data
from ttmjx.world import observation
from ttmjx.world.config import Table, opponent_half
from ttmjx.world.record import Trajectories


def _xp(*arrays):
    return np if all(isinstance(a, np.ndarray) for a in arrays) else jnp


def relabel(traj: Trajectories) -> Trajectories:
    """Hindsight relabeling: goal := the achieved landing point, in `goal [B, 2]` and in the goal
    columns of every frame of `obs [B, T, 13]`.

    Episodes without a landing (NaN: the ball was not hit) keep their commanded goal; they are
    dropped by `keep_for_training`. numpy in -> numpy out; jax arrays -> jax (jit-compatible).
    """
    if traj.obs.ndim != 3 or traj.obs.shape[-1] != 13 or traj.landing.shape != (traj.obs.shape[0], 2):
        raise ValueError(f"relabel: obs {tuple(traj.obs.shape)} and landing {tuple(traj.landing.shape)} "
                         f"must be [B, T, 13] and [B, 2]")
    xp = _xp(traj.obs, traj.landing, traj.goal)
    landed = xp.all(xp.isfinite(traj.landing), axis=-1, keepdims=True)
    goal = xp.where(landed, traj.landing, traj.goal).astype(traj.goal.dtype)
    return traj._replace(obs=observation.with_goal(traj.obs, goal[:, None, :], xp=xp), goal=goal)


def keep_for_training(traj: Trajectories, table: Table, margin: float):
    """[B] bool: the ball was hit and landed within `margin` metres of the opponent's half.

    Training goals may lie off the table by up to `margin` (the paper: goals beyond the edges
    help near them); evaluation goals stay on the table. margin=inf keeps every hit ball.
    """
    xp = _xp(traj.hit, traj.landing)
    (x0, x1), (y0, y1) = opponent_half(table)
    x, y = traj.landing[:, 0], traj.landing[:, 1]
    inside = (x >= x0 - margin) & (x <= x1 + margin) & (y >= y0 - margin) & (y <= y1 + margin)
    return xp.asarray(traj.hit, bool) & inside   # NaN landings compare False


def data_normalizer(traj: Trajectories, obs_size: int, keep=None, min_std: float = 1e-3) -> Normalizer:
    """Observation and action statistics over the valid steps of the kept episodes.

    Call it on the relabeled demonstrations (the goal columns then hold landing points).
    keep [B] bool (default: all). The result stays fixed for the whole run: the action std is
    also the unit of the exploration noise.
    """
    mask = jnp.asarray(traj.valid, bool)
    if keep is not None:
        mask = mask & jnp.asarray(keep, bool)[:, None]
    obs = observation.to_width(jnp.asarray(traj.obs), obs_size, jnp.asarray(traj.ball_vel), xp=jnp)
    return normalizer_from_data(obs, jnp.asarray(traj.actions), mask, min_std)
