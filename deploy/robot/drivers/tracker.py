"""The ball tracker's UDP stream: one datagram per sample.

Wire format (36 bytes, network byte order, struct "!Idddd"):

    offset  size  field
    0       4     seq   uint32, +1 per sample (wraps at 2**32)
    4       8     t     float64, the sample's time in seconds on the tracker's clock
    12      8     x     float64, metres, table frame (ttmjx.world: x toward the opponent, z up)
    20      8     y     float64
    28      8     z     float64

The tracker sends to this computer's port (TrackerConfig.port); there is no reply. A sample's
time on the runner's clock is t + offset_s (TrackerConfig.offset_s: 0 when the tracker stamps
with this computer's CLOCK_MONOTONIC, as `ttmjx robot serve` does; else the measured offset,
docs/ROBOT.md). A datagram of another length, a non-finite value, or a sequence number not
newer than the last is dropped and logged; the runner rejects samples from the future or out of
the plausible volume (deploy/robot/runner.py), so a bad stream ends in a stale ball and HOLD.
"""
from __future__ import annotations

import errno
import math
import socket
import struct

import numpy as np

from deploy.robot.drivers.config import TrackerConfig
from deploy.robot.drivers.faults import FaultLog
from deploy.robot.hardware import Clock

WIRE = struct.Struct("!Idddd")
SEQ_MOD = 2 ** 32


def pack_sample(seq: int, t: float, xyz) -> bytes:
    """One datagram: seq (mod 2**32), time t (s), position xyz [3] (m)."""
    x, y, z = (float(v) for v in xyz)
    return WIRE.pack(seq % SEQ_MOD, float(t), x, y, z)


def unpack_sample(buf: bytes) -> tuple[int, float, np.ndarray]:
    """(seq, t, xyz [3]); ValueError naming what is wrong with the datagram."""
    if len(buf) != WIRE.size:
        raise ValueError(f"tracker datagram of {len(buf)} bytes, expected {WIRE.size}")
    seq, t, x, y, z = WIRE.unpack(buf)
    if not all(math.isfinite(v) for v in (t, x, y, z)):
        raise ValueError(f"tracker sample {seq} has non-finite values {(t, x, y, z)}")
    return seq, t, np.array([x, y, z])


def bind_udp(host: str, port: int, what: str) -> socket.socket:
    """A non-blocking UDP socket bound to (host, port); ValueError naming the port if taken."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind((host, port))
    except OSError as e:
        s.close()
        if e.errno == errno.EADDRINUSE:
            raise ValueError(f"{what} port {port} is already in use (another runner or server?)") from None
        raise ValueError(f"{what}: cannot bind {host}:{port} ({e.strerror or e})") from None
    s.setblocking(False)
    return s


class UdpTracker:
    """deploy.robot.hardware.BallTracker over the UDP stream: read() drains the socket."""

    def __init__(self, cfg: TrackerConfig, clock: Clock, faults: FaultLog | None = None):
        self.cfg, self.clock = cfg, clock
        self.faults = faults if faults is not None else FaultLog()
        self.sock = bind_udp("0.0.0.0", cfg.port, "tracker")
        self.last_seq: int | None = None
        self.received = self.dropped = 0

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        ts, xs = [], []
        while True:
            try:
                buf = self.sock.recv(2048)
            except (BlockingIOError, InterruptedError):
                break
            self.received += 1
            sample = self._accept(buf)
            if sample is not None:
                ts.append(sample[0])
                xs.append(sample[1])
        return np.asarray(ts, np.float64), np.asarray(xs, np.float64).reshape(-1, 3)

    def _accept(self, buf: bytes) -> tuple[float, np.ndarray] | None:
        """The sample (runner time, xyz) of one datagram, or None (logged) if it is bad."""
        try:
            seq, t, xyz = unpack_sample(buf)
        except ValueError as e:
            return self._drop("tracker_malformed", str(e))
        if self.last_seq is not None:
            ahead = (seq - self.last_seq) % SEQ_MOD
            if ahead == 0 or ahead > SEQ_MOD // 2:
                return self._drop("tracker_seq_old", f"seq {seq} after {self.last_seq}")
            if ahead > 1:
                self.faults.add(self.clock.now(), "tracker", "tracker_seq_gap", f"{ahead - 1} lost before {seq}")
        self.last_seq = seq
        return t + self.cfg.offset_s, xyz

    def _drop(self, name: str, detail: str) -> None:
        self.dropped += 1
        self.faults.add(self.clock.now(), "tracker", name, detail)
        return None

    def close(self) -> None:
        self.sock.close()
