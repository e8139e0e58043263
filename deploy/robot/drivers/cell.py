"""The real cell as the runner sees it: one Robot joining the gantry (Modbus) and the arm (EGM)
into the 8 joints in the contract's order (JOINT_NAMES: gantry_x, gantry_y, j1..j6), the
tracker, the launcher, and `ttmjx robot run --station cell` (run_cell).

Timestamps: each part keeps its own (arm: receipt of the EGM message, gantry: receipt of the
Modbus reply; both in `parts()`, with recent history). read() returns one sample at the arm's
stamp (the newest, at 250 Hz): the arm's joints, and the gantry's line through its two newest
readings at that time (ModbusGantry.read_at, followed at most one poll period past the newest;
when the gantry's next reading is later than that, both parts are read at the end of its
line instead, the arm interpolated between its messages), so the 100 Hz gantry does not lag its
stamp by up to a poll (a 10 ms lag the policy, trained on feedback sampled with the arm, reads
as a slower gantry). So that one fresh part never hides a silent one, a part whose newest
sample is older than its stale_s freezes read() at the last sample it returned: the runner
sees that sample go stale (joint_stale, HOLD). Since the joined time waits for the gantry's line,
a gantry reading later than stale_s minus one poll period (90 ms by default) already holds.

Commands: send() gives the arm its 6 targets as they are, and the gantry its 2 led by the
Modbus link's latency above the arm's own (drivers/lead.py, GantryLead: extrapolated along the
recent targets' velocity by the excess, through the safety filter; unchanged on a nominal
link). Each episode's log carries what the gantry was sent (extras `gantry_sent` [T, 2],
`gantry_lead_s` [T]) and its meta the link's estimate; the session's summary both
(`gantry.link`, `gantry.lead`).
"""
from __future__ import annotations

import collections
import dataclasses
import json
import socket
import sys
import time

import numpy as np

from deploy.robot.contract import Contract
from deploy.robot.drivers.config import CellConfig, LauncherConfig
from deploy.robot.drivers.egm import EgmArm
from deploy.robot.drivers.faults import FaultLog, window_summary
from deploy.robot.drivers.gantry import ModbusGantry
from deploy.robot.drivers.lead import GantryLead
from deploy.robot.drivers.tracker import UdpTracker
from deploy.robot.hardware import Clock
from deploy.robot.safety import Limits, limits_from_contract, part_limits

GANTRY, ARM = slice(0, 2), slice(2, 8)


