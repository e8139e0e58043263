"""The RL baselines' reward (training/baselines/env.py), brax trainers' settings
(training/baselines/agents.py) and QT-Opt's (training/baselines/qtopt.py), apart from brax so that the command line can offer their fields
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


@dataclasses.dataclass(frozen=True)
class QTOptConfig:
    """QT-Opt's settings (training/baselines/qtopt.py), each with its source. "QT-Opt" is
    Kalashnikov et al. 2018 (arXiv 1806.10293) as read when this baseline was written (the paper is not in this
    repository; its values below were not re-checked against its text in the session that wrote
    them); "TF-Agents" is tf_agents/agents/qtopt/qtopt_agent.py, the maintained implementation.
    None was tuned against the result.

    The defaults are the GPU scale of Table I's row (docs/RESULTS.md "The RL baselines"): 12,000
    environments as PPO's 5-seed program, so that 120,000 trajectories are 1,600 sequential
    actor steps, and a replay prefill of 48,000 steps, so that the 1,596 actor steps after it
    split into the 7 equal epochs of the 8 curve points every RL row has. Each actor step adds
    12,000 transitions and takes 8 gradient steps (SACConfig.grad_updates_per_step) of 1,500:
    every transition is replayed once on average. The scale is the session's compute, not
    QT-Opt's.

    Validated here: each count an integer >= 1, 2 <= cem_elites <= cem_population, a replay
    buffer that holds the prefill and one actor step, rates in their ranges; ValueError naming
    the field, its value and what is expected."""
    num_envs: int = 12_000
    """Environments stepped together per actor step (ours: the session's compute; PPO's 12,000)."""
    batch_size: int = 1_500
    """Transitions per gradient step (ours: with grad_updates_per_step, replay ratio 1)."""
    grad_updates_per_step: int = 8
    """Gradient steps per actor step (SACConfig's 8, this project's other off-policy row)."""
    min_replay_size: int = 48_000
    """Transitions collected before the first gradient step (ours: whole epochs, see above),
    rounded up to whole actor steps as brax's SAC does."""
    max_replay_size: int = 1_000_000
    """brax UniformSamplingQueue capacity (ours: ~1 GB of transitions per seed, saved with every
    checkpoint; the last ~83 actor steps of every environment, half an episode)."""
    learning_rate: float = 3e-4
    """Adam's step on the Q-function (SACConfig's, brax's SAC default)."""
    discounting: float = 0.9
    """QT-Opt's discount. At 100 Hz control it weighs a reward 10 steps (0.1 s) ahead by 0.35."""
    hidden: tuple[int, ...] = (256, 256)
    """Q-network MLP (brax make_q_network's default; SAC's paper's 2 x 256). QT-Opt's Q is a
    convolutional network on camera images, which does not carry over to the state observation;
    the policy's 2 x 1024 would make CEM's 128 Q evaluations per environment step ~12x dearer."""
    cem_iterations: int = 2
    """CEM iterations per argmax (QT-Opt: 2; TF-Agents' default 3)."""
    cem_population: int = 64
    """Actions sampled per CEM iteration (QT-Opt: 64; TF-Agents' default 32)."""
    cem_elites: int = 6
    """Best actions the next iteration's Gaussian is fitted to (QT-Opt: 6; TF-Agents' default 4)."""
    epsilon: float = 0.1
    """Probability of a uniformly random action instead of CEM's argmax while collecting
    (epsilon-greedy as QT-Opt; the value is TF-Agents' default epsilon_greedy)."""
    target_tau: float = 1e-4
    """Polyak step of the first target network per gradient step (QT-Opt: averaging constant 0.9999)."""
    target_lag: int = 6000
    """Gradient steps between refreshes of the second, lagged target network (QT-Opt: lagged by
    about 6,000 gradient steps); the target is the minimum of the two (clipped double Q)."""

    def __post_init__(self):
        for name in ("num_envs", "batch_size", "grad_updates_per_step", "min_replay_size", "max_replay_size",
                     "cem_iterations", "cem_population", "target_lag"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"qtopt.{name}={v!r}; expected an integer >= 1")
        if not isinstance(self.cem_elites, int) or not 2 <= self.cem_elites <= self.cem_population:
            raise ValueError(f"qtopt.cem_elites={self.cem_elites!r}; expected an integer from 2 (a Gaussian "
                             f"needs two elites for its spread) to cem_population ({self.cem_population})")
        if not self.hidden or any(not isinstance(h, int) or h < 1 for h in self.hidden):
            raise ValueError(f"qtopt.hidden={self.hidden!r}; expected one or more layer widths >= 1")
        prefill = -(-self.min_replay_size // self.num_envs) * self.num_envs
        if self.max_replay_size < prefill:
            raise ValueError(f"qtopt.max_replay_size={self.max_replay_size}; expected >= the prefill of "
                             f"{prefill} transitions (min_replay_size in whole actor steps of num_envs)")
        for name, ok, span in (("learning_rate", lambda v: v > 0, "> 0"), ("discounting", lambda v: 0 <= v < 1, "in [0, 1)"),
                               ("epsilon", lambda v: 0 <= v <= 1, "in [0, 1]"), ("target_tau", lambda v: 0 < v <= 1, "in (0, 1]")):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or not ok(v):
                raise ValueError(f"qtopt.{name}={v!r}; expected a finite number {span}")
