"""The cell's drivers (deploy/robot/drivers/) against `ttmjx robot serve` over real loopback sockets:
a whole session plays through them, and each injected fault ends as it must (a logged driver
fault, HOLD where the data cannot be trusted), never in a traceback or a command on bad data.

One server process for the module (the simulated station on the real clock, faults switched
through its launcher between sessions); the policy is the scripted FollowBallPolicy (numpy)."""
from __future__ import annotations

import dataclasses
import os
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("abb_robot_client")
pytest.importorskip("pymodbus")

from conftest import machine_stalled  # noqa: E402
from deploy.robot.contract import Contract  # noqa: E402
from deploy.robot.drivers import config as cellconfig  # noqa: E402
from deploy.robot.drivers.cell import Launcher, run_cell
from deploy.robot.drivers.tracker import WIRE, pack_sample, unpack_sample  # noqa: E402
from deploy.robot.episode_log import load_episode  # noqa: E402
from deploy.robot.fakes import FollowBallPolicy  # noqa: E402
from deploy.robot.runner import RunnerConfig  # noqa: E402
from deploy.sim.serve import (
    parse_faults,  # noqa: E402
    serving,  # noqa: E402
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CONTRACT = Contract(control_hz=20.0)
GOALS = [[0.7, 0.3], [0.5, -0.4]]
# stale_s 0.25 (the runner's default is 0.1): these sessions are about the wire and the faults
# the server injects, not about stalls of a 2-core CI machine running the suite with a cold
# compilation cache, where one ~100 ms stall of the pair still happens at times (cause not
# attributed; the runner's own garbage-collector pauses, which held it in CI before, are gone).
# The default limit is exercised by the quiet-machine rehearsals of scripts/cell_figures.py
# (docs/RESULTS.md: 40/40 episodes per session, no HOLD). The stop tests stop for 0.9 s.
QUICK = RunnerConfig(arm_timeout_s=2.0, home_timeout_s=5.0, stale_s=0.25)


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """(config path, CellConfig, launcher, tmp) of a running `ttmjx robot serve`."""
    tmp = tmp_path_factory.mktemp("cell")
    path = tmp / "cell.toml"
    cfg = cellconfig.loopback_config()
    path.write_text(cellconfig.to_toml(cfg))
    with serving(path, "--control-hz", "20", "--seed", "3", env={"JAX_PLATFORMS": "cpu"}):
        launcher = Launcher(cfg.launcher)
        yield str(path), cfg, launcher, tmp
        launcher.close()


def session(served, name, faults="", goals=GOALS, config=QUICK):
    """run_cell (what `ttmjx robot run --station cell` runs) with faults set on the server;
    returns (summary, episodes as saved, server stats)."""
    path, _, launcher, tmp = served
    launcher.call("faults", spec=faults)
    out = tmp / name
    summary = run_cell(None, goals, path, str(out), runner_config=config,
                       policy=FollowBallPolicy(CONTRACT), contract=CONTRACT)
    stats = launcher.call("stats")
    launcher.call("faults", spec="")
    eps = [load_episode(str(out), f"episode_{i:04d}") for i in range(summary["episodes"])]
    return summary, eps, stats


def latched(summary) -> set:
    from deploy.robot.safety import FAULTS, LATCHING
    return {k for k in summary["faults"] if k in FAULTS and FAULTS[k] & LATCHING}


def test_a_session_plays_through_the_drivers(served):
    summary, eps, stats = session(served, "clean")
    if summary["mode"] == "hold" and machine_stalled(summary, stats):
        # A cold-cache suite on 2 cores still stalls the pair ~100+ ms at times (the runner's
        # garbage-collector pauses, which held it in CI before, are gone; the rest is not
        # attributed): with the stall on record, the session is played once more.
        print(f"machine stall (skipped ticks {summary['faults'].get('skipped', 0)}, serve loop gap "
              f"{stats['counts'].get('loop_max_gap_ms')} ms): session played again")
        summary, eps, stats = session(served, "clean_again")
    assert summary["episodes"] == len(GOALS) and summary["mode"] == "idle", (summary["ends"], summary["faults"], summary["driver_faults"], stats)
    assert [e.meta["end"] for e in eps] == ["done"] * len(GOALS)
    assert all(e.meta["events_detected"] and e.meta["station"] == "cell" for e in eps)
    assert all(e.extras["executed"].sum() >= 0.8 * CONTRACT.horizon for e in eps)
    assert summary["egm"]["replies"] > 100 and summary["gantry"]["writes"] > 10
    assert summary["tracker"]["received"] > 50 and not latched(summary)
    # every command reached the station: the arm's last target is the runner's last command
    assert stats["counts"]["egm_replies"] > 100 and stats["counts"]["modbus_targets"] > 10
    assert stats["counts"].get("egm_bad_replies", 0) == 0
    # a nominal link: no lead, the gantry sent the runner's commands (drivers/lead.py)
    assert summary["gantry"]["lead"]["enabled"] and summary["gantry"]["lead"]["lead_p50_ms"] == 0.0
    shift = np.concatenate([np.abs(e.extras["gantry_sent"] - e.extras["commands"][:, 0:2]).max(axis=1)[e.extras["executed"].astype(bool)]
                            for e in eps])
    assert np.median(shift) <= 1e-12, shift


def test_a_slow_gantry_link_is_measured_and_led_within_the_limits(served):
    """modbus.delay_ms=10 over a whole session: the session reports the link's excess latency
    (within 3 ms of the delay) and leads the gantry's targets by it (the lead's median), every
    target sent within the contract's range and speed limits; the opt-out
    ([gantry] compensate_latency = false) sends the commands as given, its excess still
    reported."""
    from deploy.robot.safety import count_violations, limits_from_contract
    path, cfg, _, tmp = served
    summary, eps, _ = session(served, "slow_gantry", faults="modbus.delay_ms=10")
    link, lead = summary["gantry"]["link"], summary["gantry"]["lead"]
    print(f"slow gantry link: {link}, lead: {lead}")
    assert abs(link["excess_ms"] - 10.0) < 3.0 and abs(lead["lead_p50_ms"] - 10.0) < 3.0, (link, lead)
    assert lead["led"] > 0.5 * lead["targets"] and eps[0].meta["gantry_link"]["excess_ms"] > 5.0
    limits = limits_from_contract(CONTRACT)
    for e in eps:
        ran = e.extras["executed"].astype(bool)
        sent = e.extras["commands"][ran].copy()
        sent[:, 0:2] = e.extras["gantry_sent"][ran]
        v = count_violations(limits, e.extras["t_sent"][ran], sent, tol=1e-9)
        assert v.nonfinite == v.range == v.step == 0, v
    off = tmp / "no_lead.toml"
    off.write_text(cellconfig.to_toml(dataclasses.replace(
        cfg, gantry=dataclasses.replace(cfg.gantry, compensate_latency=False))))
    summary, eps, _ = session((str(off),) + served[1:], "slow_gantry_no_lead", faults="modbus.delay_ms=10")
    assert not summary["gantry"]["lead"]["enabled"] and summary["gantry"]["lead"]["led"] == 0
    assert summary["gantry"]["link"]["excess_ms"] > 5.0
    for e in eps:
        ran = e.extras["executed"].astype(bool)
        assert np.array_equal(e.extras["gantry_sent"][ran], e.extras["commands"][ran, 0:2])


def test_lossy_networks_are_logged_and_survived(served):
    faults = ("egm.loss=0.05,egm.duplicate=0.05,egm.reorder=0.05,egm.malformed=0.02,"
              "tracker.loss=0.05,tracker.duplicate=0.05,tracker.reorder=0.05,tracker.malformed=0.05,"
              "modbus.delay_ms=10")
    summary, eps, stats = session(served, "lossy", faults, goals=GOALS[:1])
    assert [e.meta["end"] for e in eps] == ["done"], (summary["driver_faults"], summary["faults"], stats)
    found = set(summary["driver_faults"])
    assert {"egm_seq_gap", "egm_seq_old", "egm_malformed", "tracker_malformed"} <= found, found
    assert stats["egm"]["lost"] > 0 and stats["tracker"]["reordered"] > 0
    assert eps[0].meta["driver_faults"], "the episode log carries its window's driver faults"


@pytest.mark.parametrize("faults,runner_fault,driver_fault", [
    ("egm.nan=1", "joint_nonfinite", None),
    ("egm.range=1", "joint_out_of_range", None),
    ("egm.motors_off_s=0", "robot_fault", "egm_motors_off"),
    ("egm.rapid_stopped_s=0", "robot_fault", "egm_rapid_stopped"),
    ("modbus.fault_s=0", "robot_fault", "gantry_drive_fault"),
])
def test_bad_feedback_holds_and_sends_nothing_from_it(served, faults, runner_fault, driver_fault):
    """From the first message the data are bad: HOLD before any episode, the reason logged,
    and no reply carries a target computed from the bad data."""
    path, _, launcher, _ = served
    before = launcher.call("stats")["counts"].get("egm_bad_replies", 0)
    summary, eps, stats = session(served, "bad_" + faults.split("=")[0], faults, goals=GOALS[:1])
    assert summary["mode"] == "hold" and runner_fault in summary["faults"], summary
    assert driver_fault is None or driver_fault in summary["driver_faults"], summary
    # a device fault is named in the runner's faults (Robot.fault()), not only seen as bad joints
    assert driver_fault is None or f"robot_fault:{driver_fault}" in summary["faults"], summary
    assert stats["counts"].get("egm_bad_replies", 0) == before


@pytest.mark.parametrize("faults,driver_fault", [("egm.msgtype=1", "egm_msgtype"),
                                                ("egm.malformed=1", "egm_malformed")])
def test_a_controller_sending_only_bad_messages_is_a_clear_error(served, faults, driver_fault):
    """Nothing valid ever arrives: the cell does not start (one line naming the silent part and
    the driver faults seen); no reply was sent."""
    path, _, launcher, _ = served
    with pytest.raises(ValueError, match=f"no feedback from arm \\(EGM\\).*{driver_fault}") as e:
        session(served, "only_" + faults.split("=")[0], faults, goals=GOALS[:1])
    launcher.call("faults", spec="")
    assert e.value.args[0].count("\n") == 0


@pytest.mark.parametrize("faults,driver_fault", [
    ("egm.stop_s=0.9", "egm_stream_stopped"),
    ("modbus.stop_s=0.9", "gantry_transaction"),
])
def test_a_stream_that_stops_mid_session_holds(served, faults, driver_fault):
    summary, eps, _ = session(served, "stop_" + faults.split(".")[0], faults, goals=GOALS[:1])
    assert summary["mode"] == "hold" and "joint_stale" in summary["faults"], summary
    assert driver_fault in summary["driver_faults"], summary
    for e in eps:                               # an episode that ran ends in the hold
        assert e.meta["end"] == "hold: joint_stale"
        sent = np.flatnonzero(np.isfinite(e.extras["t_sent"]))
        stale = np.flatnonzero(e.extras["faults"] & 4)   # joint_stale
        assert len(stale) and (not len(sent) or sent.max() < stale.min())


def test_tracker_samples_from_the_future_are_dropped(served):
    summary, eps, _ = session(served, "future", "tracker.future=1", goals=GOALS[:1])
    assert summary["episodes"] == 0 and summary["faults"].get("ball_dropped_samples", 0) > 10, summary
    assert summary["mode"] == "idle"            # no ball came: disarmed, not a fault


# ------------------------------------------------------------------------ without a server
def test_tracker_wire_format():
    buf = pack_sample(2 ** 32 + 5, 12.5, [0.1, -0.2, 0.3])
    assert len(buf) == WIRE.size == 36
    seq, t, xyz = unpack_sample(buf)
    assert seq == 5 and t == 12.5 and np.allclose(xyz, [0.1, -0.2, 0.3])
    with pytest.raises(ValueError, match="35 bytes, expected 36"):
        unpack_sample(buf[:-1])
    with pytest.raises(ValueError, match="non-finite"):
        unpack_sample(pack_sample(1, float("nan"), [0, 0, 0]))


def test_bad_fault_specs_and_configs_name_the_value(tmp_path):
    assert parse_faults("egm.loss=0.05, modbus.delay_ms=10").spec == {"egm": {"loss": 0.05}, "modbus": {"delay_ms": 10.0}}
    for spec, match in [("egm.loss=2", "egm.loss=2: expected a probability"),
                        ("gps.loss=0.1", "'gps.loss=0.1'"), ("egm.loss=x", "expected a number"),
                        ("tracker.nan=1", "'tracker.nan=1'")]:
        with pytest.raises(ValueError, match=match):
            parse_faults(spec)
    for text, match in [("[egm]\nport = 70000\n", "port = 70000"), ("[egm]\nprt = 1\n", "egm].prt: unknown key"),
                        ("[gantry.registers]\nword_order = 'middle'\n", "word_order = 'middle'"),
                        ("[robot]\n", r"unknown section \[robot\]"), ("[egm\n", "not valid TOML"),
                        ("[gantry]\nstale_s = 0.5\n", r"gantry\].stale_s = 0.5: expected at most 0.25"),
                        ("[gantry]\ncompensate_latency = 1\n", r"compensate_latency = 1: expected a bool"),
                        ("[gantry]\nforward_share = 1.5\n", r"forward_share = 1.5: expected a share")]:
        (tmp_path / "c.toml").write_text(text)
        with pytest.raises(ValueError, match=match):
            cellconfig.load_cell_config(str(tmp_path / "c.toml"))
    off = cellconfig.CellConfig(gantry=cellconfig.GantryConfig(compensate_latency=False, forward_share=1.0))
    (tmp_path / "c.toml").write_text(cellconfig.to_toml(off))
    assert cellconfig.load_cell_config(str(tmp_path / "c.toml")) == off


def test_ports_in_use_and_unreachable_drive_are_one_line_errors(tmp_path):
    path = tmp_path / "cell.toml"
    cfg = dataclasses.replace(cellconfig.loopback_config(), launcher=None)
    path.write_text(cellconfig.to_toml(cfg))
    taken = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    taken.bind(("0.0.0.0", cfg.egm.port))
    try:
        with pytest.raises(ValueError, match=f"egm port {cfg.egm.port} is already in use"):
            run_cell(None, GOALS, str(path), policy=FollowBallPolicy(CONTRACT), contract=CONTRACT)
    finally:
        taken.close()
    with pytest.raises(ValueError, match=f"cannot connect to the Modbus TCP drive at 127.0.0.1:{cfg.gantry.port}"):
        run_cell(None, GOALS, str(path), policy=FollowBallPolicy(CONTRACT), contract=CONTRACT)
    env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
    listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    listen.bind(("127.0.0.1", cfg.gantry.port))
    listen.listen()
    try:
        r = subprocess.run([sys.executable, "-m", "ttmjx", "robot", "serve", "--config", str(path)],
                           capture_output=True, text=True, env=env, timeout=120)
    finally:
        listen.close()
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert f"gantry (Modbus) port {cfg.gantry.port}" in r.stderr and "Traceback" not in r.stderr


def test_served_arm_and_gantry_ramp_apart():
    """serve's station: each half of a command ramps from its own arrival; the gantry's half
    arriving later does not restart the arm's ramp (deploy/sim/serve_station.py)."""
    from deploy.sim.serve_station import ServedStation
    from deploy.sim.station import TIMING, SimClock
    from ttmjx.world.config import World
    clock = SimClock()
    s = ServedStation(World(control_hz=100), CONTRACT, clock=clock, timing=TIMING["zero"])
    q0 = s.joints()
    arm, gantry = q0[2:8] + 0.1, q0[0:2] + 0.05
    s.set_part_target("arm", arm, 0.0)
    s.set_part_target("gantry", gantry, 0.004)
    ramp = s.ramp_s
    assert np.allclose(s._ctrl_at(ramp)[2:8], arm) and np.allclose(s._ctrl_at(ramp)[0:2], q0[0:2] + 0.05 * (ramp - 0.004) / ramp)
    assert np.allclose(s._ctrl_at(ramp + 0.004), np.concatenate([gantry, arm]))
    assert np.allclose(s._ctrl_at(ramp / 2)[2:8], q0[2:8] + 0.05)


def joined_robot():
    """(CellRobot over a real ModbusGantry and EgmArm without sockets, clock, feed(t, part, q))."""
    import threading

    from deploy.robot.drivers import egm as egm_mod
    from deploy.robot.drivers import gantry as gantry_mod
    from deploy.robot.drivers.cell import CellRobot
    from deploy.robot.drivers.history import SampleHistory
    from deploy.robot.fakes import FakeClock
    cfg = cellconfig.CellConfig()
    clock = FakeClock(start=0.0)
    gantry, arm = object.__new__(gantry_mod.ModbusGantry), object.__new__(egm_mod.EgmArm)
    for part, c, keep in ((gantry, cfg.gantry, gantry_mod.HISTORY), (arm, cfg.egm, egm_mod.HISTORY)):
        part.cfg, part._lock, part.latched, part.sample, part.history = c, threading.Lock(), None, None, SampleHistory(keep)

    def feed(t, part, q):
        dev = gantry if part == "gantry" else arm
        dev.sample = (t, np.asarray(q, np.float64))
        dev.history.append(t, q)
    return CellRobot(gantry, arm, clock), clock, feed


def test_a_stalled_gantry_reading_is_not_joined_as_a_jump():
    """After a stall of both streams (55 ms, as a loaded serve once did) the arm's message can
    come before the gantry's reading: the joined samples must still move the gantry no faster
    than it moved (the runner's joint_jump check compares their stamps), so the parts are
    joined where the gantry's line still reaches (deploy/robot/drivers/cell.py)."""
    robot, clock, feed = joined_robot()
    v = 0.8                                                   # m/s, the gantry's x; the arm's j1
    events = [(t, "gantry") for t in np.arange(0.0, 0.1, 0.01)]
    events += [(t, "arm") for t in np.arange(0.0, 0.1, 0.004)]
    events += [(0.157, "arm"), (0.159, "gantry")]             # after the stall: the arm first
    events += [(t, "arm") for t in np.arange(0.161, 0.25, 0.004)]
    events += [(t, "gantry") for t in np.arange(0.169, 0.25, 0.01)]
    joined = []
    for t, part in sorted(events):
        clock.t = t
        feed(t, part, [v * t, 0.0] if part == "gantry" else [v * t, 0, 0, 0, 0, 0])
        s, q = robot.read()
        if np.isfinite(s) and (not joined or s > joined[-1][0]):
            joined.append((s, q[0], q[2]))
    ts, xs, js = np.array(joined).T
    assert ts.max() > 0.2 and ((ts > 0.1 + 1e-9) & (ts < 0.157)).sum() == 0
    np.testing.assert_allclose(js, v * ts, atol=1e-9)          # the arm read at the joined time
    rc = RunnerConfig()                                       # the runner's rule, at the true speed
    excess = np.abs(np.diff(xs)) - (rc.jump_factor * v * np.diff(ts) + rc.jump_tolerance)
    assert excess.max() <= 0, (excess.max(), ts[np.argmax(excess) + 1])


def test_one_late_gantry_reading_does_not_freeze_the_joined_sample():
    """The runner read nothing for 0.4 s (it was saving an episode) and the gantry's newest
    reading is 46 ms old when it reads again: the joined sample is the gantry's line's end, not
    the sample of 0.4 s ago (which the runner would find stale at once)."""
    robot, clock, feed = joined_robot()
    for t in np.arange(0.0, 0.02, 0.004):
        clock.t = t
        feed(t, "arm", np.zeros(6))
        feed(t, "gantry", np.zeros(2))
        robot.read()
    for t in np.arange(0.02, 0.5, 0.004):
        feed(t, "arm", np.zeros(6))
    for t in np.arange(0.02, 0.45, 0.01):
        feed(t, "gantry", np.zeros(2))
    clock.t = 0.5
    s, _ = robot.read()
    assert s == pytest.approx(0.44 + 0.01), s


def test_messages_queued_behind_a_late_driver_thread_keep_only_the_newest():
    """Real EGM over loopback: three controller messages wait before the driver's thread reads
    (a stall of the runner's process); all are checked, only the newest is kept and answered
    once. A motors-off message inside a burst still latches."""
    from abb_robot_client._egm_protobuf import egm_pb2

    from deploy.robot.drivers.egm import DATA, MOTORS_ON, RAPID_RUNNING, EgmArm
    from deploy.robot.hardware import MonotonicClock

    def message(seq, deg, motors=MOTORS_ON):
        m = egm_pb2.EgmRobot()
        m.header.seqno, m.header.tm, m.header.mtype = seq, seq * 4, DATA
        m.feedBack.joints.joints.extend([float(deg)] * 6)
        m.motorState.state, m.rapidExecState.state = motors, RAPID_RUNNING
        return m.SerializeToString()

    cfg = cellconfig.EgmConfig(port=cellconfig.free_port(socket.SOCK_DGRAM))
    arm = EgmArm(cfg, MonotonicClock(), control_dt=0.01)     # bound, its thread not yet reading
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", 0))
    ctl.settimeout(2.0)
    try:
        for seq, deg in ((1, 10.0), (2, 20.0), (3, 30.0)):
            ctl.sendto(message(seq, deg), ("127.0.0.1", cfg.port))
        time.sleep(0.05)
        arm.start()
        ctl.recvfrom(65536)                                   # the one reply
        ctl.settimeout(0.2)
        with pytest.raises(socket.timeout):
            ctl.recvfrom(65536)
        assert arm.received == 3 and arm.buffered == 2 and arm.replies == 1
        t, q = arm.read()
        np.testing.assert_allclose(q, np.deg2rad(30.0))
        assert len(arm.history) == 1
        for seq, deg, motors in ((4, 31.0, egm_pb2.EgmMotorState.MOTORS_OFF), (5, 32.0, MOTORS_ON)):
            ctl.sendto(message(seq, deg, motors), ("127.0.0.1", cfg.port))
        deadline = time.monotonic() + 2.0
        while arm.received < 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert arm.latched == "egm_motors_off" and np.isnan(arm.read()[1]).all()
        assert arm.faults.counts["egm_motors_off"] == 1 and not arm.faults.counts.get("egm_seq_gap")
    finally:
        ctl.close()
        arm.close()


def test_gantry_replies_late_by_a_poll_period_are_dropped_a_slower_drive_is_not(served):
    """Against serve's drive: replies turned 40 ms slower (the usual ~1 ms) lose their positions
    as late (gantry_late_reply), at most MAX_LATE_DROPS in a row, so readings still come; back to
    the usual speed, nothing more is dropped than at the usual speed before. (On a loaded machine
    a usual reply can itself come late; the window before the fault measures how often, so the
    test asks about the drive, not about the machine's load.)"""
    from deploy.robot.drivers.gantry import MAX_LATE_DROPS, ModbusGantry
    from deploy.robot.hardware import MonotonicClock
    _, cfg, launcher, _ = served
    g = ModbusGantry(cfg.gantry, MonotonicClock()).start()
    late_now = lambda: g.faults.counts.get("gantry_late_reply", 0)  # noqa: E731
    try:
        deadline = time.monotonic() + 10.0       # the first readings, however loaded the machine
        while g.reads <= 10 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert g.reads > 10
        before = late_now()
        time.sleep(0.6)
        usual = late_now() - before                                # at the usual speed, this machine
        launcher.call("faults", spec="modbus.delay_ms=40")
        reads, start = g.reads, late_now()
        time.sleep(0.6)
        launcher.call("faults", spec="")
        late, during = late_now() - start, g.reads - reads
        assert late >= MAX_LATE_DROPS and during >= 2, (late, during)
        assert late <= MAX_LATE_DROPS * (during + 1) + usual       # never more than 2 in a row
        after = late_now()
        time.sleep(0.6)
        assert late_now() - after <= usual + MAX_LATE_DROPS, (usual, late_now() - after)   # the slow tail only
        assert not g.latched
    finally:
        launcher.call("faults", spec="")
        g.close()


# ------------------------------------------------------------------------ the links' own delay
def _targets_through(g, launcher, n: int, period_s: float = 0.01) -> tuple[np.ndarray, int]:
    """Set n distinct gantry targets at 1 / period_s (the runner's 100 Hz) through driver g and
    return (each target's transport time, s, from set_target to its arrival at serve's drive,
    NaN if it never arrived; reads the driver took meanwhile)."""
    deadline = time.monotonic() + 10.0          # the first readings, however loaded the machine
    while g.read() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    q0 = g.read()[1]
    reads, t0 = g.reads, time.monotonic()
    sent = []
    for i in range(n):                          # 0.1 mm apart: whole counts, each one distinct
        target = q0 + np.array([1e-4 * (i + 1), 0.0])
        t = time.monotonic()
        g.set_target(target)
        sent.append((t, round(target[0] * g.regs.counts_per_m)))
        time.sleep(max(0.0, t0 + (i + 1) * period_s - time.monotonic()))
    time.sleep(0.2)                             # the last ones on their way
    reads = g.reads - reads
    arrived = {round(x * g.regs.counts_per_m): t for t, part, (x, _) in launcher.call("arrivals", since=t0)["arrivals"]
               if part == "gantry"}
    return np.array([arrived.get(c, np.nan) - t for t, c in sent]), reads


def test_a_gantry_target_reaches_the_drive_after_the_links_delay_alone(served):
    """With modbus.delay_ms=10 (every request 10 ms on its way) and targets at 100 Hz, every
    target reaches serve's drive, each 10 ms later than over the clean link, not later: it leaves
    at once, neither behind the read in flight (100 Hz polls over a 10 ms link always have one)
    nor behind the previous target's write; and the reads keep their rate. A client that waits
    for each reply on one connection delivered every other target, ~15 ms late (docs/ROBOT.md).
    Margin: besides the clean link's own transport (measured here), a target that waits for the
    transaction in flight waits up to a whole one, the delay itself, half of it on average; one
    that does not wait gets only serve's event loop's millisecond timers (epoll) on top. So the
    median of the rest is held under a quarter of the delay (halfway between the two designs).
    Its tail is not held: on a loaded 2-core machine (the test suite's two workers) the tail is
    the scheduler's (p90 +5.3 ms measured there), not the driver's. Reads: a client that waits
    for each reply fits at most one read per two transactions while it writes (1 / 2d = 50 a
    second at d = 10 ms), one that keeps one read in flight one per transaction (1 / d = 100,
    the poll rate); held above the midpoint, 75 a second."""
    from deploy.robot.drivers.gantry import ModbusGantry
    from deploy.robot.hardware import MonotonicClock
    _, cfg, launcher, _ = served
    delay = 0.010

    def unbroken(n):
        """_targets_through, again if a stall of this machine outlasted the driver's timeout_s
        (it then drops the connection and what was in flight, as designed: logged as
        gantry_transaction); the test measures the link, not the machine's stalls."""
        for _ in range(3):
            errors = g.errors
            out = _targets_through(g, launcher, n)
            if g.errors == errors:
                return out
        pytest.fail(f"every try of {n} targets lost its connection to a stall (timeout_s {cfg.gantry.timeout_s} s)")

    g = ModbusGantry(cfg.gantry, MonotonicClock()).start()
    try:
        clean, _ = unbroken(50)
        launcher.call("faults", spec=f"modbus.delay_ms={1000 * delay:g}")
        late, reads = unbroken(100)
    finally:
        launcher.call("faults", spec="")
        g.close()
    assert np.isfinite(clean).all() and np.isfinite(late).all(), (np.isnan(clean).sum(), np.isnan(late).sum())
    own = np.median(clean)                      # one transaction's cost besides the delay
    print(f"gantry target transport: clean p50 {1e3 * own:.2f} ms; {1e3 * delay:g} ms link p50 "
          f"{1e3 * np.median(late):.2f} ms, p90 {1e3 * np.quantile(late, 0.9):.2f} ms, max {1e3 * late.max():.2f} ms; "
          f"{reads} reads in 1 s")
    extra = late - delay - own
    assert abs(np.median(extra)) < delay / 4, (1e3 * np.median(late), 1e3 * own)
    assert late.min() >= delay - 1e-3, 1e3 * late.min()           # the fault itself still holds
    # one read in flight at a time, back to back when a reply takes the poll period
    pipelined, one_by_one = min(cfg.gantry.poll_hz, 1.0 / delay), 1.0 / (2 * delay)
    assert reads >= (pipelined + one_by_one) / 2 * 1.0, (reads, pipelined, one_by_one)


def test_serves_drive_answers_pipelined_requests_each_after_the_delay(served):
    """Two read requests in one TCP segment over a 30 ms link: each answered with its own
    transaction id, both ~30 ms after they left (side by side on the link, not one after the
    other). pymodbus's own server handler left the second unread until more data came."""
    import struct
    _, cfg, launcher, _ = served
    r = cfg.gantry.registers
    delay = 0.030
    launcher.call("faults", spec=f"modbus.delay_ms={1000 * delay:g}")
    s = socket.create_connection((cfg.gantry.host, cfg.gantry.port), timeout=2.0)
    try:
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        frames = b"".join(struct.pack(">HHHBBHH", tid, 0, 6, cfg.gantry.device_id, 3, r.status, 1) for tid in (7, 8))
        t0 = time.monotonic()
        s.sendall(frames)
        replies, buf = {}, b""
        while len(replies) < 2:
            buf += s.recv(4096)
            while len(buf) >= 6 and len(buf) >= 6 + struct.unpack_from(">H", buf, 4)[0]:
                n = 6 + struct.unpack_from(">H", buf, 4)[0]
                replies[struct.unpack_from(">H", buf)[0]] = (time.monotonic() - t0, buf[7:n])
                buf = buf[n:]
    finally:
        s.close()
        launcher.call("faults", spec="")
    assert sorted(replies) == [7, 8]
    for tid, (dt, pdu) in replies.items():
        assert pdu[0] == 3 and pdu[1] == 2, (tid, pdu)             # one register read, no exception
        assert delay - 1e-3 <= dt < 1.5 * delay, (tid, dt)          # not 2 x delay for the second


def test_a_lost_egm_message_holds_the_arms_target_one_cycle_at_most():
    """Real EGM over loopback: the controller's message 2 is lost; the reply to message 3 (the
    next one) carries the runner's newest target, set while 2 was missing, and the gap is logged."""
    from abb_robot_client._egm_protobuf import egm_pb2

    from deploy.robot.drivers.egm import DATA, MOTORS_ON, RAPID_RUNNING, EgmArm
    from deploy.robot.hardware import MonotonicClock

    def message(seq):
        m = egm_pb2.EgmRobot()
        m.header.seqno, m.header.tm, m.header.mtype = seq, seq * 4, DATA
        m.feedBack.joints.joints.extend([10.0] * 6)
        m.motorState.state, m.rapidExecState.state = MOTORS_ON, RAPID_RUNNING
        return m.SerializeToString()

    def reply():
        m = egm_pb2.EgmSensor()
        m.ParseFromString(ctl.recvfrom(65536)[0])
        return np.deg2rad(np.asarray(m.planned.joints.joints))

    cfg = cellconfig.EgmConfig(port=cellconfig.free_port(socket.SOCK_DGRAM))
    arm = EgmArm(cfg, MonotonicClock(), control_dt=0.01).start()
    ctl = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ctl.bind(("127.0.0.1", 0))
    ctl.settimeout(2.0)
    try:
        a, b = np.full(6, 0.1), np.full(6, 0.2)
        arm.set_target(a)
        ctl.sendto(message(1), ("127.0.0.1", cfg.port))
        np.testing.assert_allclose(reply(), a)
        arm.set_target(b)                       # message 2 (lost) would have carried it
        ctl.sendto(message(3), ("127.0.0.1", cfg.port))
        np.testing.assert_allclose(reply(), b)
        assert arm.faults.counts["egm_seq_gap"] == 1
    finally:
        ctl.close()
        arm.close()


def test_the_newest_gantry_target_reaches_the_drive_through_lost_requests(served):
    """modbus.loss=0.3 over a 10 ms link: requests lost (the drive answers 'gateway: no
    response' and does nothing), and a write in flight behind a lost one carries the
    new-setpoint bit the drive still holds (it starts nothing). Whatever was lost, the newest
    target before each pause reaches the drive: the driver follows the drive's bit from the
    replies and sends the newest again with the bit the drive does not hold."""
    from deploy.robot.drivers.gantry import ModbusGantry
    from deploy.robot.hardware import MonotonicClock
    _, cfg, launcher, _ = served
    g = ModbusGantry(cfg.gantry, MonotonicClock()).start()
    try:
        deadline = time.monotonic() + 10.0
        while g.read() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        q0 = g.read()[1]
        launcher.call("faults", spec="modbus.loss=0.3,modbus.delay_ms=10")
        t0, newest = time.monotonic(), []
        for burst in range(10):                 # 5 targets at 100 Hz, then 0.15 s of nothing new
            for i in range(5):
                target = q0 + np.array([1e-4 * (5 * burst + i + 1), 0.0])
                g.set_target(target)
                time.sleep(0.01)
            newest.append(round(target[0] * g.regs.counts_per_m))
            time.sleep(0.15)
        arrived = {round(x * g.regs.counts_per_m) for _, part, (x, _) in launcher.call("arrivals", since=t0)["arrivals"]
                   if part == "gantry"}
        lost = launcher.call("stats")["counts"].get("modbus_lost", 0)
    finally:
        launcher.call("faults", spec="")
        g.close()
    assert lost > 5, lost
    assert [c in arrived for c in newest] == [True] * len(newest), (newest, sorted(arrived))


# ------------------------------------------------------------------------ the gantry link's lead
def test_the_gantry_lead_extrapolates_a_ramp_as_a_plain_first_order_predictor():
    """drivers/lead.py, GantryLead against a plain reference on a known ramp: each target sent is
    the target plus the ramp's velocity times the lead (v from the last two targets; the first
    as given); no excess, or the opt-out, sends every target unchanged; a lead the speed limit
    cannot follow is filtered as any command is (steps within speed x dt, within the range)."""
    from deploy.robot.drivers.lead import MAX_LEAD_S, GantryLead
    from deploy.robot.safety import Limits
    dt, v = 0.01, np.array([0.4, -0.25])                 # s; m/s, within the limits below
    wide = Limits(np.array([-5.0, -5.0]), np.array([5.0, 5.0]), np.array([2.0, 2.0]), dt)
    t = np.arange(30) * dt
    ramp = np.array([0.1, 0.2]) + t[:, None] * v
    lead = 0.009
    g = GantryLead(wide)
    sent = np.array([g.target(q, tk, lead) for tk, q in zip(t, ramp)])
    reference = ramp + v * lead                          # where the ramp is lead later
    reference[0] = ramp[0]                               # no velocity yet from one target
    np.testing.assert_allclose(sent, reference, rtol=0, atol=1e-12)
    assert g.report()["led"] == len(t) and g.report()["lead_p50_ms"] == pytest.approx(1e3 * lead)
    for excess, enabled in ((0.0, True), (lead, False)):
        h = GantryLead(wide, enabled)
        assert all(np.array_equal(h.target(q, tk, excess), q) for tk, q in zip(t, ramp))
        assert h.report()["led"] == 0
    # capped at MAX_LEAD_S
    c = GantryLead(wide)
    out = [c.target(q, tk, 1.0) for tk, q in zip(t[:3], ramp[:3])]
    np.testing.assert_allclose(out[2], ramp[2] + v * MAX_LEAD_S, rtol=0, atol=1e-12)
    # a speed limit the led ramp would break (its first led step jumps by v x lead): filtered
    tight = Limits(np.array([-5.0, -5.0]), np.array([0.3, 5.0]), np.abs(v) * 1.05, dt)
    f = GantryLead(tight)
    sent = np.array([f.target(q, tk, lead) for tk, q in zip(t, ramp)])
    assert np.all(np.abs(np.diff(sent, axis=0)) <= tight.speed * dt + 1e-12)
    assert np.all(sent[:, 0] <= 0.3) and f.limited > 0


def test_the_link_latency_is_the_median_round_trip_not_its_stalls():
    """LinkLatency: the median of the recent round trips, scaled by forward_share; stalls of
    this machine (a few 100 ms round trips) move it by nothing; the excess is what is above the
    arm's own half EGM cycle, 0 before MIN_REPLIES and on a nominal link."""
    from deploy.robot.drivers.lead import ALLOWANCE_S, MIN_REPLIES, LinkLatency
    link = LinkLatency(0.5)
    for _ in range(MIN_REPLIES - 1):
        link.add(0.020)
    assert link.excess_s() == 0.0 and link.report()["rtt_p50_ms"] is None
    for i in range(60):
        link.add(0.100 if i % 10 == 0 else 0.020)
    assert link.forward_s() == pytest.approx(0.010) and link.excess_s() == pytest.approx(0.010 - ALLOWANCE_S)
    nominal = LinkLatency(1.0)
    for _ in range(40):
        nominal.add(0.0008)
    assert nominal.excess_s() == 0.0
    with pytest.raises(ValueError, match="forward_share = 0: expected a share"):
        LinkLatency(0)


def test_the_gantry_link_estimate_follows_an_injected_delay(served):
    """Over serve's drive (loopback_config: forward_share 1, its link delays requests only): on
    the clean link the estimated excess is 0 (no lead: the targets go as given); with
    modbus.delay_ms=10 the forward latency is the delay plus serve's own (~1 ms of millisecond
    timers), so the excess is within 3 ms of the injected delay. Medians of the estimate along
    the run, not its tail (a loaded 2-core machine)."""
    from deploy.robot.drivers.gantry import ModbusGantry
    from deploy.robot.hardware import MonotonicClock
    _, cfg, launcher, _ = served
    delay = 0.010
    g = ModbusGantry(cfg.gantry, MonotonicClock()).start()

    def estimates(n: int, warm: int = 30) -> np.ndarray:
        """The excess estimated at each of n targets set at 100 Hz after `warm` of them (0.3 s:
        the running median's window turned over)."""
        deadline = time.monotonic() + 10.0      # the first readings, however loaded the machine
        while g.read() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        q0, out = g.read()[1], []
        for i in range(warm + n):
            g.set_target(q0 + np.array([1e-4 * (i + 1), 0.0]))
            time.sleep(0.01)
            if i >= warm:
                out.append(g.link.excess_s())
        return np.array(out)
    try:
        clean = estimates(30)
        launcher.call("faults", spec=f"modbus.delay_ms={1000 * delay:g}")
        late = estimates(30)
        forward = g.link.forward_s()
    finally:
        launcher.call("faults", spec="")
        g.close()
    print(f"gantry link excess: clean p50 {1e3 * np.median(clean):.2f} ms, {1e3 * delay:g} ms link p50 "
          f"{1e3 * np.median(late):.2f} ms (forward {1e3 * forward:.2f} ms)")
    assert np.median(clean) == 0.0, 1e3 * clean
    assert abs(np.median(late) - delay) < 0.003, 1e3 * late
