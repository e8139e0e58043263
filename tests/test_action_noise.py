"""Action noise in the closed loop: a trained policy (tests/data/tiny_run_v0,
member 1) on narrow throws with real MuJoCo C physics, noise-free against the per-episode offset
of models.policy.with_action_noise (a calibration offset the policy cannot see) and against the
withdrawn integrating form (with_integrating_action_noise: z added to every target while the
true joints are observed)."""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models.policy import make_policy, member, with_action_noise, with_integrating_action_noise, with_joint_offset
from training.checkpoint import load_checkpoint
from ttmjx.world import thrower
from ttmjx.world.backends import Backend
from ttmjx.world.env import Policy, uniform_goals
from ttmjx.world.goals import RADII, goal_metrics, scored_distance

RUN = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "tiny_run_v0")
N, B = 16, 0.1                  # throws; the noise scale b of the test
REVOLUTE = slice(2, 8)          # the arm's six joints (radians); 0, 1 are the gantry (metres)


def integrating_form(policy: Policy, z) -> Policy:
    """with_integrating_action_noise with a chosen z: a + z, the true joints observed."""
    return Policy(policy.init, lambda params, carry, obs, key: (lambda c, a: (c, a + z))(
        *policy.apply(params, carry, obs, key)))


@pytest.fixture(scope="module")
def world():
    """(params, backend, play) where play(policy) -> Trajectories on the same N throws and goals."""
    loaded = load_checkpoint(RUN)
    cfg, params = loaded.cfg, member(loaded.params, 1)
    k_throw, k_goal, k_roll = jax.random.split(jax.random.PRNGKey(0), 3)
    throws = thrower.sample_throws(k_throw, cfg.world, N)
    goals = np.asarray(uniform_goals(k_goal, N, cfg.world.table), np.float32)
    backend = Backend(cfg.world, "c")
    base = make_policy(cfg.policy)
    clean = backend.rollout_one(base, params, k_roll, throws, goals)
    return params, base, clean, lambda policy: backend.rollout_one(policy, params, k_roll, throws, goals)


def joint_gap(a, b, steps):
    """[N, steps] ||q_a - q_b|| of the TRUE recorded joints, 0 where either episode had ended."""
    both = (a.valid & b.valid)[:, :steps]
    gap = np.linalg.norm(np.asarray(a.obs[:, :steps, :8]) - np.asarray(b.obs[:, :steps, :8]), axis=-1)
    return np.where(both, gap, 0.0)


def test_held_offset_is_not_integrated(world):
    """Up to the strike, |q_noisy - q_clean| <= 2|z| with the calibration offset; far more without.

    The bound: with a target of "observed joint + increment d(q, ball)" and G = dd/dq, the gap
    e = q_noisy - q_clean obeys e' - z = (I + G)(e - z) from e = 0 (the robot starts where it
    stands), so a loop that pulls back to its own trajectory keeps |e - z| <= |z|, |e| <= 2|z|.
    The integrating form instead adds z at every step: e ~ t z, tens of |z| by the strike."""
    params, base, clean, play = world
    signs = np.where(np.arange(8) % 2 == 0, 1.0, -1.0)
    z = jnp.asarray(B * np.asarray(params.norm.act_std) * signs, jnp.float32)   # a corner of the box
    strike = int(clean.hit_step.max()) + 1          # the steps that decide where the ball goes
    assert clean.hit.mean() >= 0.75 and strike > 40
    held = joint_gap(play(with_joint_offset(base, lambda p, k: z)), clean, strike) / np.linalg.norm(z)
    drift = joint_gap(play(integrating_form(base, z)), clean, strike) / np.linalg.norm(z)
    print(f"max |q_noisy - q_clean| / |z| up to step {strike}: held {held.max():.2f}, "
          f"integrating {drift.max():.2f}")
    assert held.max() <= 2.0
    assert drift.max() > 2 * 2.0


def test_noise_changes_within_30cm_by_what_an_offset_can(world):
    """b = 0.1 moves a typical landing by less than s, and within 30 cm by at most the share of
    episodes a move of s can carry across the 30 cm circle.

    s: a uniform z turns the paddle face by about sum_j E|z_j| = sum_j b a_std_j / 2 over the
    revolute joints; a bounce off a face turned by that angle leaves at up to twice it, and the
    return flies at most the table's length (2.74 m). The old form moves landings by far more."""
    params, base, clean, play = world
    tilt = float(np.sum(B * np.asarray(params.norm.act_std)[REVOLUTE] / 2))
    s = 2 * 2.74 * tilt
    d0 = scored_distance(clean.landing, clean.goal, clean.hit, clean.on_opponent)
    reach = float(np.mean(np.abs(d0 - RADII[0]) <= s))
    base_m = goal_metrics(clean.landing, clean.goal, clean.hit, clean.on_opponent)
    shifts = {}
    for name, policy in (("held", with_action_noise(base, B)), ("integrating", with_integrating_action_noise(base, B))):
        tr = play(policy)
        m = goal_metrics(tr.landing, tr.goal, tr.hit, tr.on_opponent)
        shift = np.linalg.norm(np.asarray(tr.landing) - np.asarray(clean.landing), axis=1)
        shifts[name] = float(np.nanmedian(shift))
        print(f"{name}: within 30 cm {base_m['within_30cm']:.3f} -> {m['within_30cm']:.3f} (bound {reach:.3f}), "
              f"hit {base_m['hit_rate']:.3f} -> {m['hit_rate']:.3f}, median landing shift {shifts[name]:.3f} m "
              f"(s {s:.3f})")
        if name == "held":
            assert abs(m["within_30cm"] - base_m["within_30cm"]) <= reach
    assert shifts["held"] <= s < shifts["integrating"]
