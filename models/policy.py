"""Policies for rollouts (docs/DESIGN.md `Policy`), parameters and ensembles.

`PolicyParams` = network weights + the fixed `Normalizer`. An ensemble of N members is ONE
`PolicyParams` whose every leaf has a leading [N] axis; it is created, trained and applied with
vmap. A `Policy` is written for one member and one throw; batch it with vmap.
"""
from __future__ import annotations

import functools

from typing import Any, Callable, NamedTuple

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


@functools.lru_cache(maxsize=None)
def make_policy(cfg: PolicyConfig) -> Policy:
    """A deterministic Policy for one member and one throw (params without a leading axis).

    Reads obs.frame [13 or 16] and obs.ball_vel [3] (lstm) or obs.frames [k, 13 or 16]
    (framestack); any object with those attributes works. The key is unused.

    One Policy object per configuration (cached): compiled rollouts are cached by the policy
    they play, so every evaluation of a run reuses the first one's program instead of tracing
    and compiling the whole rollout again.
    """
    def init(params, key):
        return zero_carry(cfg)

    def apply(params, carry, obs, key):
        x = normalize_obs(params.norm, _step_input(cfg, obs))
        carry, a = net_step(cfg, params.net, carry, x)
        return carry, denormalize_actions(params.norm, a)

    return Policy(init, apply)


def uniform_offset(key, scale: float, act_std):
    """[8] z ~ U(-b a_std, b a_std) ("New Results"), b = scale, a_std [8] the data's action std."""
    bound = scale * act_std
    return jax.random.uniform(key, (ACTION_SIZE,), minval=-bound, maxval=bound)


def shift_joints(obs, delta):
    """obs with the joint columns of its frame and frame stack moved by delta [8] (the ball,
    its velocity and the goal unchanged); any Obs-like NamedTuple with frame, frames."""
    move = lambda f: f.at[..., observation.JOINTS].add(delta.astype(f.dtype))  # noqa: E731
    return obs._replace(frame=move(obs.frame), frames=move(obs.frames))


def with_joint_offset(policy: Policy, draw: Callable) -> Policy:
    """The robot held z away from where the policy believes it is: a calibration offset.

    draw: (params, key) -> z [8], once per episode (in init). The inner policy is shown the
    joints shifted by -z and its action is sent shifted by +z, so it acts in its own frame and
    the executed trajectory is its usual one moved by z. The carry is (inner carry, z).
    """
    def init(params, key):
        k_inner, k_offset = jax.random.split(key)
        return policy.init(params, k_inner), draw(params, k_offset)

    def apply(params, carry, obs, key):
        inner, z = carry
        inner, a = policy.apply(params, inner, shift_joints(obs, -z), key)
        return (inner, z), a + z

    return Policy(init, apply)


def with_action_noise(policy: Policy, scale: float) -> Policy:
    """Exploration ("New Results"): the paper's a + z, z ~ U(-b a_std, b a_std) drawn ONCE per
    episode (b = scale, a_std = params.norm.act_std), applied as a calibration offset
    (with_joint_offset) that the policy cannot see.

    Why not a + z with the true joints observed: the trained policies act as "target = observed
    joint + small increment", so a held z added to every target moves the robot by z again at
    every control step and the closed loop integrates it into a drift (docs/DESIGN.md,
    "Measurements behind the code"). Hiding z from
    the observation leaves the paper's intent: one held perturbation of the executed
    trajectory, of size |z|, for the whole rollout. The rollout records the TRUE frames and the
    EXECUTED command (inner action + z, clipped), so every relabeled (observation, action,
    landing) triple is one the world really produced.
    """
    return with_joint_offset(policy, lambda params, key: uniform_offset(key, scale, params.norm.act_std))


def with_integrating_action_noise(policy: Policy, scale: float) -> Policy:
    """The paper's form as written ("New Results"): a + z on every target with the true joints
    observed, z held for the episode; the closed loop here integrates it (see with_action_noise).
    `ttmjx ablate noise` runs it as the paper-bX variants."""
    return with_held_target_offset(policy, lambda params, key: uniform_offset(key, scale, params.norm.act_std))


def with_held_target_offset(policy: Policy, draw: Callable) -> Policy:
    """z = draw(params, key), once per episode, added to every target with the true joints
    observed (the integrating form). The carry is (inner carry, z)."""
    def init(params, key):
        k_inner, k_noise = jax.random.split(key)
        return policy.init(params, k_inner), draw(params, k_noise)

    def apply(params, carry, obs, key):
        inner, z = carry
        inner, a = policy.apply(params, inner, obs, key)
        return (inner, z), a + z

    return Policy(init, apply)


class NoisyParams(NamedTuple):
    """A policy's parameters with the scale b of its held action noise as data: for the lanes
    of one program whose b differs (training.seeds). `scale` [] (or [N] beside an ensemble's [N]
    leaves)."""
    params: Any
    scale: Any


def with_lane_action_noise(policy: Policy, form: str) -> Policy:
    """with_action_noise (form 'offset') or with_integrating_action_noise ('integrating') with b
    read from NoisyParams instead of written in: the same draws and arithmetic, b = 0 exact."""
    inner = Policy(lambda p, key: policy.init(p.params, key), lambda p, c, obs, key: policy.apply(p.params, c, obs, key))
    draw = lambda p, key: uniform_offset(key, p.scale, p.params.norm.act_std)  # noqa: E731
    return (with_joint_offset if form == "offset" else with_held_target_offset)(inner, draw)
