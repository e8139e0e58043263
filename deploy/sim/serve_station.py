"""The simulated station as `ttmjx robot serve` runs it (deploy/sim/serve.py): deploy/sim/station.py's
SimStation with two differences that the real cell's protocols call for.

* Two controllers. The arm (EGM) and the gantry (Modbus) are separate controllers: each half of
  a runner command reaches the station on its own protocol, at its own time, and ramps from its
  own arrival (SimStation.set_target with `part`; one 8-joint ramp would restart the arm at
  every gantry write).
* Lazy events. The served physics advances in real time about every millisecond; folding the
  new physics steps into the throw's events (a compiled JAX call, ~0.3 ms) at every such sync
  would cost the real-time loop more than the physics. Steps are folded once FOLD_CHUNK have
  gathered, before a launch or a park, and when the referee asks (`fold_events`), so the events
  are the same, found by the same rules, only later.
"""
from __future__ import annotations

from deploy.sim.station import FOLD_CHUNK, SimStation


class ServedStation(SimStation):
    """SimStation with per-part commands and lazy event folding (module docstring)."""

    def set_part_target(self, part: str, q, now: float) -> None:
        """Part `part` (deploy.sim.station.PARTS) of a command, arrived at `now` on its own protocol."""
        self.set_target(q, now, part)

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
