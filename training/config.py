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
