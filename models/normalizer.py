"""Input and output normalization: statistics from data, carried with the parameters."""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp

from models.config import ACTION_SIZE


class Normalizer(NamedTuple):
    """Per-feature statistics; fixed after they are computed (never trained)."""
    obs_mean: jnp.ndarray    # [O]
    obs_std: jnp.ndarray     # [O]
    act_mean: jnp.ndarray    # [8]
    act_std: jnp.ndarray     # [8]


def identity_normalizer(obs_size: int) -> Normalizer:
    """Mean 0, std 1: a placeholder until statistics from data exist."""
    return Normalizer(jnp.zeros(obs_size), jnp.ones(obs_size),
                      jnp.zeros(ACTION_SIZE), jnp.ones(ACTION_SIZE))


def normalizer_from_data(obs, actions, mask, min_std: float = 1e-3) -> Normalizer:
    """Mean and std over the steps where mask is set.

    obs [..., O], actions [..., 8], mask [...] (bool). A feature whose std is below `min_std`
    (a joint that never moves in the data) gets std = min_std, so normalizing never divides by 0.
    """
    if obs.shape[:-1] != mask.shape or actions.shape[:-1] != mask.shape or actions.shape[-1] != ACTION_SIZE:
        raise ValueError(f"normalizer_from_data: obs {obs.shape}, actions {actions.shape} and mask "
                         f"{mask.shape} must share leading axes, with actions [..., {ACTION_SIZE}]")
    w = jnp.asarray(mask, jnp.float32)[..., None]
    n = jnp.maximum(w.sum(), 1.0)

    def mean_std(x):
        x = jnp.asarray(x, jnp.float32)
        mean = (w * x).reshape(-1, x.shape[-1]).sum(0) / n
        var = (w * (x - mean) ** 2).reshape(-1, x.shape[-1]).sum(0) / n
        return mean, jnp.maximum(jnp.sqrt(var), min_std)

    return Normalizer(*mean_std(obs), *mean_std(actions))


def normalize_obs(norm: Normalizer, obs):
    """[..., O] -> [..., O]."""
    return (obs - norm.obs_mean) / norm.obs_std


def normalize_actions(norm: Normalizer, actions):
    """[..., 8] -> [..., 8]."""
    return (actions - norm.act_mean) / norm.act_std


def denormalize_actions(norm: Normalizer, actions):
    """[..., 8] normalized -> [..., 8] joint targets."""
    return actions * norm.act_std + norm.act_mean
