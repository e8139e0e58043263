"""The gantry link's latency, measured, and the lead that makes up for its excess (issue 49).

The policy was trained with one command delay for all 8 joints (the export's timing record,
`action_delay_s`: the cell's command to motion). Over the cell's protocols the arm's target
waits for the controller's next EGM message (half a 4 ms cycle on average) and the gantry's
goes at once over Modbus TCP (~0.5 ms on loopback, docs/ROBOT.md "Timing over the protocols");
neither is in the trained delay. A slow gantry link (e.g. `serve --faults modbus.delay_ms=10`)
makes every gantry target arrive late on top of it: the gantry's 2 axes lag the arm's 6 by more
than anything the policy saw (37.5% within 30 cm in process, 20% with the 10 ms link).

What is done about it, on the gantry only (an EGM reply always carries the newest target, so the
arm's own wait is bounded by one cycle and is not compensated):

* LinkLatency: the gantry driver pairs every reply with its request (Modbus TCP transaction
  id), so each transaction's round trip is known. The link's one-way latency to the drive is
  `forward_share` (config, [gantry]) times the running median of the recent round trips (a
  median: one stall of this machine or of the drive moves it by nothing). Its EXCESS is what
  is above ALLOWANCE_S, the arm's own average wait for its EGM cycle: a gantry target no later
  than that is no later than the arm's, and the policy played over loopback sockets at its
  in-process score (docs/RESULTS.md). So on a link as fast as nominal the excess is 0.
* GantryLead: each gantry target is sent extrapolated forward by that excess from the recent
  targets' velocity (first order: q + v * excess, v from the last two targets; the feed-forward
  half of a Smith predictor), then through the same safety filter as every command
  (deploy.robot.safety.safe_target on the gantry's 2 joints: range, and the speed limit from the
  last target actually sent), so a late link sends where the target will be when it arrives,
  never faster or further than the limits allow. An excess of 0 sends the target unchanged.

`forward_share` says how the round trip splits: 0.5 on a symmetric network (the default: what
PTP or NTP assume too); 1.0 on the rehearsal server's link, which delays requests only
(deploy/sim/serve.py, Server.modbus_link: the reply leaves when the request is carried out), so
loopback_config() sets it. A link whose round trip cannot be split so (one leg much longer than
the other) should have it set from a measurement of the cell.
"""
from __future__ import annotations

import collections
import threading

import numpy as np

from deploy.robot.drivers.config import EGM_CYCLE_S
from deploy.robot.safety import Limits, safe_target

# s, the latency a gantry target may have without a lead: the arm's average wait for its next
# EGM cycle (half a cycle), which every arm target has too. Measured over loopback sockets, the
# gantry's transport p50 is ~0.5 ms and its round trip ~1 ms: below this, so nominal gets no lead.
ALLOWANCE_S = EGM_CYCLE_S / 2
# s, the largest lead: a link later than this has left the trained timing far behind (the
# export's command delay spreads +-10 ms), and a first-order prediction from two targets so far
# ahead mostly extrapolates their noise. The excess is still reported in full.
MAX_LEAD_S = 0.025
WINDOW = 64          # round trips in the running median (~0.3 s at 100 Hz writes and reads)
MIN_REPLIES = 8      # round trips before any estimate (none: no lead)


class LinkLatency:
    """The running median of the gantry transactions' round trips and what it implies, thread
    safe (the gantry thread adds, the runner's send reads)."""

    def __init__(self, forward_share: float, window: int = WINDOW):
        if not 0.0 < forward_share <= 1.0:
            raise ValueError(f"forward_share = {forward_share}: expected a share of the round trip in (0, 1]")
        self.forward_share = float(forward_share)
        self._rtts: collections.deque = collections.deque(maxlen=window)
        self._lock = threading.Lock()
        self._rtt_p50 = float("nan")

    def add(self, rtt_s: float) -> None:
        """One transaction's round trip (s, request sent to reply received)."""
        with self._lock:
            self._rtts.append(float(rtt_s))
            if len(self._rtts) >= MIN_REPLIES:
                self._rtt_p50 = float(np.median(self._rtts))

    def rtt_s(self) -> float:
        """The median round trip (s) of the recent replies; NaN before MIN_REPLIES."""
        return self._rtt_p50

    def forward_s(self) -> float:
        """The link's one-way latency to the drive (s): forward_share x the median round trip."""
        return self.forward_share * self._rtt_p50

    def excess_s(self) -> float:
        """The forward latency above ALLOWANCE_S (s, >= 0; 0 before MIN_REPLIES)."""
        f = self.forward_s()
        return max(0.0, f - ALLOWANCE_S) if np.isfinite(f) else 0.0

    def report(self) -> dict:
        """The estimate now, in ms (session summaries)."""
        return {"rtt_p50_ms": _ms(self.rtt_s()), "forward_ms": _ms(self.forward_s()),
                "excess_ms": 1e3 * self.excess_s(), "forward_share": self.forward_share,
                "allowance_ms": 1e3 * ALLOWANCE_S}


