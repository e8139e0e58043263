"""The runtime contract between an exported policy and the robot runner.

Everything the runner must agree on with the policy and the robot: the control rate, the frame
stack, the observation size and the joint limits. deploy/sim/export.py writes it (the `runtime`
section of an export's contract.json, beside the robot id, layouts and hashes);
`contract_from_world` builds it from the simulation config.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ttmjx.world import observation
from ttmjx.world.config import JOINT_NAMES, Robot, World

# The paper's robot frame has no ball velocity (paper, Policy architecture): joints, ball position
# and goal, ttmjx.world.observation's narrow layout (13 values), the default. A 16-value frame adds
# the ball velocity as the tracker gives it: the slope of the line through its two newest samples,
# which is what the training world's timing model shows the policy too (ttmjx.world.env.sensed_frame).
REAL_OBS_SIZE = min(observation.WIDTHS)
OBS_SIZES = observation.WIDTHS
# The robot an export is made for (deploy/sim/export.py checks it at load): ABB IRB 120T on a
# two-axis gantry, joints JOINT_NAMES. Another robot (or a changed joint order) gets a new id.
ROBOT_MODEL_ID = "abb-irb120t-on-2axis-gantry/v1"
_ROBOT = Robot()
# The control rates a runner paces (Hz): a contract outside is refused at load (one claiming 1e9 Hz
# was accepted, and the fake station then ran until killed).
PACED_HZ = (1.0, 1000.0)


@dataclasses.dataclass(frozen=True)
class Contract:
    """Control rate, observation layout and joint limits (order = JOINT_NAMES)."""
    control_hz: float = 20.0          # 20 Hz (narrow/any balls), 60 Hz (varied balls) on the robot
    frame_stack: int = 8
    obs_size: int = REAL_OBS_SIZE
    episode_s: float = 1.6
    joint_names: tuple = JOINT_NAMES
    lower: tuple = _ROBOT.lower
    upper: tuple = _ROBOT.upper
    max_speed: tuple = _ROBOT.max_speed   # per joint, m/s (gantry) or rad/s (arm)
    speed_margin: float = _ROBOT.speed_margin  # fraction of max_speed commands may use
    home: tuple = _ROBOT.home
    home_noise: tuple = (0.0,) * 8    # per-episode start pose: home +- this (uniform), as trained
    extrapolate_s: float = 0.02       # how far past the newest sample the runner follows its line
                                      # (ttmjx.world.config.Timing.extrapolate_s of the training world)

    def __post_init__(self):
        if not PACED_HZ[0] <= self.control_hz <= PACED_HZ[1]:      # NaN too
            raise ValueError(f"Contract.control_hz={self.control_hz!r}: expected a rate the runner can pace, "
                             f"{PACED_HZ[0]:g} to {PACED_HZ[1]:g} Hz (ttmjx trains at 20, 60 or 100 Hz)")
        if self.frame_stack < 1:
            raise ValueError(f"Contract.frame_stack={self.frame_stack}, expected >= 1")
        if self.obs_size not in OBS_SIZES:
            raise ValueError(f"Contract.obs_size={self.obs_size}: the robot's frames hold {OBS_SIZES[0]} values "
                             f"(joints, ball position, goal) or {OBS_SIZES[1]} (with the tracker's ball velocity)")
        if not (isinstance(self.extrapolate_s, (int, float)) and 0 <= self.extrapolate_s < 1):
            raise ValueError(f"Contract.extrapolate_s={self.extrapolate_s!r}, expected seconds in [0, 1)")
        if not self.episode_s > 0:
            raise ValueError(f"Contract.episode_s={self.episode_s}, expected > 0")
        if tuple(self.joint_names) != JOINT_NAMES:
            raise ValueError(f"Contract.joint_names={tuple(self.joint_names)}, expected {JOINT_NAMES}")
        for name in ("lower", "upper", "max_speed", "home", "home_noise"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (8,) or not np.all(np.isfinite(v)):
                raise ValueError(f"Contract.{name} must be 8 finite numbers (one per joint "
                                 f"{JOINT_NAMES}), got {getattr(self, name)!r}")
        lo, hi = np.asarray(self.lower), np.asarray(self.upper)
        if np.any(lo >= hi):
            j = int(np.argmax(lo >= hi))
            raise ValueError(f"Contract: joint {JOINT_NAMES[j]} has lower={lo[j]} >= upper={hi[j]}")
        if np.any(np.asarray(self.home_noise) < 0):
            j = int(np.argmax(np.asarray(self.home_noise) < 0))
            raise ValueError(f"Contract.home_noise[{JOINT_NAMES[j]}]={self.home_noise[j]}, expected >= 0")
        if np.any(np.asarray(self.max_speed) <= 0):
            j = int(np.argmax(np.asarray(self.max_speed) <= 0))
            raise ValueError(f"Contract.max_speed[{JOINT_NAMES[j]}]={self.max_speed[j]}, expected > 0")
        if not 0 < self.speed_margin <= 1:
            raise ValueError(f"Contract.speed_margin={self.speed_margin}, expected in (0, 1]")
        home = np.asarray(self.home)
        if np.any((home < lo) | (home > hi)):
            j = int(np.argmax((home < lo) | (home > hi)))
            raise ValueError(f"Contract.home[{JOINT_NAMES[j]}]={home[j]} is outside [{lo[j]}, {hi[j]}]")

    @property
    def dt(self) -> float:
        """Control period (s)."""
        return 1.0 / self.control_hz

    @property
    def horizon(self) -> int:
        """Control ticks per episode."""
        return max(1, int(round(self.episode_s * self.control_hz)))


def contract_from_world(cfg: World, control_hz: float = 20.0) -> Contract:
    """The robot contract for a simulation config at the robot's policy rate.

    control_hz is separate from cfg.control_hz: the simulation runs at 100 Hz, the robot at 20 or
    60 Hz (60 Hz does not divide the 1 ms physics step, so it cannot be a World rate).
    """
    r = cfg.robot
    return Contract(control_hz=float(control_hz), frame_stack=cfg.frame_stack,
                    obs_size=cfg.obs_size,
                    extrapolate_s=float(cfg.timing.extrapolate_s), episode_s=cfg.episode_s, lower=tuple(r.lower), upper=tuple(r.upper),
                    max_speed=tuple(r.max_speed), speed_margin=r.speed_margin, home=tuple(r.home),
                    home_noise=tuple(r.home_noise))


def contract_to_dict(c: Contract) -> dict:
    """JSON-ready dict."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(c).items()}


def contract_from_dict(d: dict) -> Contract:
    """Inverse of contract_to_dict; unknown keys are an error naming them."""
    fields = {f.name for f in dataclasses.fields(Contract)}
    unknown = sorted(set(d) - fields)
    if unknown:
        raise ValueError(f"contract has unknown keys {unknown}; expected a subset of {sorted(fields)}")
    return Contract(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
