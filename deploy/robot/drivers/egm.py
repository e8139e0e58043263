"""The ABB arm over Externally Guided Motion (EGM), through abb-robot-client's `EGM` (UDP and
ABB's protobuf messages, egm.proto).

EGM's roles: the controller initiates. Once RAPID runs EGMRunJoint, the controller sends an
EgmRobot message (feedback: joints in degrees, motor and RAPID state, a sequence number) every
EGM cycle (4 ms: 250 Hz; the paper's cell ~240 Hz) to this computer's port, and expects an
EgmSensor message in reply (planned joint positions in degrees, speedRef joint velocities in
degrees/s) sent back to the address it came from. A controller that gets no reply for its comm
timeout stops EGM, so replies come from a thread of their own, never from the control tick.

Each message is checked: its sequence number (a number not newer than the last is a duplicate
or reordered message: dropped; a gap is logged with the count lost), type, motor and RAPID
state. The newest accepted one is kept: stamped with the runner's clock at receipt, degrees to
radians, and answered. Messages that queued up behind a late thread (a stall of this process)
are all checked, but only the newest is kept and answered: stamped at one receipt, the older
ones would put old joints at a new time. The reply carries the runner's latest target
and, for one control period after a new target, the velocity that reaches it in that period
(zero after); before the runner's first target it holds the arm where the first valid feedback
put it. A malformed message, an unknown message type, a message without six joints: dropped,
logged, not answered (no command is sent on bad data). Motors off or RAPID not running: a
latching fault (faults.LATCHING): `read()` then returns non-finite joints (joint_nonfinite)
and the cell's Robot.fault() names it (robot_fault): the runner HOLDs. No message for stale_s:
logged; the runner sees the newest sample go stale (joint_stale, HOLD).
"""
from __future__ import annotations

import threading

import numpy as np
from abb_robot_client._egm_protobuf import egm_pb2
from abb_robot_client.egm import EGM
from google.protobuf.message import DecodeError

from deploy.robot.drivers.config import EgmConfig
from deploy.robot.drivers.faults import FaultLog
from deploy.robot.drivers.history import SampleHistory
from deploy.robot.drivers.tracker import bind_udp
from deploy.robot.hardware import Clock

ARM_JOINTS = 6
HISTORY = 64                    # messages kept for read_at (0.26 s at 250 Hz)
DATA = egm_pb2.EgmHeader.MessageType.Value("MSGTYPE_DATA")
MOTORS_ON = egm_pb2.EgmMotorState.MotorStateType.Value("MOTORS_ON")
RAPID_RUNNING = egm_pb2.EgmRapidCtrlExecState.RapidCtrlExecStateType.Value("RAPID_RUNNING")
RAPID_STOPPED = egm_pb2.EgmRapidCtrlExecState.RapidCtrlExecStateType.Value("RAPID_STOPPED")


def open_egm(cfg: EgmConfig) -> EGM:
    """abb-robot-client's EGM on cfg.port; ValueError naming the port if it is taken."""
    bind_udp("0.0.0.0", cfg.port, "egm").close()      # a clear error before EGM binds it itself
    try:
        return EGM(port=cfg.port)
    except OSError as e:
        raise ValueError(f"egm port {cfg.port}: cannot bind ({e.strerror or e})") from None


