"""Timestamped samples and their linear interpolation to a control tick."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Interpolated(NamedTuple):
    """A value at time t and the two samples it came from (equal before the first sample)."""
    value: np.ndarray     # [d]
    slope: np.ndarray     # [d] per second between the two samples (the first two before them); 0 if one sample
    t_lo: float
    t_hi: float
    x_lo: np.ndarray      # [d]
    x_hi: np.ndarray      # [d]


def interpolate(times: np.ndarray, values: np.ndarray, t: float,
                max_extrapolate_s: float = 0.0) -> Interpolated:
    """Linear interpolation of samples (times [n] increasing, values [n, d]) at t.

    After the newest sample the line through the last two samples is followed for at most
    max_extrapolate_s, then held: with a tracker's few ms of latency the newest sample is usually
    just before the deadline, and holding it would show the policy a 7 m/s ball 3-8 cm behind.
    Before the oldest sample it is held. Staleness is judged elsewhere. The samples used are
    returned with the value: value = x_lo + slope * (clip(t, t_lo, t_hi + max_extrapolate_s) - t_lo)
    whenever t_hi > t_lo.
    """
    n = len(times)
    if n == 0:
        raise ValueError("interpolate: no samples")
    i = int(np.searchsorted(times, t, side="right"))   # times[i-1] <= t < times[i]
    if i == n and n >= 2:                                # after the newest: extrapolate (bounded)
        lo, hi = n - 2, n - 1
        t_eval = min(t, float(times[hi]) + max_extrapolate_s)
    else:
        lo, hi = max(i - 1, 0), min(i, n - 1)
        t_eval = t
    t_lo, t_hi = float(times[lo]), float(times[hi])
    x_lo, x_hi = values[lo], values[hi]
    if hi > lo:
        slope = (x_hi - x_lo) / (t_hi - t_lo)
        value = x_lo + slope * (max(t_eval, t_lo) - t_lo)
    else:
        value = x_lo.copy()
        slope = (values[1] - values[0]) / (times[1] - times[0]) if n >= 2 else np.zeros_like(x_lo)
    return Interpolated(value, slope, t_lo, t_hi, x_lo.copy(), x_hi.copy())


class SampleBuffer:
    """The last `capacity` accepted samples of a d-dimensional signal, oldest first."""

    def __init__(self, dim: int, capacity: int = 256):
        self.dim, self.capacity = dim, capacity
        self._t = np.empty(2 * capacity)
        self._x = np.empty((2 * capacity, dim))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def clear(self) -> None:
        self._n = 0

    def add(self, t: float, x: np.ndarray) -> None:
        """Append one sample (the caller checked that t increases and x is finite)."""
        if self._n == len(self._t):   # keep the newest `capacity`, shift once per `capacity` adds
            self._t[:self.capacity] = self._t[self._n - self.capacity:self._n]
            self._x[:self.capacity] = self._x[self._n - self.capacity:self._n]
            self._n = self.capacity
        self._t[self._n] = t
        self._x[self._n] = x
        self._n += 1

    @property
    def times(self) -> np.ndarray:
        """[n] sample times."""
        return self._t[:self._n]

    @property
    def values(self) -> np.ndarray:
        """[n, d] samples."""
        return self._x[:self._n]

    @property
    def newest_time(self) -> float:
        """Time of the newest sample, -inf when empty."""
        return float(self._t[self._n - 1]) if self._n else -np.inf

    @property
    def newest(self) -> np.ndarray | None:
        """[d] newest sample, None when empty."""
        return self._x[self._n - 1].copy() if self._n else None

    def at(self, t: float, max_extrapolate_s: float = 0.0) -> Interpolated:
        return interpolate(self.times, self.values, t, max_extrapolate_s)
