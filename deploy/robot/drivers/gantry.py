"""The Festo two-axis gantry over Modbus TCP, through pymodbus's ModbusTcpClient.

The drive is a Modbus TCP server (this computer connects to it). A background thread, never the
control tick, does every transaction: it writes each new position target as soon as the runner
sets it (with the fixed positioning velocity and a toggled new-setpoint bit; a target leaves
within a transaction, not up to a poll period late), and poll_hz times a second, on a schedule
of its own, reads the actual positions and the status word; each reading is stamped with the
runner's clock at receipt; a reply a poll period later than the drive usually answers has its
position dropped (gantry_late_reply: it cannot be placed in time), its status word still read.
The drive sees at most control_hz writes and poll_hz reads a second. A slow or lost transaction
only delays the thread: the runner keeps ticking and sees the gantry's newest sample go stale
(joint_stale, HOLD) if it lasts longer than stale_s.

The register map (config.Registers, one block of holding registers):

    target_x, target_y  int32 (2 registers each), position target in counts (counts_per_m)
    velocity            uint16, positioning velocity in mm/s
    control             uint16, bit 0 enable, bit 1 new setpoint (toggled with every target)
    actual_x, actual_y  int32, actual position in counts
    status              uint16, bit 0 ready, bit 1 fault, bit 2 setpoint acknowledged

This is this project's layout, modelled on what Festo's FHPP profile carries in its I/O data
(control bytes CCON/CPOS with enable and start/toggle bits, a position setpoint and a velocity
setpoint; status bytes SCON/SPOS with ready, fault and acknowledge bits, the actual position).
It is NOT the register numbering of a particular drive: before the first run, map each entry
onto the drive's manual (the Modbus address of its FHPP or direct-mode I/O, the word order of
32-bit values, the position unit and scaling, and which bit starts a positioning job) and put
those addresses in the cell config. `ttmjx robot serve` implements exactly this map.
"""
from __future__ import annotations

import collections
import logging
import threading
import time

import numpy as np
from pymodbus.client import ModbusTcpClient
from pymodbus.exceptions import ModbusException

from deploy.robot.drivers.config import GantryConfig, Registers
from deploy.robot.drivers.faults import FaultLog
from deploy.robot.drivers.history import SampleHistory
from deploy.robot.hardware import Clock

ENABLE, NEW_SETPOINT = 1, 2                 # control bits
READY, FAULT, ACK = 1, 2, 4                 # status bits
INT32 = ModbusTcpClient.DATATYPE.INT32
HISTORY = 32                                # readings kept for read_at (0.32 s at 100 Hz)
MAX_LATE_DROPS = 2                          # late replies dropped in a row (_late), at most


def encode_int32(value: int, regs: Registers) -> list[int]:
    return ModbusTcpClient.convert_to_registers(int(value), INT32, word_order=regs.word_order)


def decode_int32(words, regs: Registers) -> int:
    return int(ModbusTcpClient.convert_from_registers(list(words), INT32, word_order=regs.word_order))


def to_counts(m: float, regs: Registers) -> int:
    c = round(float(m) * regs.counts_per_m)
    if not -2 ** 31 <= c < 2 ** 31:
        raise ValueError(f"gantry target {m} m is {c} counts, outside int32")
    return c


