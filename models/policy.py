"""Policies for rollouts (docs/DESIGN.md `Policy`), parameters and ensembles.

`PolicyParams` = network weights + the fixed `Normalizer`. An ensemble of N members is ONE
`PolicyParams` whose every leaf has a leading [N] axis; it is created, trained and applied with
vmap. A `Policy` is written for one member and one throw; batch it with vmap.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from models.config import ACTION_SIZE, PolicyConfig
from models.networks import init_net, net_sequence, net_step, zero_carry
from models.normalizer import Normalizer, denormalize_actions, normalize_obs
from ttmjx.world import observation
from ttmjx.world.env import Policy


class PolicyParams(NamedTuple):
    net: Any              # flax params dict (the only part the optimizer updates)
    norm: Normalizer      # fixed statistics from data


def init_params(key, cfg: PolicyConfig, norm: Normalizer) -> PolicyParams:
    """One member's parameters."""
    if norm.obs_mean.shape != (cfg.obs_size,) or norm.act_mean.shape != (ACTION_SIZE,):
        raise ValueError(f"init_params: normalizer has obs_mean {norm.obs_mean.shape} and act_mean "
                         f"{norm.act_mean.shape}, expected ({cfg.obs_size},) and ({ACTION_SIZE},)")
    return PolicyParams(init_net(key, cfg), jax.tree.map(jnp.asarray, norm))


def init_ensemble(key, cfg: PolicyConfig, norm: Normalizer, members: int) -> PolicyParams:
    """N members with independent initial weights: every leaf gets a leading [N] axis."""
    if members < 1:
        raise ValueError(f"init_ensemble: members={members}, expected >= 1")
    return jax.vmap(lambda k: init_params(k, cfg, norm))(jax.random.split(key, members))


def ensemble_size(params: PolicyParams) -> int:
    """N, the leading axis of an ensemble's leaves."""
    return int(jax.tree.leaves(params.net)[0].shape[0])


def member(params: PolicyParams, i: int) -> PolicyParams:
    """Member i of an ensemble (leaves lose the leading [N] axis)."""
    return jax.tree.map(lambda x: x[i], params)


def predict_sequence(cfg: PolicyConfig, params: PolicyParams, frames):
    """frames [L, S, O] raw, from a zero state -> normalized predicted actions [L, 8]."""
    return net_sequence(cfg, params.net, normalize_obs(params.norm, frames))


def _step_input(cfg: PolicyConfig, obs):
    """env.Obs -> the network input [S, O] (raw). Frames may be 13 or 16 wide (the env's
    World.ball_velocity_obs); they are converted to cfg.obs_size."""
    if cfg.kind == "lstm":
        return observation.to_width(obs.frame, cfg.obs_size, obs.ball_vel, xp=jnp)[None]
    if obs.frames.ndim != 2 or obs.frames.shape[0] != cfg.frame_stack:
        raise ValueError(f"policy: obs.frames has shape {tuple(obs.frames.shape)}, expected "
                         f"({cfg.frame_stack}, 13 or 16) for PolicyConfig.frame_stack={cfg.frame_stack}")
    return observation.to_width(obs.frames, cfg.obs_size, xp=jnp)


def make_policy(cfg: PolicyConfig) -> Policy:
    """A deterministic Policy for one member and one throw (params without a leading axis).

    Reads obs.frame [13 or 16] and obs.ball_vel [3] (lstm) or obs.frames [k, 13 or 16]
    (framestack); any object with those attributes works. The key is unused.
    """
    def init(params, key):
        return zero_carry(cfg)

    def apply(params, carry, obs, key):
        x = normalize_obs(params.norm, _step_input(cfg, obs))
        carry, a = net_step(cfg, params.net, carry, x)
        return carry, denormalize_actions(params.norm, a)

    return Policy(init, apply)


def with_action_noise(policy: Policy, scale: float) -> Policy:
    """Exploration ("New Results"): a + z, z ~ U(-b a_std, b a_std) drawn ONCE per episode.

    The carry is (inner carry, z [8]); z is drawn in init from the key and added unchanged to
    every action of the episode. a_std = params.norm.act_std, the action std of the data.
    """
    def init(params, key):
        k_inner, k_noise = jax.random.split(key)
        bound = scale * params.norm.act_std
        z = jax.random.uniform(k_noise, (ACTION_SIZE,), minval=-bound, maxval=bound)
        return policy.init(params, k_inner), z

    def apply(params, carry, obs, key):
        inner, z = carry
        inner, a = policy.apply(params, inner, obs, key)
        return (inner, z), a + z

    return Policy(init, apply)
