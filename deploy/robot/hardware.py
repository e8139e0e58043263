"""The hardware the runner talks to, as three small interfaces, and the real-time clock.

All timestamps are seconds on ONE time base, the runner's `Clock`: a driver whose device stamps
samples with its own clock converts them before returning them (the runner compares sample
times with `clock.now()` to decide whether data are stale).

Fakes for tests (simple kinematics, fake time) live in deploy/robot/fakes.py; the simulated station
(MuJoCo C + thrower) implements the same interfaces.
"""
from __future__ import annotations

import time
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Seconds on the runner's time base (monotonic)."""

    def sleep_until(self, t: float) -> None:
        """Return at or after time t (immediately if t has passed)."""


@runtime_checkable
class Robot(Protocol):
    """8 joints in JOINT_NAMES order (gantry in m, arm in rad)."""

    def read(self) -> tuple[float, np.ndarray]:
        """(timestamp, q [8]): the newest joint feedback sample."""

    def send(self, q: np.ndarray) -> None:
        """Command absolute joint position targets q [8]."""

    # Optional: `fault() -> str | None`, the name of a device fault the drivers latched (motors
    # off, a drive fault) or None; the runner reads it with every joint sample (robot_fault,
    # HOLD). Robots without it report faults as non-finite joints only.


@runtime_checkable
class BallTracker(Protocol):
    def read(self) -> tuple[np.ndarray, np.ndarray]:
        """(t [n], xyz [n, 3]): the ball samples received since the previous call, oldest first
        (n = 0 when none; a 125 Hz tracker gives ~6 per 20 Hz tick)."""


class MonotonicClock:
    """The real clock: time.monotonic, sleeping until ~1 ms before a deadline, then spinning
    (time.sleep alone overshoots by up to a scheduler quantum)."""

    def __init__(self, spin_s: float = 0.001):
        self.spin_s = spin_s

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, t: float) -> None:
        while True:
            left = t - time.monotonic()
            if left <= 0:
                return
            if left > self.spin_s:
                time.sleep(left - self.spin_s)
