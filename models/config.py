"""Policy architecture configuration."""
from __future__ import annotations

import dataclasses

POLICY_KINDS = ("lstm", "framestack")
HEADS = ("mean", "mixture")
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
    head:       mean (the paper: a linear head trained with the MSE, so it predicts the mean
                action of the data at each input) or mixture (`components` Gaussians with
                diagonal covariance, trained by their negative log-likelihood; the policy acts
                with the mean of its most probable component, so two strokes the relabelled
                data holds for one input are not averaged into a third).
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
    head: str = "mean"
    """mean (MSE, the paper) or mixture (a Gaussian mixture trained by likelihood)."""
    components: int = 5
    """Gaussians of the mixture head (head=mixture only)."""

    def __post_init__(self):
        if self.kind not in POLICY_KINDS:
            raise ValueError(f"PolicyConfig.kind={self.kind!r}; expected one of {POLICY_KINDS}")
        if self.obs_size not in OBS_SIZES:
            raise ValueError(f"PolicyConfig.obs_size={self.obs_size}; expected one of {OBS_SIZES}")
        if self.hidden < 1 or self.layers < 1:
            raise ValueError(f"PolicyConfig.hidden={self.hidden} and layers={self.layers} must be >= 1")
        if self.head not in HEADS:
            raise ValueError(f"PolicyConfig.head={self.head!r}; expected one of {HEADS}")
        if self.head == "mixture" and self.components < 1:
            raise ValueError(f"PolicyConfig.components={self.components} must be >= 1 for head='mixture'")
        if self.kind == "framestack" and self.frame_stack < 1:
            raise ValueError(f"PolicyConfig.frame_stack={self.frame_stack} must be >= 1")

    @property
    def input_frames(self) -> int:
        """Frames the network sees per control step: 1 for the LSTM, frame_stack for the MLP."""
        return self.frame_stack if self.kind == "framestack" else 1

    @property
    def head_size(self) -> int:
        """Outputs of the network's last layer: 8 action values (mean), or per component a
        logit, 8 means and 8 log standard deviations (mixture)."""
        return ACTION_SIZE if self.head == "mean" else self.components * (1 + 2 * ACTION_SIZE)
