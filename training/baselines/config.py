"""The RL baselines' reward (training/baselines/env.py) and brax trainers' settings
(training/baselines/agents.py), apart from brax so that the command line can offer their fields
as flags (`ttmjx baseline ppo --ppo.num-envs 12000 --ppo.num-minibatches 96`) without importing
brax."""
from __future__ import annotations

import dataclasses
import math


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """The RL baselines' reward, per control step (the paper names the terms, not their weights):

        r = goal * exp(-d / goal_scale)        once, at the landing (d: landing to goal, metres)
          + hit                                once, at the first paddle contact
          + opponent                           once, when the first bounce after the hit is on the
                                               opponent's half
          - pose * mean_j ((q_j - home_j) / reach_j)^2       every step (arm pose, in [0, 1])
          - smooth * mean_j ((u_j - u_prev_j) / max_step_j)^2  every step (action change, in [0, 1])

    Every weight must be finite and >= 0 (a negative weight rewards the opposite of the task);
    goal_scale must be finite and > 0. With the defaults a return to the goal is worth ~2, a hit
    that lands anywhere on the opponent's half ~1 + exp(-d/0.3), and the style terms together at
    most 2 * 0.001 * horizon = 0.32 over an episode of flailing.
    """
    goal: float = 1.0
    """Weight of the closeness of the landing to the goal."""
    goal_scale: float = 0.3
    """Distance (m) at which the closeness term falls to 1/e."""
    hit: float = 0.5
    """Weight of the first paddle contact."""
    opponent: float = 0.5
    """Weight of the first bounce after the hit on the opponent's half."""
    pose: float = 0.001
    """Weight of the per-step arm-pose penalty."""
    smooth: float = 0.001
    """Weight of the per-step action-change penalty."""
    end_at_landing: bool = False
    """Done at the world's episode end (landing); False: at the horizon (exact trajectory counts)."""

    def __post_init__(self):
        for name in ("goal", "hit", "opponent", "pose", "smooth"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"reward weight {name}={v!r}; expected a finite number >= 0")
        if not isinstance(self.goal_scale, (int, float)) or not math.isfinite(self.goal_scale) or self.goal_scale <= 0:
            raise ValueError(f"reward goal_scale={self.goal_scale!r}; expected a finite number > 0")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """brax.training.agents.ppo.train arguments (Playground-like values for MJX tasks).

    One training step is batch_size * num_minibatches sequences of unroll_length steps, i.e.
    num_minibatches * batch_size / num_envs = 8 unrolls of 20 steps of every environment: exactly
    one 160-step episode of each of the 4,000 environments, 4,000 trajectories, so every batch
    holds every phase of the throw and any multiple of 4,000 trajectories (120,000 included) is
    run exactly."""
    num_envs: int = 4000
    unroll_length: int = 20
    batch_size: int = 1000
    num_minibatches: int = 32
    num_updates_per_batch: int = 4
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-2
    discounting: float = 0.99
    clipping_epsilon: float = 0.2
    init_noise_std: float = 0.5
    value_hidden: tuple[int, ...] = (256, 256, 256)

    def __post_init__(self):
        for name in ("num_envs", "unroll_length", "batch_size", "num_minibatches", "num_updates_per_batch"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"ppo.{name}={v!r}; expected an integer >= 1")
        if self.batch_size * self.num_minibatches % self.num_envs:
            raise ValueError(f"ppo: batch_size x num_minibatches ({self.batch_size} x {self.num_minibatches}) must be a "
                             f"multiple of num_envs ({self.num_envs}): brax collects whole unrolls of every environment")


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """brax.training.agents.sac.train arguments.

    No Q-network size: brax's make_sac_networks takes one hidden_layer_sizes for the policy and
    the Q networks, so the Q networks are the policy's MLP size (the run's PolicyConfig.hidden x
    layers). A separate size would need a network factory of our own; the field that claimed one
    (q_hidden) was ignored and is gone."""
    num_envs: int = 256
    batch_size: int = 512
    grad_updates_per_step: int = 8
    min_replay_size: int = 65_536
    max_replay_size: int = 2_000_000
    learning_rate: float = 3e-4
    discounting: float = 0.99

    def __post_init__(self):
        for name in ("num_envs", "batch_size", "grad_updates_per_step", "min_replay_size", "max_replay_size"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"sac.{name}={v!r}; expected an integer >= 1")


@dataclasses.dataclass(frozen=True)
class ESConfig:
    """brax.training.agents.es.train arguments (2 * population_size episodes per update: 2,000, so
    120,000 trajectories are 60 updates exactly)."""
    population_size: int = 1000
    perturbation_std: float = 0.02
    learning_rate: float = 0.01
    init_noise_std: float = 0.05
    """Std of the actions ES samples in its rollouts (brax ES acts stochastically); also perturbed."""
    checkpoint_every: int = 1
    """ES epochs between checkpoints of the whole state (training/baselines/es.py); curve points
    are always saved."""

    def __post_init__(self):
        for name in ("population_size", "checkpoint_every"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"es.{name}={v!r}; expected an integer >= 1")