def extrapolated(q: np.ndarray, q_prev: np.ndarray | None, interval_s: float, lead_s: float) -> np.ndarray:
    """q [n] moved lead_s (s) ahead along the velocity of the last two targets, (q - q_prev) /
    interval_s (s between them); q itself without a previous target or a lead."""
    q = np.asarray(q, np.float64)
    if q_prev is None or lead_s <= 0.0:
        return q.copy()
    return q + (q - np.asarray(q_prev, np.float64)) / interval_s * lead_s


class GantryLead:
    """The gantry's targets as sent: led by the link's excess latency (module docstring).

    limits: the contract's limits of the gantry's joints (Limits with [2] arrays; its dt the
    control period). enabled False: every target is sent as given (the comparison's opt-out,
    [gantry] compensate_latency = false)."""

    def __init__(self, limits: Limits, enabled: bool = True):
        self.limits, self.enabled = limits, bool(enabled)
        self._given: tuple[float, np.ndarray] | None = None     # (time, target) last given
        self._sent: tuple[float, np.ndarray] | None = None      # (time, target) last sent
        self.leads: collections.deque = collections.deque(maxlen=100_000)   # s, per target
        self.shifts: collections.deque = collections.deque(maxlen=100_000)  # m, |sent - given|
        self.limited = 0                    # led targets the safety filter changed

    def target(self, q: np.ndarray, t: float, excess_s: float) -> np.ndarray:
        """What to send for the runner's gantry target q [2] (m) given at t (s, runner clock)
        over a link excess_s (s) later than the allowance."""
        q = np.asarray(q, np.float64)
        lead = min(max(float(excess_s), 0.0), MAX_LEAD_S) if self.enabled else 0.0
        caught_up = self._sent is None or np.array_equal(self._sent[1], self._given[1])
        if lead == 0.0 and caught_up:
            out = q.copy()                  # the runner's filtered target, unchanged
        else:
            prev, interval = (None, 1.0) if self._given is None else (
                self._given[1], max(t - self._given[0], self.limits.dt))
            # (an interval shorter than a control period, two sends close together, is taken
            # as one period: the velocity is then under-, never over-estimated)
            cmd = safe_target(self.limits, extrapolated(q, prev, interval, lead),
                              self._sent[1] if self._sent is not None else q,
                              None if self._sent is None else t - self._sent[0])
            out = cmd.target
            self.limited += bool(cmd.faults)
        self._given, self._sent = (t, q.copy()), (t, out.copy())
        self.leads.append(lead)
        self.shifts.append(float(np.max(np.abs(out - q))))
        return out

    def report(self) -> dict:
        """The leads applied so far (session summaries): counts, ms and mm."""
        leads, shifts = np.asarray(self.leads), np.asarray(self.shifts)
        led = leads > 0
        return {"enabled": self.enabled, "targets": int(leads.size), "led": int(led.sum()),
                "lead_p50_ms": 1e3 * float(np.median(leads)) if leads.size else 0.0,
                "lead_max_ms": 1e3 * float(leads.max()) if leads.size else 0.0,
                "shift_p50_mm": 1e3 * float(np.median(shifts[led])) if led.any() else 0.0,
                "shift_max_mm": 1e3 * float(shifts.max()) if shifts.size else 0.0,
                "limited": self.limited, "max_lead_ms": 1e3 * MAX_LEAD_S}


def _ms(s: float) -> float | None:
    return 1e3 * s if np.isfinite(s) else None
