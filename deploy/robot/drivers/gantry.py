"""The Festo two-axis gantry over Modbus TCP: a pipelined Modbus TCP client of its own (function
3, read holding registers; function 16, write multiple registers) on one TCP connection.

The drive is a Modbus TCP server (this computer connects to it). A background thread, never the
control tick, does every transaction, and never waits for a reply before sending: Modbus TCP
pairs each reply with its request by the MBAP transaction id, so several requests may be in
flight on the connection, and TCP keeps them in order.

* Each new position target is written the moment the runner sets it (with the fixed positioning
  velocity and a toggled new-setpoint bit), whatever is in flight: not behind an outstanding
  read, not behind the previous target's write. Over a link that delays every message by d, a
  target reaches the drive after d, not after d plus the rest of a read (a request/reply client
  on one connection, pymodbus's ModbusTcpClient before, took ~1.5 d: at d = 10 ms and 100 Hz
  polls the link was always busy with a read, so each target waited for that read's reply,
  and a target set while the previous one's write was in flight was replaced before it left).
* poll_hz times a second, on a schedule of its own, it reads the actual positions and the status
  word, with at most one read in flight (a poll due while one is in flight goes when its reply
  arrives); each reading is stamped with the runner's clock at receipt; a reply a poll period
  later than the drive usually answers has its position dropped (gantry_late_reply: it cannot be
  placed in time), its status word still read.
* A request with no reply within timeout_s is logged (gantry_transaction) and the connection is
  opened anew; a reply whose transaction id is not in flight (a stale reply) is dropped, never
  taken for another request's.
* The drive starts a target when its new-setpoint bit differs from the one it holds. Replies
  come in order, so the driver follows the drive's bit from them (and from the status word's
  acknowledge bit where they cannot tell: at start, after a connection was dropped with a write
  in flight); the newest target, if the drive refused it (busy, gateway: not carried out) or it
  started nothing (a write before it in flight was refused, so it carried the drive's own bit),
  is sent again with the bit the drive does not hold, unless the runner has set a newer one.
* Every reply's round trip (reads and writes, from the request's send) goes to `link`
  (drivers/lead.py, LinkLatency): the link's latency, whose excess over the arm's own the
  cell's Robot leads the gantry's targets by (drivers/cell.py).

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
import select
import socket
import struct
import threading
import time

import numpy as np
from pymodbus.client import ModbusTcpClient

from deploy.robot.drivers.config import GantryConfig, Registers
from deploy.robot.drivers.faults import FaultLog
from deploy.robot.drivers.history import SampleHistory
from deploy.robot.drivers.lead import LinkLatency
from deploy.robot.hardware import Clock

ENABLE, NEW_SETPOINT = 1, 2                 # control bits
READY, FAULT, ACK = 1, 2, 4                 # status bits
INT32 = ModbusTcpClient.DATATYPE.INT32      # pymodbus's int32 <-> registers conversion only
HISTORY = 32                                # readings kept for read_at (0.32 s at 100 Hz)
MAX_LATE_DROPS = 2                          # late replies dropped in a row (_late), at most
READ_HOLDING, WRITE_MULTIPLE = 3, 16        # Modbus function codes
MBAP = struct.Struct(">HHHB")               # transaction id, protocol id (0), length, unit id
# Exception codes after which the drive did not carry the request out and may if asked again
# (server busy; gateway path unavailable; gateway target failed to respond): a write is resent.
TRANSIENT = frozenset({0x06, 0x0A, 0x0B})
# Requests in flight, at most: a server queues only so many (Modbus TCP servers commonly take
# a handful per connection). At 100 Hz writes and poll_hz reads with replies due within
# timeout_s (50 ms), ~6 are ever in flight; past this a new target waits for a reply.
MAX_IN_FLIGHT = 16


def encode_int32(value: int, regs: Registers) -> list[int]:
    return ModbusTcpClient.convert_to_registers(int(value), INT32, word_order=regs.word_order)


def decode_int32(words, regs: Registers) -> int:
    return int(ModbusTcpClient.convert_from_registers(list(words), INT32, word_order=regs.word_order))


def to_counts(m: float, regs: Registers) -> int:
    c = round(float(m) * regs.counts_per_m)
    if not -2 ** 31 <= c < 2 ** 31:
        raise ValueError(f"gantry target {m} m is {c} counts, outside int32")
    return c


def connect(cfg: GantryConfig) -> socket.socket:
    """A TCP connection to the drive (OSError if it cannot be made within timeout_s). Nagle's
    algorithm off: a request must leave at once, not wait for the previous segment's ACK."""
    s = socket.create_connection((cfg.host, cfg.port), timeout=cfg.timeout_s)
    s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    s.setblocking(False)
    return s


