"""Policy architecture configuration."""
from __future__ import annotations

import dataclasses

POLICY_KINDS = ("lstm", "framestack")
OBS_SIZES = (13, 16)
ACTION_SIZE = 8


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """The network that maps observations (and the goal) to 8 joint position targets.

    lstm:       the paper's policy, `layers` stacked LSTM cells of `hidden` units and a linear
                head, stepped once per control step on the current frame.
    framestack: an MLP (`layers` hidden layers of `hidden` units, ReLU) on the last
                `frame_stack` frames flattened ("New Results": an (8, 13) observation).
    obs_size:   13 (joints, ball pos, goal) or 16 (joints, ball pos, ball vel, goal).
    """
    kind: str = "lstm"
    """lstm (the paper's policy) or framestack (an MLP on the last frame_stack frames)."""
    hidden: int = 1024
    """Units per layer."""
    layers: int = 2
    """LSTM cells or MLP hidden layers."""
    obs_size: int = 13
    """Values per frame: 13 (joints, ball position, goal) or 16 (with the ball velocity)."""
    frame_stack: int = 8
    """Frames the MLP sees (kind=framestack only)."""

    def __post_init__(self):
        if self.kind not in POLICY_KINDS:
            raise ValueError(f"PolicyConfig.kind={self.kind!r}; expected one of {POLICY_KINDS}")
        if self.obs_size not in OBS_SIZES:
            raise ValueError(f"PolicyConfig.obs_size={self.obs_size}; expected one of {OBS_SIZES}")
        if self.hidden < 1 or self.layers < 1:
            raise ValueError(f"PolicyConfig.hidden={self.hidden} and layers={self.layers} must be >= 1")
        if self.kind == "framestack" and self.frame_stack < 1:
            raise ValueError(f"PolicyConfig.frame_stack={self.frame_stack} must be >= 1")

    @property
    def input_frames(self) -> int:
        """Frames the network sees per control step: 1 for the LSTM, frame_stack for the MLP."""
        return self.frame_stack if self.kind == "framestack" else 1
