"""Configuration of the learning core (the trainer and practice loop add their own)."""
from __future__ import annotations

import dataclasses
import math
from typing import Literal

PRACTICE_KEEP = ("hits", "near_half")
PRACTICE_GOALS = ("uniform", "frontier")   # where practice goals are drawn (training.frontier)
NOISE_FORMS = ("offset", "integrating")    # how action noise is applied (training.practice)
UPDATE_DTYPES = ("float32", "bfloat16")    # the arithmetic of the updates (training.loss)
LSTM_KERNELS = ("auto", "scan", "cudnn")    # how the updates run the LSTM (training.loss.lstm_kernel)
# Practice goals farther than this beyond the table's edges (m) are not goals a return can aim at
# (the opponent's half is 1.37 m deep and 1.525 m wide).
MAX_GOAL_MARGIN = 1.0


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    # Sub-sequence length k of every training window; the hit step is always inside it.
    # Paper: 96 at 100 Hz in simulation, 16 at 20 Hz on the robot.
    window: int = 96
    batch_size: int = 64                 # windows per member per update
    learning_rate: float = 1e-4          # Adam (not given in the paper)
    grad_clip: float = 1.0               # global-norm clipping of each member's gradient
    members: int = 1                     # ensemble size N (paper: 10 in simulation, 5 real)
    capacity: int = 131_072              # episodes the on-device cache holds (FIFO beyond)
    # Relabeled goals (landing points) of demonstrations and robot logs are kept for training up
    # to this far outside the opponent's half, in metres (and practice episodes with
    # practice_keep="near_half").
    goal_margin: float = 0.3
    # Practice goals are uniform over the opponent's half extended this far (m) beyond its end
    # line and side lines (ttmjx.world.goals.goals_from_unit); evaluation goals stay on the table.
    # Paper, Sec. III (Method): "extending the permissible goals in training beyond the physical
    # boundaries of the table improved performance in simulation by ~20% when the goal is less
    # than 20cm from the edges". The paper gives no margin; 0.2 m spans that band.
    practice_goal_margin: float = 0.2
    # How practice goals are drawn: "uniform" over the half extended by practice_goal_margin (the
    # paper); "frontier", a share frontier_fraction of each round's goals moved to the least dense
    # of the pool's achieved landings, jittered, within the same region (MEGA, arXiv 2007.02832;
    # training.frontier): goals just beyond what the policy reaches, where a uniform draw rarely
    # aims.
    practice_goals: Literal[PRACTICE_GOALS] = "uniform"
    # Share of each round's practice goals drawn from the frontier with practice_goals="frontier"
    # (the rest stay uniform, so that every region keeps being practised).
    frontier_fraction: float = 0.5
    # Which practice episodes join the cache: "hits", every hit ball with a landing (paper,
    # "Continuous improvement through self-supervised practice": an episode "is processed and
    # filtered out if ... the ball was not hit"); "near_half", only hits landing within
    # goal_margin of the opponent's half (this project's earlier filter).
    practice_keep: Literal[PRACTICE_KEEP] = "hits"
    action_noise: float = 0.0            # b of the per-episode uniform action noise
    # How it is applied (models.policy): "offset", a calibration offset the policy cannot see
    # (this project's own method); "integrating", the paper's a + z as written, which the closed
    # loop integrates.
    action_noise_form: Literal[NOISE_FORMS] = "offset"
    # The acting policy is an exponential moving average of the trained weights with this
    # decay per update (0: the weights themselves).
    ema_decay: float = 0.0
    # Each training window comes from a demonstration with probability at least this (0: rows
    # uniform over the whole pool, as in the paper); see training.sampler.sample_episodes.
    demo_fraction: float = 0.0
    # Landing-balanced sampling: each training row is drawn with weight count ** -balance, count
    # the pool's episodes whose landing lies in its cell (training.sampler.balanced_weights);
    # 0: uniform over rows (the paper), 1: uniform over the places landed on.
    balance: float = 0.0
    min_std: float = 1e-3                # floor of normalization stds
    # The arithmetic of each update's forward and backward pass: float32, or bfloat16 (the
    # network's weights and inputs cast to bfloat16 for the products; the weights themselves,
    # Adam's moments and the loss stay float32). Rollouts and evaluations act in float32.
    update_dtype: Literal[UPDATE_DTYPES] = "float32"
    # How the updates run an LSTM policy over its windows: "scan", a lax.scan of the cell (every
    # backend); "cudnn", cuDNN's LSTM (models.cudnn_lstm: a GPU, float32, one member of one
    # lane); "auto", cuDNN where all of that holds, else the scan. The same parameters and function either way; rollouts always step
    # the cell, and an MLP policy (framestack) has no recurrence to run either way.
    lstm_kernel: Literal[LSTM_KERNELS] = "auto"

    def __post_init__(self):
        for name in ("window", "batch_size", "members", "capacity"):
            if getattr(self, name) < 1:
                raise ValueError(f"TrainConfig.{name}={getattr(self, name)}, expected >= 1")
        for name in ("learning_rate", "grad_clip", "min_std"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TrainConfig.{name}={getattr(self, name)}, expected > 0")
        for name in ("goal_margin", "action_noise"):
            if getattr(self, name) < 0:
                raise ValueError(f"TrainConfig.{name}={getattr(self, name)}, expected >= 0")
        if not 0.0 <= self.practice_goal_margin <= MAX_GOAL_MARGIN:
            raise ValueError(f"TrainConfig.practice_goal_margin={self.practice_goal_margin}, expected metres "
                             f"in [0, {MAX_GOAL_MARGIN}] beyond the table's edges")
        if self.action_noise_form not in NOISE_FORMS:
            raise ValueError(f"TrainConfig.action_noise_form={self.action_noise_form!r}, expected one of {NOISE_FORMS}")
        if self.practice_goals not in PRACTICE_GOALS:
            raise ValueError(f"TrainConfig.practice_goals={self.practice_goals!r}, expected one of {PRACTICE_GOALS}")
        if not 0.0 <= self.frontier_fraction <= 1.0:
            raise ValueError(f"TrainConfig.frontier_fraction={self.frontier_fraction}, expected the share of each "
                             f"round's practice goals drawn from the frontier, in [0, 1]")
        if self.update_dtype not in UPDATE_DTYPES:
            raise ValueError(f"TrainConfig.update_dtype={self.update_dtype!r}, expected one of {UPDATE_DTYPES}")
        if self.lstm_kernel not in LSTM_KERNELS:
            raise ValueError(f"TrainConfig.lstm_kernel={self.lstm_kernel!r}, expected one of {LSTM_KERNELS}")
        if self.lstm_kernel == "cudnn" and self.update_dtype != "float32":
            raise ValueError(f"TrainConfig.lstm_kernel='cudnn' with update_dtype={self.update_dtype!r}: cuDNN's "
                             f"LSTM runs float32 only; expected update_dtype='float32' or lstm_kernel 'scan'/'auto'")
        if self.practice_keep not in PRACTICE_KEEP:
            raise ValueError(f"TrainConfig.practice_keep={self.practice_keep!r}, expected one of {PRACTICE_KEEP}")
        if not 0.0 <= self.demo_fraction <= 1.0:
            raise ValueError(f"TrainConfig.demo_fraction={self.demo_fraction}, expected in [0, 1]")
        if not 0.0 <= self.balance <= 2.0:
            raise ValueError(f"TrainConfig.balance={self.balance}, expected an exponent in [0, 2] "
                             f"(0: uniform rows, 1: uniform over the cells landed on)")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay={self.ema_decay}, expected in [0, 1)")

    @property
    def practice_keep_margin(self) -> float:
        """How far (m) outside the opponent's half a practice landing may lie and be kept:
        infinite for "hits" (training.data.keep_for_training keeps every hit that landed)."""
        return math.inf if self.practice_keep == "hits" else self.goal_margin