class ModbusGantry:
    """The gantry's 2 axes (m) over Modbus TCP, served by a polling thread (start() / close())."""

    def __init__(self, cfg: GantryConfig, clock: Clock, faults: FaultLog | None = None):
        self.cfg, self.regs, self.clock = cfg, cfg.registers, clock
        self.faults = faults if faults is not None else FaultLog()
        self.client = ModbusTcpClient(cfg.host, port=cfg.port, timeout=cfg.timeout_s, retries=0)
        quiet = logging.getLogger("pymodbus.logging")       # its own line would precede ours
        level, quiet.level = quiet.level, logging.CRITICAL
        try:
            connected = self.client.connect()
        finally:
            quiet.setLevel(level)
        if not connected:
            self.client.close()
            raise ValueError(f"gantry: cannot connect to the Modbus TCP drive at {cfg.host}:{cfg.port} "
                             f"(unreachable host, or nothing listening)")
        self._lock = threading.Lock()
        self.sample: tuple[float, np.ndarray] | None = None      # (receipt time, q [2] m)
        self.history = SampleHistory(HISTORY)                  # recent readings
        self.latched: str | None = None
        self._pending: np.ndarray | None = None
        self._toggle = 0
        self.reads = self.writes = self.errors = 0
        self._rtts: collections.deque = collections.deque(maxlen=32)   # recent read round trips (s)
        self._late_in_row = 0
        self._stop = threading.Event()
        self._wake = threading.Event()             # a new target (or close)
        self._thread = threading.Thread(target=self._loop, name="gantry", daemon=True)

    def start(self) -> "ModbusGantry":
        self._thread.start()
        return self

    # ------------------------------------------------------------------ runner side
    def read(self) -> tuple[float, np.ndarray] | None:
        with self._lock:
            if self.sample is None:
                return None
            t, q = self.sample
            return t, (np.full(2, np.nan) if self.latched else q.copy())

    def read_at(self, t: float) -> np.ndarray | None:
        """q [2] m at time t from the recent readings (HISTORY): interpolated between the two
        around t, or the line through the two newest followed at most one poll period past the
        newest (so a 100 Hz reading joins a 250 Hz arm sample without lagging it by up to a
        poll); the oldest kept reading before it. The same t gives the same value."""
        with self._lock:
            if self.latched and self.history:
                return np.full(2, np.nan)
            return self.history.at(t, 1.0 / self.cfg.poll_hz)

    def set_target(self, q: np.ndarray) -> None:
        """New position target q [2] m: the thread writes it at once (its next transaction)."""
        q = np.asarray(q, np.float64)
        for v in q:
            to_counts(v, self.regs)
        with self._lock:
            self._pending = q.copy()
        self._wake.set()

    # ------------------------------------------------------------------ the polling thread
    def _loop(self) -> None:
        period, nxt = 1.0 / self.cfg.poll_hz, time.monotonic()
        while not self._stop.is_set():
            if time.monotonic() >= nxt:            # a read is due (and a pending target first)
                nxt = max(nxt + period, time.monotonic())
                self._cycle(read=True)
            elif self._wake.wait(max(0.0, nxt - time.monotonic())):
                self._wake.clear()                  # a new target: written now, not at the read
                self._cycle(read=False)

    def _cycle(self, read: bool) -> None:
        try:
            self._write_pending()
            if read:
                self._poll()
        except (ModbusException, OSError, ValueError) as e:
            self._error(e)

    def _write_pending(self) -> None:
        with self._lock:
            q, self._pending = self._pending, None
        if q is None:
            return
        r, words = self.regs, []
        self._toggle ^= NEW_SETPOINT
        velocity = int(min(round(self.cfg.velocity_m_s * 1000.0), 65535))
        block = {r.target_x: encode_int32(to_counts(q[0], r), r),
                 r.target_y: encode_int32(to_counts(q[1], r), r),
                 r.velocity: [velocity], r.control: [ENABLE | self._toggle]}
        for addr in sorted(block):          # one transaction where the map is contiguous
            words.append((addr, block[addr]))
        for addr, values in _runs(words):
            res = self.client.write_registers(addr, values, device_id=self.cfg.device_id)
            if res.isError():
                with self._lock:            # try again at the next transaction
                    self._pending = q if self._pending is None else self._pending
                raise ModbusException(f"write at {addr}: {res}")
        self.writes += 1

    def _poll(self) -> None:
        r = self.regs
        lo = min(r.actual_x, r.actual_y, r.status)
        n = max(r.actual_x + 2, r.actual_y + 2, r.status + 1) - lo
        sent = self.clock.now()
        res = self.client.read_holding_registers(lo, count=n, device_id=self.cfg.device_id)
        now = self.clock.now()
        if res.isError():
            raise ModbusException(f"read at {lo}: {res}")
        w = res.registers
        status = w[r.status - lo]
        latched = "gantry_drive_fault" if status & FAULT or not status & READY else None
        if latched and not self.latched:
            self.faults.add(now, "gantry", latched, f"status word {status:#06x}")
        if latched:
            with self._lock:
                self.latched = self.latched or latched
        if self._late(now - sent, now):
            return
        q = np.array([decode_int32(w[r.actual_x - lo:r.actual_x - lo + 2], r),
                      decode_int32(w[r.actual_y - lo:r.actual_y - lo + 2], r)]) / r.counts_per_m
        with self._lock:
            self.sample = (now, q)
            self.history.append(now, q)
            self.latched = self.latched or latched
        self.reads += 1

    def _late(self, rtt: float, now: float) -> bool:
        """Whether a read's position is dropped as late. The drive measured somewhere between
        the request and the receipt: a reply a poll period later than its usual answer (the
        median of recent round trips; a stall of the drive, the network or this process)
        cannot be placed in time, and stamped at receipt it would put an old position at a new
        time (a false jump). At most MAX_LATE_DROPS in a row: a drive that has become slower
        for good is then the usual (its status word is read either way)."""
        usual = float(np.median(self._rtts)) if self._rtts else rtt
        self._rtts.append(rtt)
        if rtt <= usual + 1.0 / self.cfg.poll_hz or self._late_in_row >= MAX_LATE_DROPS:
            self._late_in_row = 0
            return False
        self._late_in_row += 1
        self.faults.add(now, "gantry", "gantry_late_reply", f"{1000 * rtt:.1f} ms (usually {1000 * usual:.1f} ms)")
        return True

    def _error(self, e: Exception) -> None:
        self.errors += 1
        self.faults.add(self.clock.now(), "gantry", "gantry_transaction", f"{type(e).__name__}: {e}")
        # A fresh connection: a late reply to the failed request would otherwise be read as the
        # reply to the next one (Modbus TCP matches them by transaction id and skips, slowly).
        self.client.close()
        self.client.connect()

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.client.close()


def _runs(words: list[tuple[int, list[int]]]) -> list[tuple[int, list[int]]]:
    """Join (address, values) entries sorted by address into contiguous runs."""
    out: list[tuple[int, list[int]]] = []
    for addr, values in words:
        if out and out[-1][0] + len(out[-1][1]) == addr:
            out[-1] = (out[-1][0], out[-1][1] + list(values))
        else:
            out.append((addr, list(values)))
    return out