class CellRobot:
    """deploy.robot.hardware.Robot over ModbusGantry + EgmArm. limits: the contract's [8]
    (deploy.robot.safety.limits_from_contract) for the gantry's lead (None: no lead, targets sent
    as given)."""

    def __init__(self, gantry: ModbusGantry, arm: EgmArm, clock: Clock, limits: Limits | None = None):
        self.gantry, self.arm, self.clock = gantry, arm, clock
        self.stale_s = (gantry.cfg.stale_s, arm.cfg.stale_s)
        self._last = (-np.inf, np.full(8, np.nan))
        self.lead = None if limits is None else GantryLead(part_limits(limits, GANTRY), gantry.cfg.compensate_latency)
        # (time, gantry target sent [2], lead s) of the recent sends, for the episode logs
        self.sent: collections.deque = collections.deque(maxlen=4096)

    def parts(self) -> tuple:
        """(gantry sample, arm sample): each (receipt time, q) or None."""
        return self.gantry.read(), self.arm.read()

    def read(self) -> tuple[float, np.ndarray]:
        g, a = self.parts()
        if g is None or a is None:      # nothing yet: a sample the runner finds stale at once
            return self._last
        now = self.clock.now()
        if now - g[0] > self.stale_s[0] or now - a[0] > self.stale_s[1]:
            return self._last[0], self._last[1].copy()
        # The joined time: the arm's newest, unless the gantry's line does not reach it (its next
        # reading is late: a stall of the drive, the network or this process). Joined later,
        # the gantry would show held and then jump by all the motion it missed within one arm
        # period (a false joint_jump); joined at the arm's newest but with the old gantry stamp,
        # one late reading would freeze the sample. So both parts are read at the time the
        # gantry's line still covers.
        t = min(a[0], g[0] + 1.0 / self.gantry.cfg.poll_hz)
        if t <= self._last[0]:
            return self._last[0], self._last[1].copy()
        q = np.empty(8)
        # (t reaches before the arm's kept messages only at start-up: later a gantry that stale
        # is caught above, config.MAX_STALE_S)
        q[GANTRY], q[ARM] = self.gantry.read_at(t), self.arm.read_at(t)
        self._last = (t, q)
        return self._last[0], q.copy()

    def fault(self) -> str | None:
        """The name of a latched device fault (arm: motors off, RAPID stopped; gantry: drive
        fault), or None (deploy.robot.hardware.Robot's optional fault())."""
        return self.arm.latched or self.gantry.latched

    def send(self, q: np.ndarray) -> None:
        q = np.asarray(q, np.float64)
        if q.shape != (8,) or not np.all(np.isfinite(q)):
            raise ValueError(f"CellRobot.send: expected 8 finite targets, got {q!r}")
        self.arm.set_target(q[ARM])
        t, g, lead = self.clock.now(), q[GANTRY], 0.0
        if self.lead is not None:
            g = self.lead.target(g, t, self.gantry.link.excess_s())
            lead = self.lead.leads[-1]
        self.gantry.set_target(g)
        self.sent.append((t, g.copy(), lead))

    def sent_at(self, t_sent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gantry target sent [T, 2] m, its lead [T] s) for the runner's send times t_sent [T]
        (NaN: no send; each the first send at or after it: the runner reads its clock just
        before robot.send)."""
        t_sent = np.asarray(t_sent, np.float64)
        q, lead = np.full((t_sent.size, 2), np.nan), np.full(t_sent.size, np.nan)
        rec = list(self.sent)
        if not rec:
            return q, lead
        times = np.array([r[0] for r in rec])
        j = np.searchsorted(times, np.where(np.isfinite(t_sent), t_sent, np.inf))
        found = j < len(rec)
        q[found] = np.array([rec[k][1] for k in j[found]]).reshape(-1, 2)
        lead[found] = [rec[k][2] for k in j[found]]
        return q, lead

    def wait_for_feedback(self, timeout_s: float) -> None:
        """Until both parts have reported (ValueError naming the silent ones after timeout_s)."""
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            g, a = self.parts()
            if g is not None and a is not None:
                return
            time.sleep(0.01)
        g, a = self.parts()
        silent = [name for name, s in (("gantry (Modbus)", g), ("arm (EGM)", a)) if s is None]
        raise ValueError(f"no feedback from {' and '.join(silent)} within {timeout_s} s: is the "
                         f"controller streaming / the drive answering? (docs/ROBOT.md)")


class Launcher:
    """The rehearsal server's launcher and referee: one JSON object per line over TCP."""

    def __init__(self, cfg: LauncherConfig, timeout_s: float = 10.0):
        try:
            self.sock = socket.create_connection((cfg.host, cfg.port), timeout=timeout_s)
        except OSError as e:
            raise ValueError(f"launcher at {cfg.host}:{cfg.port}: cannot connect ({e.strerror or e})") from None
        self.file = self.sock.makefile("rwb")

    def call(self, cmd: str, **args) -> dict:
        self.file.write((json.dumps({"cmd": cmd, **args}) + "\n").encode())
        self.file.flush()
        line = self.file.readline()
        if not line:
            raise ValueError(f"launcher closed the connection during {cmd!r}")
        out = json.loads(line)
        if "error" in out:
            raise ValueError(f"launcher {cmd!r}: {out['error']}")
        return out

    def close(self) -> None:
        self.file.close()
        self.sock.close()


class Cell:
    """The open drivers of a cell (close() closes them all)."""

    def __init__(self, cfg: CellConfig, clock: Clock, contract: Contract, feedback_timeout_s: float = 5.0):
        self.cfg, self.clock, self.faults = cfg, clock, FaultLog()
        self._open = []
        try:
            self.tracker = self._keep(UdpTracker(cfg.tracker, clock, self.faults))
            self.arm = self._keep(EgmArm(cfg.egm, clock, contract.dt, self.faults).start())
            self.gantry = self._keep(ModbusGantry(cfg.gantry, clock, self.faults).start())
            self.launcher = self._keep(Launcher(cfg.launcher)) if cfg.launcher else None
            self.robot = CellRobot(self.gantry, self.arm, clock, limits_from_contract(contract))
            try:
                self.robot.wait_for_feedback(feedback_timeout_s)
            except ValueError as e:
                raise ValueError(f"{e}; driver faults so far: {dict(self.faults.counts) or 'none'}") from None
        except BaseException:
            self.close()
            raise

    def _keep(self, part):
        self._open.append(part)
        return part

    def close(self) -> None:
        for part in reversed(self._open):
            part.close()
        self._open = []