class EgmArm:
    """The arm's 6 joints (rad) over EGM, served by a background thread (start() / close())."""

    def __init__(self, cfg: EgmConfig, clock: Clock, control_dt: float, faults: FaultLog | None = None,
                 poll_s: float = 0.05):
        self.cfg, self.clock, self.control_dt, self.poll_s = cfg, clock, float(control_dt), poll_s
        self.faults = faults if faults is not None else FaultLog()
        self.egm = open_egm(cfg)
        self._lock = threading.Lock()
        self.sample: tuple[float, np.ndarray] | None = None     # (receipt time, q [6] rad)
        self.history = SampleHistory(HISTORY)                   # recent accepted messages
        self.latched: str | None = None                         # a LATCHING fault's name
        self.last_seq: int | None = None
        self._target: np.ndarray | None = None                  # [6] rad
        self._speed = np.zeros(ARM_JOINTS)                      # [6] rad/s
        self._t_target = -np.inf
        self.received = self.replies = self.buffered = 0
        self._stale_logged = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="egm", daemon=True)

    def start(self) -> "EgmArm":
        self._thread.start()
        return self

    # ------------------------------------------------------------------ runner side
    def read(self) -> tuple[float, np.ndarray] | None:
        """(receipt time, q [6] rad) of the newest accepted message (None before the first);
        q is NaN while a latching fault stands."""
        with self._lock:
            if self.sample is None:
                return None
            t, q = self.sample
            return t, (np.full(ARM_JOINTS, np.nan) if self.latched else q.copy())

    def read_at(self, t: float) -> np.ndarray | None:
        """q [6] rad at time t (at most the newest receipt time: interpolated between the
        accepted messages around it); NaN while a latching fault stands; None before the first."""
        with self._lock:
            if self.latched and len(self.history):
                return np.full(ARM_JOINTS, np.nan)
            return self.history.at(t, 0.0)

    def set_target(self, q: np.ndarray) -> None:
        """New position target q [6] rad: sent in the replies from the next message on."""
        q = np.asarray(q, np.float64)
        now = self.clock.now()
        with self._lock:
            prev = self._target if self._target is not None else q
            self._speed = (q - prev) / self.control_dt
            self._target, self._t_target = q.copy(), now

    # ------------------------------------------------------------------ the EGM thread
    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                ok, state = self.egm.receive_from_robot(timeout=self.poll_s)
            except DecodeError as e:
                self.faults.add(self.clock.now(), "egm", "egm_malformed", f"protobuf: {e}")
                continue
            except OSError:
                if self._stop.is_set():
                    return
                raise
            if not ok:
                self._check_stale(self.clock.now())
                continue
            states = [state] + self._buffered()
            now = self.clock.now()
            self.received += len(states)
            accepted = [q for q in (self._accept(st.robot_message, now) for st in states) if q is not None]
            if accepted and self._keep(accepted[-1], now):     # every one checked, the newest kept
                self._reply(now)

    def _buffered(self) -> list:
        """Messages already waiting behind the one just received (this thread was late: a
        stall of this process). All stamped at this receipt, the older ones would put old
        joints at a new time (a false jump), so only the newest is kept."""
        out, addr = [], self.egm.egm_addr       # the reply goes where the last message came from
        while True:
            try:
                ok, state = self.egm.receive_from_robot(timeout=0)
            except DecodeError as e:
                self.faults.add(self.clock.now(), "egm", "egm_malformed", f"protobuf: {e}")
                continue
            except OSError:                     # (closing): what was received is still answered
                ok = False
            if not ok:
                if self.egm.egm_addr is None:   # abb-robot-client forgets it on a receive error
                    self.egm.egm_addr = addr
                return out
            out.append(state)
            self.buffered += 1

    def _check_stale(self, now: float) -> None:
        with self._lock:
            t = self.sample[0] if self.sample is not None else None
        if t is not None and now - t > self.cfg.stale_s and not self._stale_logged:
            self._stale_logged = True
            self.faults.add(now, "egm", "egm_stream_stopped", f"no message for {now - t:.3f} s")

    def _accept(self, msg, now: float) -> np.ndarray | None:
        """Check one EgmRobot message (sequence, type, motors, RAPID): its joints q [6] rad, or
        None (logged) if it is dropped."""
        fault = self._message_fault(msg)
        if fault is not None:
            self.faults.add(now, "egm", *fault)
            return None
        q = np.deg2rad(np.asarray(msg.feedBack.joints.joints, np.float64))
        latched = None
        if msg.motorState.state != MOTORS_ON:
            latched = "egm_motors_off"
        elif msg.rapidExecState.state != RAPID_RUNNING:
            latched = "egm_rapid_stopped"
        if latched and not self.latched:
            self.faults.add(now, "egm", latched, f"seq {msg.header.seqno}")
        with self._lock:
            self.last_seq = msg.header.seqno
            self.latched = self.latched or latched
        self._stale_logged = False
        return q

    def _keep(self, q: np.ndarray, now: float) -> bool:
        """q [6] becomes the newest sample, stamped now; True if it may be answered."""
        with self._lock:
            self.sample = (now, q)
            self.history.append(now, q)
            return not self.latched

    def _message_fault(self, msg) -> tuple[str, str] | None:
        """(name, detail) of what is wrong with the message, or None."""
        h = msg.header
        if not h.HasField("mtype") or h.mtype != DATA:
            return "egm_msgtype", f"message type {h.mtype} (expected MSGTYPE_DATA)"
        if not h.HasField("seqno") or not msg.HasField("feedBack"):
            return "egm_malformed", "no sequence number or no feedback"
        n = len(msg.feedBack.joints.joints)
        if n != ARM_JOINTS:
            return "egm_malformed", f"{n} joints, expected {ARM_JOINTS}"
        if self.last_seq is not None:
            ahead = (h.seqno - self.last_seq) % 2 ** 32
            if ahead == 0 or ahead > 2 ** 31:
                return "egm_seq_old", f"seq {h.seqno} after {self.last_seq}"
            if ahead > 1:
                self.faults.add(self.clock.now(), "egm", "egm_seq_gap", f"{ahead - 1} lost before {h.seqno}")
        return None

    def _reply(self, now: float) -> None:
        """EgmSensor to the controller: the target (deg) and its velocity (deg/s)."""
        with self._lock:
            if self._target is None:                        # hold where the arm is
                if not np.all(np.isfinite(self.sample[1])):
                    return                                  # never a command from bad data
                self._target = self.sample[1].copy()
            target = self._target.copy()
            speed = self._speed if now - self._t_target < self.control_dt else np.zeros(ARM_JOINTS)
        if self.egm.send_to_robot(np.rad2deg(target), np.rad2deg(speed)):
            self.replies += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2 * self.poll_s + 0.5)
        self.egm.close()