class ModbusGantry:
    """The gantry's 2 axes (m) over Modbus TCP, served by a thread of its own (start() / close())."""

    def __init__(self, cfg: GantryConfig, clock: Clock, faults: FaultLog | None = None):
        self.cfg, self.regs, self.clock = cfg, cfg.registers, clock
        self.faults = faults if faults is not None else FaultLog()
        try:
            self._sock: socket.socket | None = connect(cfg)
        except OSError:
            raise ValueError(f"gantry: cannot connect to the Modbus TCP drive at {cfg.host}:{cfg.port} "
                             f"(unreachable host, or nothing listening)") from None
        self._lock = threading.Lock()
        self.sample: tuple[float, np.ndarray] | None = None      # (receipt time, q [2] m)
        self.history = SampleHistory(HISTORY)                  # recent readings
        self.latched: str | None = None
        self._pending: np.ndarray | None = None                # the newest target not yet sent
        self._toggle = 0                                       # the new-setpoint bit last sent
        self._drive_bit: int | None = None     # the drive's, from the replies (None: not known)
        self.reads = self.writes = self.errors = self.stale_replies = 0
        self._rtts: collections.deque = collections.deque(maxlen=32)   # recent read round trips (s)
        # every reply's round trip (reads and writes): the link's latency, for the lead that
        # makes up for its excess (drivers/lead.py; the runner's send reads it)
        self.link = LinkLatency(cfg.forward_share)
        self._late_in_row = 0
        # Only the gantry thread touches these: the requests in flight by transaction id, each
        # (kind, time.monotonic() when sent, what it carried); the read in flight; targets sent.
        self._in_flight: dict[int, tuple] = {}
        self._tid = 0
        self._poll_tid: int | None = None
        self._write_seq = 0
        self._rx = b""
        self._stop = threading.Event()
        self._wake_r, self._wake_w = socket.socketpair()       # a new target (or close) wakes select
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
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
        """New position target q [2] m: the thread writes it at once, whatever is in flight."""
        q = np.asarray(q, np.float64)
        for v in q:
            to_counts(v, self.regs)
        with self._lock:
            self._pending = q.copy()
        self._wake()

    def _wake(self) -> None:
        try:
            self._wake_w.send(b"\0")
        except (BlockingIOError, OSError):      # already woken (a full pipe), or closing
            pass

    # ------------------------------------------------------------------ the gantry thread
    def _loop(self) -> None:
        period, nxt = 1.0 / self.cfg.poll_hz, time.monotonic()
        retry_at = -np.inf                      # the next connection attempt, while there is none
        while not self._stop.is_set():
            now = time.monotonic()
            if self._sock is None and now >= retry_at:
                if not self._reconnect():
                    retry_at = now + period
            if self._sock is not None:
                try:
                    self._write_pending()       # a new target leaves now, whatever is in flight
                    if now >= nxt and self._poll_tid is None:
                        nxt = max(nxt + period, now)
                        self._send_poll()
                except (OSError, ValueError) as e:
                    self._drop_connection(f"send: {type(e).__name__}: {e}")
            self._expire(time.monotonic())
            # sleep until a reply, a new target, the next poll or the oldest request's deadline
            wake = [retry_at if self._sock is None else (nxt if self._poll_tid is None else np.inf)]
            wake += [sent + self.cfg.timeout_s for _, sent, _ in self._in_flight.values()]
            waits = [self._wake_r] + ([self._sock] if self._sock is not None else [])
            ready, _, _ = select.select(waits, [], [], min(max(0.0, min(wake) - time.monotonic()), 0.1))
            if self._wake_r in ready:
                try:
                    while self._wake_r.recv(4096):
                        pass
                except (BlockingIOError, OSError):
                    pass
            if self._sock is not None and self._sock in ready:
                self._receive()

    def _send(self, kind: str, pdu: bytes, what) -> int:
        """Send one request now; returns its transaction id."""
        self._tid = self._tid % 0xFFFF + 1
        while self._tid in self._in_flight:     # (65,535 in flight: never; kept exact anyway)
            self._tid = self._tid % 0xFFFF + 1
        frame = MBAP.pack(self._tid, 0, len(pdu) + 1, self.cfg.device_id) + pdu
        self._sock.sendall(frame)
        self._in_flight[self._tid] = (kind, time.monotonic(), what)
        return self._tid

    def _write_pending(self) -> None:
        if len(self._in_flight) >= MAX_IN_FLIGHT:
            return                              # the drive's queue is full: sent at the next reply
        with self._lock:
            q, self._pending = self._pending, None
        if q is None:
            return
        r = self.regs
        # The bit the drive does not hold: the drive's own, once every write has been answered
        # (_written follows it); else the one after the last sent (that write presumed started).
        writing = any(kind == "write" for kind, _, _ in self._in_flight.values())
        held = self._drive_bit if self._drive_bit is not None and not writing else self._toggle
        self._toggle = held ^ NEW_SETPOINT
        velocity = int(min(round(self.cfg.velocity_m_s * 1000.0), 65535))
        block = {r.target_x: encode_int32(to_counts(q[0], r), r),
                 r.target_y: encode_int32(to_counts(q[1], r), r),
                 r.velocity: [velocity], r.control: [ENABLE | self._toggle]}
        runs = _runs([(addr, block[addr]) for addr in sorted(block)])   # one request where contiguous
        self._write_seq += 1
        for i, (addr, values) in enumerate(runs):
            pdu = struct.pack(f">BHHB{len(values)}H", WRITE_MULTIPLE, addr, len(values), 2 * len(values), *values)
            has_control = addr <= r.control < addr + len(values)
            self._send("write", pdu, (addr, len(values), q, self._toggle, has_control, self._write_seq))

    def _send_poll(self) -> None:
        r = self.regs
        lo = min(r.actual_x, r.actual_y, r.status)
        n = max(r.actual_x + 2, r.actual_y + 2, r.status + 1) - lo
        self._poll_tid = self._send("read", struct.pack(">BHH", READ_HOLDING, lo, n), (lo, n))

    def _receive(self) -> None:
        """Every complete reply now in the socket, each matched to its request by transaction id."""
        try:
            data = self._sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as e:
            self._drop_connection(f"receive: {type(e).__name__}: {e}")
            return
        if not data:
            self._drop_connection("the drive closed the connection")
            return
        now, mono = self.clock.now(), time.monotonic()
        self._rx += data
        while len(self._rx) >= MBAP.size:
            tid, proto, length, unit = MBAP.unpack_from(self._rx)
            if proto != 0 or length < 2:
                self._drop_connection(f"not a Modbus TCP reply (protocol id {proto}, length {length})")
                return
            if len(self._rx) < 6 + length:
                return                          # the rest of this reply is still on its way
            pdu, self._rx = self._rx[MBAP.size:6 + length], self._rx[6 + length:]
            request = self._in_flight.pop(tid, None)
            if request is None:                 # a reply to nothing in flight: dropped
                self.stale_replies += 1
                self.faults.add(now, "gantry", "gantry_transaction", f"stale reply (transaction {tid}): dropped")
                continue
            kind, sent, what = request
            self.link.add(mono - sent)
            if kind == "read":
                self._poll_tid = None
            try:
                self._reply(kind, mono - sent, what, unit, pdu, now)
            except ValueError as e:
                self._error(now, f"{kind}: {e}")

    def _reply(self, kind: str, rtt: float, what, unit: int, pdu: bytes, now: float) -> None:
        """Carry out one reply: a write acknowledged or refused, a reading taken (rtt: s since
        its request left)."""
        fc = READ_HOLDING if kind == "read" else WRITE_MULTIPLE
        if unit != self.cfg.device_id or pdu[0] & 0x7F != fc:
            raise ValueError(f"reply from unit {unit} with function {pdu[0]}, expected unit "
                             f"{self.cfg.device_id} function {fc}")
        if kind == "write":
            self._written(what, None if not pdu[0] & 0x80 else (pdu[1] if len(pdu) > 1 else -1), now)
            return
        if pdu[0] & 0x80:
            self._error(now, f"read at {what[0]}: exception code {pdu[1] if len(pdu) > 1 else -1:#04x}")
            return
        lo, n = what
        if len(pdu) != 2 + 2 * n or pdu[1] != 2 * n:
            raise ValueError(f"read at {lo}: {len(pdu) - 2} bytes of registers, expected {2 * n}")
        self._reading(list(struct.unpack(f">{n}H", pdu[2:])), lo, rtt, now)

    def _written(self, what, code: int | None, now: float) -> None:
        """A write's reply (code: its exception code, None if carried out). The drive starts a
        target when its new-setpoint bit differs from the one it holds; a write it refused
        leaves that bit, so a write sent after it in flight carries the drive's own bit and
        starts nothing. Replies come in order: the drive's bit is followed exactly here, and the
        newest target, if it was refused (transient: busy, gateway) or started nothing, is sent
        again with the bit the drive does not hold, unless the runner has set a newer one. An
        older target is never resent: a newer one is on its way."""
        addr, _, q, bit, has_control, seq = what
        if code is not None:
            self._error(now, f"write at {addr}: exception code {code:#04x}")
        if not has_control:
            return                              # a run without the control word starts nothing
        started = code is None and (self._drive_bit is None or bit != self._drive_bit)
        if code is None:
            self._drive_bit = bit               # what it holds now, started or not
            self.writes += started
        if seq == self._write_seq and not started and (code is None or code in TRANSIENT):
            with self._lock:
                self._pending = q if self._pending is None else self._pending

    def _reading(self, w: list[int], lo: int, rtt: float, now: float) -> None:
        r = self.regs
        status = w[r.status - lo]
        latched = "gantry_drive_fault" if status & FAULT or not status & READY else None
        if latched and not self.latched:
            self.faults.add(now, "gantry", latched, f"status word {status:#06x}")
        if latched:
            with self._lock:
                self.latched = self.latched or latched
        if self._drive_bit is None and not any(kind == "write" for kind, _, _ in self._in_flight.values()):
            self._drive_bit = NEW_SETPOINT if status & ACK else 0    # acknowledged: the bit it holds
        if self._late(rtt, now):
            return
        q = np.array([decode_int32(w[r.actual_x - lo:r.actual_x - lo + 2], r),
                      decode_int32(w[r.actual_y - lo:r.actual_y - lo + 2], r)]) / r.counts_per_m
        with self._lock:
            self.sample = (now, q)
            self.history.append(now, q)
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

    def _error(self, now: float, detail: str) -> None:
        self.errors += 1
        self.faults.add(now, "gantry", "gantry_transaction", detail)

    def _expire(self, now: float) -> None:
        """A request with no reply within timeout_s: logged, and the connection opened anew (the
        drive, or the link, has stopped answering; what it still holds is not waited for)."""
        late = [(kind, what) for kind, sent, what in self._in_flight.values() if now - sent > self.cfg.timeout_s]
        if late:
            kind, what = late[0]
            self._drop_connection(f"{kind} at {what[0]}: no reply within {1000 * self.cfg.timeout_s:g} ms "
                                  f"({len(self._in_flight)} in flight)")

    def _drop_connection(self, detail: str) -> None:
        """Log the failure, close the connection and forget what was in flight on it (its replies
        cannot arrive on the next one); the loop connects again."""
        self._error(self.clock.now(), detail)
        if self._sock is not None:
            self._sock.close()
        if any(kind == "write" for kind, _, _ in self._in_flight.values()):
            self._drive_bit = None              # a write's fate unknown: the status word tells
        self._sock, self._rx, self._poll_tid = None, b"", None
        self._in_flight.clear()

    def _reconnect(self) -> bool:
        try:
            self._sock = connect(self.cfg)
            return True
        except OSError as e:
            self._error(self.clock.now(), f"connect to {self.cfg.host}:{self.cfg.port}: {e.strerror or e}")
            return False

    def close(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if self._sock is not None:
            self._sock.close()
        self._wake_r.close()
        self._wake_w.close()


def _runs(words: list[tuple[int, list[int]]]) -> list[tuple[int, list[int]]]:
    """Join (address, values) entries sorted by address into contiguous runs."""
    out: list[tuple[int, list[int]]] = []
    for addr, values in words:
        if out and out[-1][0] + len(out[-1][1]) == addr:
            out[-1] = (out[-1][0], out[-1][1] + list(values))
        else:
            out.append((addr, list(values)))
    return out
