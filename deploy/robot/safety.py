"""What may be sent to the robot: the command filter and the fault codes.

Every command passes, in this order:
  1. finite check: a non-finite action (NaN/Inf anywhere) holds the last target;
  2. joint-range clamp to [lower, upper];
  3. step limit: |target - last target| <= max_speed * speed_margin * min(dt, time since the last
     command), so neither a late tick nor two ticks close together (clock jitter) can ask for
     more than the speed limits allow;
and stale or implausible input data hold the last target before the policy is consulted (the
runner's job, see deploy/robot/runner.py). The filter never uses joint feedback: a feedback fault can
mislead the policy but can never widen what is sent.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from deploy.robot.contract import Contract

# Fault bits (a tick's faults are OR-ed into an int32 in the episode log).
FAULTS = {
    "policy_nonfinite": 1 << 0,   # NaN/Inf action
    "policy_error": 1 << 1,       # the policy raised or returned a wrong shape
    "joint_stale": 1 << 2,        # newest joint sample older than the bound (or none)
    "joint_nonfinite": 1 << 3,
    "joint_jump": 1 << 4,         # feedback moved faster than the joints can
    "joint_out_of_range": 1 << 5, # feedback outside the ranges by more than a tolerance
    "joint_time": 1 << 6,         # joint timestamp from the future or going backwards
    "ball_stale": 1 << 7,         # newest ball sample older than the bound (or none)
    "ball_dropped": 1 << 8,       # a ball sample rejected (non-finite, implausible, bad time)
    "skipped": 1 << 9,            # the tick's deadline passed before it could run
    "overrun": 1 << 10,           # the command left after the next deadline
    "command_range": 1 << 11,     # the action was clamped to the joint ranges
    "command_step": 1 << 12,      # the action was limited by the speed limits
    "joint_mismatch": 1 << 13,    # settled feedback far from the last command (moving home)
    "robot_fault": 1 << 14,       # the robot's own drivers report a device fault (Robot.fault())
}
# Faults that stop the episode (the runner enters HOLD). The others are handled in the tick.
LATCHING = (FAULTS["policy_nonfinite"] | FAULTS["policy_error"] | FAULTS["joint_stale"]
            | FAULTS["joint_nonfinite"] | FAULTS["joint_jump"] | FAULTS["joint_out_of_range"]
            | FAULTS["joint_time"] | FAULTS["ball_stale"] | FAULTS["joint_mismatch"]
            | FAULTS["robot_fault"])


def fault_names(bits: int) -> list[str]:
    """The names of the faults set in `bits`."""
    return [name for name, b in FAULTS.items() if bits & b]


class Limits(NamedTuple):
    """Joint limits as the filter uses them ([8] each, float64)."""
    lower: np.ndarray
    upper: np.ndarray
    speed: np.ndarray     # max_speed * speed_margin
    dt: float             # control period (s)

    @property
    def max_step(self) -> np.ndarray:
        """[8] the largest change of target in one control tick."""
        return self.speed * self.dt


def limits_from_contract(c: Contract) -> Limits:
    return Limits(np.asarray(c.lower, np.float64), np.asarray(c.upper, np.float64),
                  np.asarray(c.max_speed, np.float64) * c.speed_margin, c.dt)


def part_limits(limits: Limits, joints: slice) -> Limits:
    """The limits of some joints only (e.g. slice(0, 2): the gantry's), for safe_target."""
    return Limits(limits.lower[joints], limits.upper[joints], limits.speed[joints], limits.dt)


class Command(NamedTuple):
    """The filter's output for one tick."""
    target: np.ndarray    # [8] what may be sent
    faults: int           # policy_nonfinite / command_range / command_step bits


def safe_target(limits: Limits, action, last_target: np.ndarray, elapsed: float | None = None,
                speed_scale: float = 1.0) -> Command:
    """[8] target within the joint ranges and one speed-limited step of last_target [8].

    action: the policy's [8] output (anything: it is checked here); with the limits of some of
    the joints only (Limits of [k] arrays, e.g. the gantry's 2 in drivers/lead.py), [k] of them.
    elapsed: seconds since the last command was sent (None = a full tick). speed_scale <= 1
    slows the step (moving home).
    """
    last = np.asarray(last_target, np.float64)
    a = np.asarray(action, np.float64)
    faults = 0
    if a.shape != limits.lower.shape or not np.all(np.isfinite(a)):
        return Command(last.copy(), FAULTS["policy_nonfinite"])
    clamped = np.clip(a, limits.lower, limits.upper)
    if np.any(clamped != a):
        faults |= FAULTS["command_range"]
    dt = limits.dt if elapsed is None else min(max(float(elapsed), 0.0), limits.dt)
    step = limits.speed * dt * min(max(speed_scale, 0.0), 1.0)
    delta = np.clip(clamped - last, -step, step)
    if np.any(delta != clamped - last):
        faults |= FAULTS["command_step"]
    # The final clip matters only if last_target itself were out of range (never, by induction).
    return Command(np.clip(last + delta, limits.lower, limits.upper), faults)


class Violations(NamedTuple):
    """Counts of commands that broke a limit (all must be zero)."""
    nonfinite: int
    range: int            # outside [lower, upper]
    step: int             # changed by more than one tick's max_step
    rate: int             # changed faster than speed over the time between the two commands
    first: int            # the first command too far from where the robot actually was


def count_violations(limits: Limits, times: np.ndarray, commands: np.ndarray,
                     start: np.ndarray | None = None, tol: float = 1e-9) -> Violations:
    """Check a log of sent commands (times [N], commands [N, 8]) against the limits.

    start [8]: the robot's true joints when the first command was sent (optional).
    """
    q = np.asarray(commands, np.float64).reshape(-1, 8)
    t = np.asarray(times, np.float64).reshape(-1)
    finite = np.all(np.isfinite(q), axis=1)
    out = np.any((q < limits.lower - tol) | (q > limits.upper + tol), axis=1)
    d = np.abs(np.diff(q, axis=0))
    step = np.any(d > limits.max_step + tol, axis=1)
    dt = np.minimum(np.diff(t), limits.dt)[:, None]
    rate = np.any(d > limits.speed * dt + tol, axis=1)
    first = 0
    if start is not None and len(q):
        first = int(np.any(np.abs(q[0] - start) > limits.max_step + tol))
    return Violations(int(np.sum(~finite)), int(np.sum(out)), int(np.sum(step)),
                      int(np.sum(rate)), first)
