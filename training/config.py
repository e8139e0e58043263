"""Configuration of the learning core (the trainer and practice loop add their own)."""
from __future__ import annotations

import dataclasses


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
    # Relabeled goals (landing points) are kept for training up to this far outside the
    # opponent's half, in metres; the paper found goals beyond the table edges help near them.
    goal_margin: float = 0.3
    action_noise: float = 0.0            # b of the per-episode uniform action noise
    # The acting policy is an exponential moving average of the trained weights with this
    # decay per update (0: the weights themselves).
    ema_decay: float = 0.0
    # Each training window comes from a demonstration with probability at least this (0: rows
    # uniform over the whole pool, as in the paper); see training.sampler.sample_episodes.
    demo_fraction: float = 0.0
    min_std: float = 1e-3                # floor of normalization stds

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
        if not 0.0 <= self.demo_fraction <= 1.0:
            raise ValueError(f"TrainConfig.demo_fraction={self.demo_fraction}, expected in [0, 1]")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"TrainConfig.ema_decay={self.ema_decay}, expected in [0, 1)")