def run_cell(policy_dir: str, goals, config_path: str, out_dir: str | None = None,
             runner_config=None, throw_delay_s: float = 0.3, finish_s: float = 3.0,
             policy=None, contract: Contract | None = None) -> dict:
    """`ttmjx robot run --station cell`: the export in policy_dir (or `policy` + `contract`)
    played toward goals [N, 2] on the cell in config_path, on the real clock, in the robot
    side's one session loop (deploy.robot.session.run_session). With a [launcher] section each episode's
    throw is fired by it and completed with its referee's events (as the simulated station
    completes its own); without, the operator throws and the runner's trigger starts episodes.
    Returns the session summary (also written to out_dir/session.json)."""
    from deploy.robot.drivers.config import load_cell_config
    from deploy.robot.goals import check_goals
    from deploy.robot.hardware import MonotonicClock
    from deploy.robot.runner import Runner, RunnerConfig
    from deploy.robot.session import StationHooks, run_session
    cfg = load_cell_config(config_path)
    if policy is None:
        from deploy.robot.exported import load_export
        policy, contract = load_export(policy_dir)
    goals = check_goals(goals)
    sys.setswitchinterval(2e-4)     # the driver threads must answer within an EGM cycle (4 ms)
    clock = MonotonicClock()
    cell = Cell(cfg, clock, contract)
    try:
        runner = Runner(cell.robot, cell.tracker, clock, policy, contract, runner_config or RunnerConfig())
        station = _Session(runner, cell, throw_delay_s, finish_s, {"policy": policy_dir, "config": config_path})
        return run_session(runner, goals, out_dir, StationHooks(armed=station.armed, complete=station.complete,
                                                                no_ball=station.no_ball, summary=station.summary))
    finally:
        cell.close()


class _Session:
    """The cell's part of each episode (the launcher's throw and referee, the driver faults of
    its window) and of the session's summary (deploy.robot.session.run_session)."""

    def __init__(self, runner, cell: Cell, throw_delay_s: float, finish_s: float, about: dict):
        self.runner, self.cell, self.about = runner, cell, about
        self.throw_delay_s, self.finish_s = throw_delay_s, finish_s
        self.t_window = cell.clock.now()          # driver faults since then belong to the next episode

    def armed(self, i: int) -> None:
        if self.cell.launcher is not None:
            self.cell.launcher.call("throw", delay_s=self.throw_delay_s)
        return None                               # episodes start on the ball's track

    def no_ball(self, i: int) -> None:
        self.runner.disarm()
        if self.cell.launcher is not None:
            self.cell.launcher.call("finish", max_s=self.finish_s)

    def complete(self, i: int, ep):
        now = self.cell.clock.now()
        meta = {**ep.meta, "station": "cell",
                **window_summary(self.cell.faults.between(self.t_window, now)),
                "gantry_link": self.cell.gantry.link.report()}
        self.t_window = now
        from deploy.robot.episode_log import Episode
        sent, lead = self.cell.robot.sent_at(ep.extras["t_sent"])
        ep = Episode(ep.traj, {**ep.extras, "gantry_sent": sent, "gantry_lead_s": lead}, meta)
        if self.cell.launcher is None:
            return ep
        events = self.cell.launcher.call("finish", max_s=self.finish_s)["events"]
        from deploy.robot.outcomes import complete_episode
        ep = complete_episode(ep, _throw_events(events), self.runner.contract)
        return Episode(ep.traj, ep.extras, {**ep.meta, "station": "cell"})

    def summary(self, episodes, wall_s: float) -> dict:
        out = {**self.about, "driver_faults": dict(self.cell.faults.counts),
               "egm": {"received": self.cell.arm.received, "replies": self.cell.arm.replies},
               "gantry": {"reads": self.cell.gantry.reads, "writes": self.cell.gantry.writes,
                          "errors": self.cell.gantry.errors, "link": self.cell.gantry.link.report(),
                          "lead": None if self.cell.robot.lead is None else self.cell.robot.lead.report()},
               "tracker": {"received": self.cell.tracker.received, "dropped": self.cell.tracker.dropped}}
        if self.cell.launcher is not None:
            from deploy.robot.outcomes import goal_summary, latency_ms
            out["metrics"] = goal_summary(episodes)
            out["latency_ms"] = latency_ms(episodes)
        return out


def _throw_events(d: dict | None):
    """deploy.robot.outcomes.ThrowEvents from the referee's JSON (None values are NaN)."""
    if d is None:
        return None
    from deploy.robot.outcomes import ThrowEvents
    kw = {}
    for f in dataclasses.fields(ThrowEvents):
        v = d[f.name]
        if isinstance(v, list):
            v = np.array([np.nan if x is None else x for x in v], np.float64)
        elif v is None:
            v = float("nan")
        kw[f.name] = v
    return ThrowEvents(**kw)
