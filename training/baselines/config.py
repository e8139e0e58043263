"""The RL baselines' reward (training/baselines/env.py), apart from brax so that the command line
can offer its fields as flags without importing brax."""
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
