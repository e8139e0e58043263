"""The drivers' fault log: what went wrong on the wire, per device, on the runner's clock.

The runner's own fault bits (deploy.robot.safety.FAULTS) say what the runner did about bad data (HOLD
on stale or non-finite joints, dropped ball samples); this log says why, in the device's terms
(a sequence gap on EGM, a Modbus timeout, a malformed tracker datagram). `ttmjx robot run
--station cell` copies the entries of each episode's time window into its log's meta
(`driver_faults`: counts by name, `driver_fault_events`: the first entries).
"""
from __future__ import annotations

import threading
from collections import Counter

# Faults after which the device must not be trusted until an operator looks (motors off, RAPID
# stopped, a drive fault): the Robot names it (fault(): robot_fault) and reports non-finite
# joints until then (joint_nonfinite); both hold the runner.
LATCHING = frozenset({"egm_motors_off", "egm_rapid_stopped", "gantry_drive_fault"})
MAX_EVENTS = 10_000     # kept entries (the counts go on past it)


class FaultLog:
    """Thread-safe (time, device, name, detail) entries and counts by name."""

    def __init__(self):
        self._lock = threading.Lock()
        self.events: list[tuple[float, str, str, str]] = []
        self.counts: Counter = Counter()

    def add(self, t: float, device: str, name: str, detail: str = "") -> None:
        with self._lock:
            self.counts[name] += 1
            if len(self.events) < MAX_EVENTS:
                self.events.append((float(t), device, name, detail))

    def between(self, t_from: float, t_to: float) -> list[tuple[float, str, str, str]]:
        """The entries with t_from <= t < t_to, oldest first."""
        with self._lock:
            return [e for e in self.events if t_from <= e[0] < t_to]


def window_summary(events: list, first: int = 50) -> dict:
    """{'driver_faults': {name: count}, 'driver_fault_events': the first `first` entries}."""
    counts = Counter(e[2] for e in events)
    return {"driver_faults": dict(counts),
            "driver_fault_events": [{"t": t, "device": d, "name": n, "detail": s}
                                    for t, d, n, s in events[:first]]}
