"""The simulated station as `ttmjx robot serve` runs it (deploy/serve.py): deploy/station.py's
SimStation with two differences that the real cell's protocols call for.

* Two controllers. The arm (EGM) and the gantry (Modbus) are separate controllers: each half of
  a runner command reaches the station on its own protocol, at its own time, and each part
  ramps toward its own newest target from when that target arrived (+ the timing profile's
  action delay). SimStation.set_target ramps all 8 joints from one command, so feeding it the
  halves one after the other would restart the half that arrived first each time the other
  arrives (the arm's ramp restarted by every gantry write: the arm then lags by up to a gantry
  poll, which the in-process station never does). `set_part_target(part, q, now)` ramps one part.
* Lazy events. The served physics advances in real time about every millisecond; folding the
  new physics steps into the throw's events (a compiled JAX call, ~0.3 ms) at every such sync
  would cost the real-time loop more than the physics. Steps are folded once FOLD_CHUNK have
  gathered, before a launch or a park, and when the referee asks (`fold_events`), so the events
  are the same, found by the same rules, only later.
"""
from __future__ import annotations

import collections
import math

import numpy as np

from deploy.station import FOLD_CHUNK, SimStation

PARTS = {"gantry": slice(0, 2), "arm": slice(2, 8)}


class ServedStation(SimStation):
    """SimStation with per-part ramps and lazy event folding (module docstring)."""

    def _place_robot(self, q0) -> np.ndarray:
        q0 = super()._place_robot(q0)
        self._part_ramps = {name: collections.deque([(-math.inf, q0[p].copy(), q0[p].copy())], maxlen=64)
                            for name, p in PARTS.items()}
        return q0

    def set_part_target(self, part: str, q, now: float) -> None:
        """Part `part` (PARTS) of a command, arrived at `now`: its ramp starts action_delay_s later
        from where that part's earlier targets have it then; the other part is not touched."""
        p = PARTS[part]
        q = np.clip(np.asarray(q, np.float64), self.cfg.robot.lower[p], self.cfg.robot.upper[p])
        start = now + self.action_delay_s
        self._part_ramps[part].append((start, self._part_at(part, start), q))

    def set_target(self, q: np.ndarray, now: float) -> None:
        """All 8 joints (both parts, the same arrival time)."""
        q = np.asarray(q, np.float64)
        for part, p in PARTS.items():
            self.set_part_target(part, q[p], now)

    def _part_at(self, part: str, t: float) -> np.ndarray:
        for t0, q_from, q_to in reversed(self._part_ramps[part]):
            if t0 <= t + 1e-12:
                break
        w = 1.0 if self.ramp_s <= 0 else float(np.clip((t - t0) / self.ramp_s, 0.0, 1.0))
        return q_from + w * (q_to - q_from)

    def _ctrl_at(self, t: float) -> np.ndarray:
        out = np.empty(8)
        for part, p in PARTS.items():
            out[p] = self._part_at(part, t)
        return out

    def part_targets(self) -> dict:
        """{part: its newest target} (what the controllers were last told)."""
        return {part: r[-1][2].copy() for part, r in self._part_ramps.items()}

    # ------------------------------------------------------------------ lazy events
    def _fold_track(self) -> None:
        if len(self._track) >= FOLD_CHUNK:
            super()._fold_track()

    def fold_events(self) -> None:
        """Fold every step taken so far into the throw's events (before reading them)."""
        SimStation._fold_track(self)

    def _launch(self, t: float) -> None:
        self.fold_events()
        super()._launch(t)

    def _park(self) -> None:
        self.fold_events()
        super()._park()
