"""The runner's state machine.

    IDLE --move_home()--> HOMING --at home--> ARMED --ball in play--> RUNNING --horizon--> IDLE
                             |                  |                        |
                             +---- fault -------+------ fault -----------+--> HOLD
    HOLD --release()--> IDLE          HOLD --move_home()--> HOMING    (explicit commands only)

* IDLE: nothing is commanded; the robot holds its last target.
* HOMING: waits for `settle_reads` agreeing fresh joint samples, then moves, speed-limited, from
  the last target (at first: from the settled feedback) to the contract's home pose. Faults, a
  timeout, or feedback that disagrees with the last target by more than a tick's step -> HOLD.
* ARMED: at home, waiting for a ball moving toward the robot; stale joint data -> HOLD; no ball
  within the timeout leaves it ARMED (NoBallError); disarm() -> IDLE.
* RUNNING: the policy is stepped on a deadline-paced grid; the episode ends at the horizon
  (-> IDLE: the next episode starts with move_home) or on a latching fault (-> HOLD).
* HOLD: entered from anywhere on a fault or hold(); the last safe target is sent once and
  nothing else until an operator calls release() or move_home().
"""
from __future__ import annotations

import enum


class Mode(str, enum.Enum):
    IDLE = "idle"
    HOMING = "homing"
    ARMED = "armed"
    RUNNING = "running"
    HOLD = "hold"


TRANSITIONS = {
    Mode.IDLE: (Mode.HOMING, Mode.HOLD),
    Mode.HOMING: (Mode.ARMED, Mode.HOLD),
    Mode.ARMED: (Mode.RUNNING, Mode.IDLE, Mode.HOLD),
    Mode.RUNNING: (Mode.IDLE, Mode.HOLD),
    Mode.HOLD: (Mode.IDLE, Mode.HOMING, Mode.HOLD),
}


class TransitionError(RuntimeError):
    """A command that the current mode does not allow."""


class StateMachine:
    """The current mode and the history of transitions [(time, from, to, reason)]."""

    def __init__(self):
        self.mode = Mode.IDLE
        self.history: list[tuple[float, str, str, str]] = []

    def require(self, *modes: Mode, action: str) -> None:
        """Raise TransitionError unless the mode is one of `modes`."""
        if self.mode not in modes:
            raise TransitionError(f"{action} needs mode {' or '.join(m.value for m in modes)}, "
                                  f"but the runner is {self.mode.value}"
                                  + (" (call release() or move_home() first)" if self.mode == Mode.HOLD else ""))

    def to(self, new: Mode, t: float, reason: str = "") -> None:
        if new not in TRANSITIONS[self.mode]:
            raise TransitionError(f"no transition {self.mode.value} -> {new.value} ({reason}); "
                                  f"allowed: {[m.value for m in TRANSITIONS[self.mode]]}")
        self.history.append((float(t), self.mode.value, new.value, reason))
        self.mode = new
