"""`ttmjx robot serve`: the simulated station (deploy/sim/station.py, MuJoCo C physics, real time)
served over the real cell's protocols on this computer, so `ttmjx robot run --station cell`
rehearses the deployment over real sockets:

* EGM peer (UDP): as the ABB controller does, sends an EgmRobot message every EGM cycle (250 Hz)
  to the runner's EGM port (the controller initiates) with the arm's joints in degrees, motors
  on, RAPID running; takes the EgmSensor replies' planned joints as the arm's target.
* Modbus TCP server (pymodbus): behaves like the gantry drive of deploy/robot/drivers/gantry.py's
  register map: a write with a toggled new-setpoint bit is a new gantry target; reads return
  the actual positions and the status word. Each connection is a link (_DriveLink): requests
  may be pipelined (several in flight, replies matched by transaction id, as Modbus TCP allows);
  each is taken off the wire on arrival, delayed by the link's faults from its arrival (not
  queued behind the one before it), and carried out in arrival order.
* Tracker stream (UDP): the station's ball samples (125 Hz, delivered with its latency) in
  deploy/robot/drivers/tracker.py's wire format, stamped with this computer's CLOCK_MONOTONIC.
* Launcher and referee (JSON lines over TCP): `throw` launches the station's next throw,
  `finish` returns its events (hit, landing...) to complete the episode log, `faults` changes
  the injected faults, `stats` returns counters, `arrivals` (since=t) the time each new arm and
  gantry target reached the station (for the command transport delay, scripts/cell_figures.py).

The arm's and the gantry's targets are separate, as on the cell (two controllers): each part
ramps toward its newest target (over a control period, as in-process) from when it arrived on
its protocol, plus the timing profile's action delay (deploy/sim/serve_station.py). Feedback (EGM
joints, Modbus actual positions) is the station's newest joint sample delivered by then (its
joint rate, latency and jitter), and the tracker stream its ball samples as they are delivered.

Faults (`--faults`, or the launcher's `faults` command; FAULT_KINDS): per stream (egm, tracker,
modbus) `stream.kind=value`, comma separated, e.g. `egm.loss=0.05,modbus.delay_ms=10`. Times
(`stop_s`, `motors_off_s`, `rapid_stopped_s`, `fault_s`) count from when the faults were set.
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import gc
import heapq
import json
import math
import os
import select
import signal
import socket
import socketserver
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
from abb_robot_client._egm_protobuf import egm_pb2
from google.protobuf.message import DecodeError
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.transaction import TransactionManager

from deploy.robot.drivers.config import CellConfig
from deploy.robot.drivers.egm import DATA, MOTORS_ON, RAPID_RUNNING, RAPID_STOPPED
from deploy.robot.drivers.gantry import ACK, ENABLE, FAULT, NEW_SETPOINT, READY, decode_int32, encode_int32
from deploy.robot.drivers.tracker import pack_sample
from deploy.robot.hardware import MonotonicClock

EGM_HZ = 250.0
ARRIVALS_KEPT = 100_000         # new targets remembered for the `arrivals` command (~7 min at 100 Hz)
# What each stream's faults may name: probabilities per message, delays in ms, times in s.
FAULT_KINDS = {
    "egm": ("loss", "delay_ms", "reorder", "duplicate", "malformed", "stop_s", "nan", "range",
            "msgtype", "motors_off_s", "rapid_stopped_s"),
    "tracker": ("loss", "delay_ms", "reorder", "duplicate", "malformed", "stop_s", "future"),
    "modbus": ("loss", "delay_ms", "stop_s", "fault_s"),
}
PROBABILITIES = ("loss", "reorder", "duplicate", "malformed", "nan", "range", "msgtype", "future")


def make_station(cfg, contract, seed: int, timing):
    """The simulated station on the real clock: the one place `serve` builds it. timing: a
    ttmjx.world.config.Timing or a profile name."""
    from deploy.sim.serve_station import ServedStation
    from deploy.sim.station import TIMING
    if isinstance(timing, str):
        if timing not in TIMING:
            raise ValueError(f"--timing {timing!r}: expected one of {', '.join(TIMING)}")
        timing = TIMING[timing]
    return ServedStation(cfg, contract, clock=MonotonicClock(), seed=seed, timing=timing)


# --------------------------------------------------------------------------------------------
# Faults
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Faults:
    """{stream: {kind: value}} and the time they were set (times count from there)."""
    spec: dict = dataclasses.field(default_factory=dict)
    t_set: float = 0.0

    def get(self, stream: str, kind: str, default=0.0):
        return self.spec.get(stream, {}).get(kind, default)

    def after(self, stream: str, kind: str, now: float) -> bool:
        """Whether the timed fault `kind` (e.g. stop_s) of stream has begun."""
        v = self.get(stream, kind, None)
        return v is not None and now - self.t_set >= v


def parse_faults(spec: str, t_set: float = 0.0) -> Faults:
    """'egm.loss=0.05,modbus.delay_ms=10' -> Faults; ValueError naming the bad entry."""
    out: dict = {}
    for item in filter(None, (s.strip() for s in (spec or "").split(","))):
        key, sep, value = item.partition("=")
        stream, _, kind = key.strip().partition(".")
        if not sep or stream not in FAULT_KINDS or kind not in FAULT_KINDS[stream]:
            allowed = "; ".join(f"{s}.{{{','.join(k)}}}" for s, k in FAULT_KINDS.items())
            raise ValueError(f"--faults entry {item!r}: expected stream.kind=value with {allowed}")
        try:
            v = float(value)
        except ValueError:
            raise ValueError(f"--faults {key}={value!r}: expected a number") from None
        if not math.isfinite(v) or v < 0 or (kind in PROBABILITIES and v > 1):
            expected = "a probability in [0, 1]" if kind in PROBABILITIES else "a finite number >= 0"
            raise ValueError(f"--faults {key}={value}: expected {expected}")
        out.setdefault(stream, {})[kind] = v
    return Faults(out, t_set)


class FaultyUdp:
    """A UDP sender that loses, delays, reorders, duplicates and corrupts datagrams as told."""

    def __init__(self, sock: socket.socket, addr: tuple, stream: str, rng: np.random.Generator):
        self.sock, self.addr, self.stream, self.rng = sock, addr, stream, rng
        self.queue: list = []                   # heap of (due time, n, payload)
        self.held: bytes | None = None          # a datagram held back to go after the next
        self.n = 0
        self.counts = collections.Counter()

    def send(self, payload: bytes, faults: Faults, now: float) -> None:
        f = lambda kind: faults.get(self.stream, kind)      # noqa: E731
        if faults.after(self.stream, "stop_s", now):
            self.counts["stopped"] += 1
            return
        if self.rng.random() < f("loss"):
            self.counts["lost"] += 1
            return
        if self.rng.random() < f("malformed"):
            self.counts["malformed"] += 1
            payload = payload[: len(payload) // 2] + b"\xff"   # truncated mid-field
        copies = 2 if self.rng.random() < f("duplicate") else 1
        self.counts["duplicated"] += copies - 1
        out = [payload] * copies
        if self.held is not None:
            out.append(self.held)
            self.held = None
        elif self.rng.random() < f("reorder"):
            self.counts["reordered"] += 1
            self.held, out = out[0], out[1:]
        due = now + f("delay_ms") / 1000.0
        for p in out:
            self.n += 1
            heapq.heappush(self.queue, (due, self.n, p))
        self.flush(now)

    def flush(self, now: float) -> None:
        while self.queue and self.queue[0][0] <= now:
            _, _, p = heapq.heappop(self.queue)
            self.sock.sendto(p, self.addr)
            self.counts["sent"] += 1


# --------------------------------------------------------------------------------------------
# The server
# --------------------------------------------------------------------------------------------
class Server:
    """The station behind the three protocols and the launcher (module docstring)."""

    def __init__(self, station, cell: CellConfig, faults: Faults, egm_hz: float = EGM_HZ, seed: int = 0):
        self.s, self.cell, self.egm_hz = station, cell, egm_hz
        self.lock = threading.Lock()             # the station: physics loop, Modbus, launcher
        self.faults = dataclasses.replace(faults, t_set=time.monotonic())
        self.rng = np.random.default_rng(seed + 1)
        self.target = station.joints()           # [8] the newest arm and gantry targets
        self.gantry_toggle = 0
        self.seq = 0
        self.counts = collections.Counter()
        self.stop = threading.Event()
        self.egm_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.egm_sock.bind(("127.0.0.1", 0))
        self.egm_sock.setblocking(False)
        self.egm_out = FaultyUdp(self.egm_sock, (cell.egm.host, cell.egm.port), "egm", self.rng)
        self.trk_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.trk_out = FaultyUdp(self.trk_sock, (cell.tracker.host, cell.tracker.port), "tracker", self.rng)
        self.trk_seq, self.trk_last = 0, -math.inf
        # (arrival time, part, target) of each new arm / gantry target (the `arrivals` command)
        self.arrivals: collections.deque = collections.deque(maxlen=ARRIVALS_KEPT)
        self.modbus_resumed = -math.inf          # when the drive last answered again after a stop

    # ------------------------------------------------------------------ physics loop
    def run(self, duration_s: float | None = None) -> None:
        """The real-time loop (until stop or duration_s): physics, EGM, tracker."""
        period = 1.0 / self.egm_hz
        t_end = None if duration_s is None else time.monotonic() + duration_s
        next_egm = last = time.monotonic()
        while not self.stop.is_set() and (t_end is None or time.monotonic() < t_end):
            now = time.monotonic()
            self._lateness(now - last)
            last = now
            with self.lock:
                self.s.sync()
                self._receive_egm()
                if now >= next_egm:
                    self._send_egm(now)
                    next_egm = max(next_egm + period, now - period)
                self._send_ball(now)
            self.egm_out.flush(now)
            self.trk_out.flush(now)
            # until the next EGM cycle or physics millisecond, or at once when a reply arrives
            select.select([self.egm_sock], [], [], max(0.0, min(next_egm, now + 0.001) - time.monotonic()))

    def _lateness(self, gap: float) -> None:
        """Count loop gaps (the physics and streams paused that long)."""
        for ms in (5, 20, 100):
            if gap > ms / 1000.0:
                self.counts[f"loop_gaps_over_{ms}ms"] += 1
        self.counts["loop_max_gap_ms"] = max(self.counts["loop_max_gap_ms"], int(gap * 1000))

    def delivered_joints(self, now: float) -> np.ndarray:
        """[8] the joints as the controllers measure them when they answer: an EGM message carries
        the arm's joints at its send time, the drive's registers the gantry's position at the
        read. The runner's drivers stamp both at receipt, so the transport is the feedback's
        only delay; the timing profile's joint latency, which in process ages samples that keep
        their exact stamps, is not applied again (it would shift every stamp by the latency
        plus the sample's age)."""
        return self.s.joints()

    def _send_egm(self, now: float) -> None:
        f, q = self.faults, np.rad2deg(self.delivered_joints(now)[2:8])
        if self.rng.random() < f.get("egm", "nan"):
            q[self.rng.integers(6)] = np.nan
        if self.rng.random() < f.get("egm", "range"):
            q[self.rng.integers(6)] = 720.0
        self.seq += 1
        m = egm_pb2.EgmRobot()
        m.header.seqno, m.header.tm = self.seq % 2 ** 32, int(now * 1000) % 2 ** 32
        m.header.mtype = egm_pb2.EgmHeader.MSGTYPE_COMMAND if self.rng.random() < f.get("egm", "msgtype") else DATA
        m.feedBack.joints.joints.extend(q.tolist())
        m.feedBack.time.sec, m.feedBack.time.usec = int(now), int((now % 1) * 1e6)
        m.planned.joints.joints.extend(np.rad2deg(self.target[2:8]).tolist())
        motors_off = f.after("egm", "motors_off_s", now)
        m.motorState.state = egm_pb2.EgmMotorState.MOTORS_OFF if motors_off else MOTORS_ON
        # RAPID stopped (a program stop or an error on the controller) while motors stay on
        m.rapidExecState.state = RAPID_STOPPED if f.after("egm", "rapid_stopped_s", now) else RAPID_RUNNING
        self.egm_out.send(m.SerializeToString(), f, now)

    def _receive_egm(self) -> None:
        while True:
            try:
                buf = self.egm_sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionRefusedError:     # the runner's port is not open (yet)
                continue
            q = self._sensor_joints(buf)
            if q is not None:
                if not np.array_equal(q, self.target[2:8]):   # the reply to every message repeats it
                    self.target[2:8] = q
                    t = time.monotonic()
                    self.s.set_part_target("arm", q, t)
                    self.arrivals.append((t, "arm", q.tolist()))
                self.counts["egm_replies"] += 1

    def _sensor_joints(self, buf: bytes) -> np.ndarray | None:
        """The planned joints [6] (rad) of an EgmSensor reply, or None (counted) if bad."""
        m = egm_pb2.EgmSensor()
        try:
            m.ParseFromString(buf)
        except DecodeError:
            self.counts["egm_bad_replies"] += 1
            return None
        q = np.deg2rad(np.asarray(m.planned.joints.joints, np.float64))
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            self.counts["egm_bad_replies"] += 1
            return None
        return q

    def _send_ball(self, now: float) -> None:
        """The station's ball samples now due (sample time + tracker latency <= now)."""
        f = self.faults
        for t, x, due in list(self.s.ball_samples):
            if t <= self.trk_last or due > now:
                continue
            self.trk_last = t
            stamp = t + 1.0 if self.rng.random() < f.get("tracker", "future") else t
            self.trk_seq += 1
            self.trk_out.send(pack_sample(self.trk_seq, stamp, x), f, now)

    # ------------------------------------------------------------------ Modbus (the drive)
    async def modbus_link(self, t_arrival: float, delay_s: float) -> ExcCodes | None:
        """The link's faults on one request that arrived at t_arrival (delay_s: modbus.delay_ms
        then): it is carried out delay_s after its arrival (a network's latency: requests in
        flight are delayed side by side, none waits for the one before to be answered), unless
        the drive has stopped or the request is lost (then an exception code)."""
        await asyncio.sleep(max(0.0, t_arrival + delay_s - time.monotonic()))
        f, stopped = self.faults, False
        while f.after("modbus", "stop_s", time.monotonic()) and not self.stop.is_set():
            stopped = True
            await asyncio.sleep(0.05)          # the drive stops answering
            f = self.faults
        if stopped:
            self.modbus_resumed = time.monotonic()
        if stopped or t_arrival < self.modbus_resumed:
            # A request the stopped drive held is lost, not carried out when the drive answers
            # again: its writes were a session ago (a later session's homing saw the gantry
            # leap to an old target). So is every request that arrived before it answered again.
            self.counts["modbus_lost_in_stop"] += 1
            return ExcCodes.GATEWAY_NO_RESPONSE
        if self.rng.random() < f.get("modbus", "loss"):
            self.counts["modbus_lost"] += 1
            return ExcCodes.GATEWAY_NO_RESPONSE
        return None

    async def modbus_action(self, fc: int, start: int, address: int, count: int, regs: list,
                            values) -> ExcCodes | None:
        """pymodbus SimDevice action (after the link, modbus_link): a write sets the target, a
        read the actuals."""
        r = self.cell.gantry.registers
        if values is not None:
            return self._modbus_write(address, list(values), regs, start, r)
        self._modbus_read(regs, start, r, self.faults)
        return None

    def _modbus_write(self, address, values, regs, start, r) -> ExcCodes | None:
        new = {a: regs[a - start] for a in range(start, start + len(regs))}
        new.update({address + i: int(v) for i, v in enumerate(values)})
        control = new.get(r.control, 0)
        if control & NEW_SETPOINT != self.gantry_toggle:
            if not control & ENABLE or new.get(r.velocity, 0) <= 0:
                self.counts["modbus_rejected"] += 1
                return ExcCodes.ILLEGAL_VALUE
            x = decode_int32([new[r.target_x], new[r.target_x + 1]], r) / r.counts_per_m
            y = decode_int32([new[r.target_y], new[r.target_y + 1]], r) / r.counts_per_m
            with self.lock:
                if not np.array_equal((x, y), self.target[0:2]):
                    self.target[0:2] = (x, y)
                    t = time.monotonic()
                    self.s.set_part_target("gantry", self.target[0:2].copy(), t)
                    self.arrivals.append((t, "gantry", [x, y]))
            self.gantry_toggle = control & NEW_SETPOINT
            self.counts["modbus_targets"] += 1
        return None

    def _modbus_read(self, regs, start, r, f) -> None:
        with self.lock:
            q = self.delivered_joints(time.monotonic())[0:2]
        status = READY | (ACK if self.gantry_toggle else 0)
        if f.after("modbus", "fault_s", time.monotonic()):
            status |= FAULT
        words = {r.status: [status]}
        for addr, v in ((r.actual_x, q[0]), (r.actual_y, q[1])):
            words[addr] = encode_int32(round(v * r.counts_per_m), r)
        for addr, ws in words.items():
            for i, w in enumerate(ws):
                if 0 <= addr + i - start < len(regs):
                    regs[addr + i - start] = w
        self.counts["modbus_reads"] += 1

    def modbus_server(self) -> ModbusTcpServer:
        r, g = self.cell.gantry.registers, self.cell.gantry
        block = SimData(0, count=r.span, values=0, datatype=DataType.REGISTERS)
        device = SimDevice(id=g.device_id, simdata=[block], action=self.modbus_action)
        return _DriveServer(self, device, address=(g.host, g.port))

    # ------------------------------------------------------------------ launcher and referee
    def command(self, req: dict) -> dict:
        cmd = req.get("cmd")
        if cmd == "throw":
            throw = self.s._next_throw()       # JAX, outside the lock: the physics keeps time
            with self.lock:
                return {"t_launch": self.s.throw_in(float(req.get("delay_s", 0.3)), throw)}
        if cmd == "finish":
            return {"events": self._finish(float(req.get("max_s", 3.0)))}
        if cmd == "faults":
            self.faults = parse_faults(req.get("spec", ""), time.monotonic())
            return {"ok": True, "faults": self.faults.spec}
        if cmd == "stats":
            return self.stats()
        if cmd == "arrivals":
            since = float(req.get("since", -math.inf))
            with self.lock:
                return {"arrivals": [a for a in self.arrivals if a[0] >= since]}
        raise ValueError(f"unknown command {cmd!r}; expected throw, finish, faults, stats or arrivals")

    def _finish(self, max_s: float):
        t_end = time.monotonic() + max_s
        while time.monotonic() < t_end:
            with self.lock:
                s = self.s
                s.fold_events()
                over = s.pending is None and (not s.in_flight or s.events is None or s.events.done)
            if over:
                break
            time.sleep(0.02)
        with self.lock:
            ev = self.s.finish_throw(0.0)
        return None if ev is None else ev.to_dict()

    def stats(self) -> dict:
        return {"counts": dict(self.counts), "egm": dict(self.egm_out.counts),
                "tracker": dict(self.trk_out.counts), "faults": self.faults.spec,
                "realtime_lag_s": time.monotonic() - self.s.time}


class _DriveLink(ServerRequestHandler):
    """One Modbus TCP connection to the simulated drive: the link and the drive's request queue.
    pymodbus's own handler keeps one request per connection (the reply to a request answered
    after the next one arrived goes out with the next one's transaction id; two requests in one
    segment leave the second unread): it serves only a client that waits for each reply. Here each request is queued with its arrival time, the link's faults
    (Server.modbus_link) delay it from that arrival, and the requests are carried out and
    answered in arrival order, each reply with its own request's transaction id."""

    def __init__(self, owner, *args):
        super().__init__(owner, *args)
        self.requests: asyncio.Queue = asyncio.Queue()
        self.worker: asyncio.Task | None = None

    def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
        used, app = 0, self.server.app
        while used < len(data):
            try:
                n = TransactionManager.callback_data(self, data[used:], addr)   # one frame
            except ModbusIOException as exc:    # as pymodbus's handler answers an undecodable one
                self.server_send(ExceptionResponse(exc.fcode or 0, exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                                   device_id=exc.dev_id, transaction=exc.transaction_id), addr)
                return len(data)
            if not n:
                break                           # the rest of a frame is still on its way
            used += n
            if self.last_pdu is not None:
                delay_s = app.faults.get("modbus", "delay_ms") / 1000.0
                self.requests.put_nowait((time.monotonic(), delay_s, self.last_pdu, self.last_addr))
        if self.worker is None and not self.requests.empty():
            self.worker = asyncio.get_running_loop().create_task(self._serve())
        return used

    async def _serve(self) -> None:
        app = self.server.app
        while True:
            t, delay_s, pdu, addr = await self.requests.get()
            code = await app.modbus_link(t, delay_s)
            if code is not None:
                response = ExceptionResponse(pdu.function_code, code)
            else:
                try:
                    response = await pdu.datastore_update(self.server.context, pdu.dev_id)
                except NoSuchIdException:
                    response = ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
                except Exception:               # noqa: BLE001 - answered as pymodbus's handler does,
                    app.counts["modbus_device_failures"] += 1   # and the link keeps serving
                    response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
            response.transaction_id, response.dev_id = pdu.transaction_id, pdu.dev_id
            self.server_send(response, addr)

    def callback_disconnected(self, exc: Exception | None) -> None:
        if self.worker is not None:             # what the closed connection still held is dropped
            self.worker.cancel()
        super().callback_disconnected(exc)


class _DriveServer(ModbusTcpServer):
    """pymodbus's Modbus TCP server with a _DriveLink per connection."""

    def __init__(self, app: Server, *args, **kwargs):
        self.app = app
        super().__init__(*args, **kwargs)

    def callback_new_connection(self):
        return _DriveLink(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _LauncherHandler(socketserver.StreamRequestHandler):
    def handle(self):
        for line in self.rfile:
            try:
                out = self.server.app.command(json.loads(line))
            except (ValueError, KeyError, TypeError) as e:
                out = {"error": str(e)}
            self.wfile.write((json.dumps(out, allow_nan=False, default=float) + "\n").encode())


class _LauncherServer(socketserver.ThreadingTCPServer):
    daemon_threads = allow_reuse_address = True


def check_port_free(host: str, port: int, kind: int, what: str) -> None:
    """ValueError naming the port if (host, port) is taken."""
    s = socket.socket(socket.AF_INET, kind)
    try:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
    except OSError as e:
        raise ValueError(f"{what} port {port} on {host} is not free ({e.strerror or e})") from None
    finally:
        s.close()


def _start_modbus(app: Server):
    """The pymodbus server on an event loop of its own thread (it must be built inside the loop);
    returns its thread once the server listens (it shuts down when app.stop is set)."""
    loop, started, box = asyncio.new_event_loop(), threading.Event(), []

    async def main():
        box.append(app.modbus_server())
        await box[0].serve_forever(background=True)
        started.set()
        while not app.stop.is_set():
            await asyncio.sleep(0.1)
        await box[0].shutdown()

    def run():
        try:
            loop.run_until_complete(main())
        except BaseException as e:       # reported to the caller below
            box.append(e)
            started.set()

    thread = threading.Thread(target=run, name="modbus", daemon=True)
    thread.start()
    started.wait(10.0)
    if len(box) != 1:
        err = box[-1] if box else "did not start within 10 s"
        raise ValueError(f"gantry (Modbus) server on {app.cell.gantry.host}:{app.cell.gantry.port}: {err}")
    return thread


def check_ports(cell: CellConfig) -> None:
    """The server's listening ports are free (ValueError naming the first taken one)."""
    check_port_free(cell.gantry.host, cell.gantry.port, socket.SOCK_STREAM, "gantry (Modbus)")
    if cell.launcher is not None:
        check_port_free(cell.launcher.host, cell.launcher.port, socket.SOCK_STREAM, "launcher")


def serve(cell: CellConfig, station, faults: Faults, egm_hz: float = EGM_HZ, seed: int = 0,
          duration_s: float | None = None, ready=print) -> dict:
    """Serve the station until interrupted (or duration_s); returns the final stats."""
    check_ports(cell)
    app = Server(station, cell, faults, egm_hz, seed)
    station.prefetch()
    # Python's cyclic collector stops every thread; a full pass over what loading JAX and
    # compiling left behind takes ~100 ms, a stall of every stream. Frozen, later passes skip it.
    gc.freeze()
    modbus_thread = _start_modbus(app)
    launcher = None
    if cell.launcher is not None:
        launcher = _LauncherServer((cell.launcher.host, cell.launcher.port), _LauncherHandler)
        launcher.app = app
        threading.Thread(target=launcher.serve_forever, name="launcher", daemon=True).start()
    ready(json.dumps({"ready": True, "egm_to": [cell.egm.host, cell.egm.port],
                      "modbus": [cell.gantry.host, cell.gantry.port], "faults": faults.spec}), flush=True)
    try:
        app.run(duration_s)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop.set()
        if launcher is not None:
            launcher.shutdown()
        modbus_thread.join(timeout=5)
    return app.stats()


@contextlib.contextmanager
def serving(config_path: str, *args: str, cpu: int | None = None, env: dict | None = None):
    """`ttmjx robot serve --config config_path --json *args` in a subprocess (pinned to core
    `cpu` if given) for the block, once it is ready; stopped as Ctrl-C stops it (killed if it
    does not end within 20 s). Yields the process."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = {**os.environ, "PYTHONPATH": root, **(env or {})}
    err = tempfile.TemporaryFile("w+")        # not a pipe: a long session's log would fill it
    proc = subprocess.Popen([sys.executable, "-m", "ttmjx", "robot", "serve", "--config", str(config_path),
                             "--json", *args], stdout=subprocess.PIPE, stderr=err, env=env, text=True,
                            preexec_fn=None if cpu is None else lambda: os.sched_setaffinity(0, {cpu}))
    try:
        line = proc.stdout.readline()           # the server's ready line (it prints nothing else
        if '"ready": true' not in line:         # until it stops)
            proc.wait(timeout=20)
            err.seek(0)
            raise ValueError(f"ttmjx robot serve did not start: {line.strip()} {err.read()[-2000:]}")
        yield proc
    finally:
        err.close()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
