"""Recent (receipt time, value) samples of one device, read at any time: what lets the cell's
Robot join two devices that report at different rates (deploy/robot/drivers/cell.py)."""
from __future__ import annotations

import collections

import numpy as np


class SampleHistory:
    """The newest `keep` samples (time, value [D]); not thread-safe (its owner locks)."""

    def __init__(self, keep: int):
        self.samples: collections.deque = collections.deque(maxlen=keep)

    def __len__(self) -> int:
        return len(self.samples)

    def append(self, t: float, q: np.ndarray) -> None:
        self.samples.append((float(t), np.asarray(q, np.float64)))

    def newest_time(self) -> float:
        return self.samples[-1][0] if self.samples else -np.inf

    def at(self, t: float, follow_s: float) -> np.ndarray | None:
        """value [D] at time t: interpolated between the two samples around t; past the newest,
        the line through the two newest followed at most follow_s, then held; before the oldest
        kept, the oldest (at start-up, before a history has built up). None if there is no
        sample. The same t gives the same value."""
        if not self.samples:
            return None
        ts = np.array([s[0] for s in self.samples])
        qs = np.array([s[1] for s in self.samples])
        if len(ts) < 2 or t <= ts[-1]:
            return np.array([np.interp(t, ts, qs[:, i]) for i in range(qs.shape[1])])
        dt = min(t - ts[-1], follow_s)
        return qs[-1] + (qs[-1] - qs[-2]) * (dt / max(ts[-1] - ts[-2], 1e-9))
