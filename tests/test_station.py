"""The simulated station (MuJoCo C physics behind the runner's hardware interfaces): sampling and
timestamps, whole episodes of an exported policy through the runner, and logs that load as
Trajectories and relabel. Its events (the world's rules): tests/test_event_rules.py."""
from __future__ import annotations

import dataclasses
import json
import os

import jax
import numpy as np
import pytest

from deploy.robot import (
    BallTracker,
    Clock,
    Contract,
    Mode,
    Robot,
    Runner,
    RunnerConfig,
    Violations,
    count_violations,
    load_episode,
    load_export,
)
from deploy.sim.export import export
from documented import check_episode_meta, check_sim_session, check_sweep
from deploy.sim.station import SimClock, SimStation, complete_episode, play, run_sim
from models import PolicyConfig, identity_normalizer, init_params
from training.data import relabel
from ttmjx.world import observation, record
from ttmjx.world.config import CELL_TRAINING, Timing, World

CFG = World()
HOME = np.asarray(CFG.robot.home)
NO_VIOLATIONS = Violations(0, 0, 0, 0, 0)
# A ball thrown at the paddle of the robot held at home: hit, then it flies off behind the robot.
AT_PADDLE = ((-0.6, 0.0, 1.38), (-4.0, 0.0, 0.0), (0.0, 0.0, 0.0), (-1.2, 0.0))


class HoldHome:
    """A numpy policy that keeps the robot at home."""
    policy_hash = "test:hold-home"

    def reset(self):
        return None

    def step(self, state, frame, frames):
        return state, HOME.copy()


# Fixed sensor timing without jitter, so the sample times below are exact.
LAB = Timing(tracker_hz=125.0, tracker_latency_s=0.004, joint_hz=250.0, joint_latency_s=0.002)


def test_station_implements_the_hardware_interfaces_with_timestamps():
    clock = SimClock(start=5.0)
    st = SimStation(CFG, Contract(), clock=clock, q0=HOME, timing=LAB)
    assert isinstance(st.robot, Robot) and isinstance(st.tracker, BallTracker) and isinstance(clock, Clock)
    clock.sleep_until(5.1)
    t, q = st.robot.read()
    assert st.time == pytest.approx(5.1) and t == pytest.approx(5.096)    # 250 Hz, 2 ms late
    np.testing.assert_allclose(q, HOME, atol=1e-3)
    ts, xs = st.tracker.read()
    assert ts.shape == (0,) and xs.shape == (0, 3)                         # no ball yet
    st.throw_in(0.0, ((1.75, 0.35, 0.95), (-7.0, -0.3, 1.5), (0.0, 0.0, 0.0), (-0.8, -0.3)))
    clock.sleep_until(5.3)
    ts, xs = st.tracker.read()
    assert len(ts) == 25 and ts[-1] <= 5.3 - 0.004 + 1e-9                  # 125 Hz, 4 ms late
    np.testing.assert_allclose(np.diff(ts), 0.008, atol=1e-9)
    assert np.all(np.diff(xs[:, 0]) < 0) and xs[0, 0] < 1.75               # coming at the robot
    ts2, _ = st.tracker.read()
    assert len(ts2) == 0                                                   # each sample once
    # Commands ramp the servo targets in; the robot moves toward them.
    target = HOME + np.r_[0.1, -0.1, 0.2, 0, 0, 0, 0, 0]
    st.robot.send(target)
    clock.sleep_until(5.8)
    _, q = st.robot.read()
    np.testing.assert_allclose(q, target, atol=5e-3)
    t_log, q_log = st.robot.command_log()
    assert t_log.tolist() == [pytest.approx(5.3)] and np.array_equal(q_log[0], target)


def test_station_episode_of_a_held_robot_is_logged_with_its_hit_and_landing(tmp_path):
    clock = SimClock()
    contract = Contract()
    st = SimStation(CFG, contract, clock=clock, q0=HOME)
    runner = Runner(st.robot, st.tracker, clock, HoldHome(), contract)
    assert runner.move_home()
    st.throw_in(0.05, AT_PADDLE)
    ep = runner.run_episode((0.7, 0.3))
    ev = st.finish_throw()
    ep = complete_episode(ep, ev, contract)
    assert ep.meta["end"] == "done" and runner.mode == Mode.IDLE
    tr = ep.traj
    assert tr.hit[0] and 0 <= tr.hit_step[0] < 5
    assert tr.hit_step[0] == int((ev.t_hit - ep.meta["t0"]) / contract.dt)
    np.testing.assert_allclose(tr.landing[0], ev.landing, atol=1e-6)
    np.testing.assert_allclose(tr.launch_pos[0], AT_PADDLE[0], atol=1e-6)
    record.validate(tr)
    rel = relabel(tr)
    np.testing.assert_allclose(rel.goal[0], ev.landing, atol=1e-6)
    np.testing.assert_allclose(observation.goal(rel.obs[0]), np.broadcast_to(ev.landing, (contract.horizon, 2)), atol=1e-6)


@pytest.fixture(scope="module")
def tiny_export(tmp_path_factory):
    """A tiny random-init LSTM exported at the robot's 20 Hz."""
    pcfg = PolicyConfig(hidden=8, layers=1)
    params = init_params(jax.random.key(0), pcfg, identity_normalizer(13))
    out = str(tmp_path_factory.mktemp("station") / "policy")
    # trained (so its contract says) under the presets' cell timing: the station plays nominal
    return export(params, pcfg, dataclasses.replace(CFG, timing=CELL_TRAINING), out, control_hz=20,
                  source="random-init")


def test_robot_run_on_the_sim_station_end_to_end(tiny_export, tmp_path):
    """Sampled throws, a random-init exported policy, whole episodes through the runner, zero
    safety violations, logs that load as Trajectories with the station's events."""
    logs = str(tmp_path / "logs")
    goals = [[0.7, 0.3], [0.4, -0.5]]
    out = run_sim(tiny_export, goals, logs, seed=1, charge_compute=False)
    assert out["episodes"] == 2 and out["ends"] == ["done", "done"] and out["mode"] == "idle"
    assert out["violations"] == NO_VIOLATIONS._asdict() and out["commands"] > 2 * 32
    assert out["self_test_error"] <= 1e-5 and out["policy_hash"].startswith("sha256:")
    assert set(out["metrics"]) >= {"within_30cm", "within_20cm", "mean_dist", "hit_rate"}
    latching = {"policy_nonfinite", "policy_error", "joint_stale", "joint_jump", "ball_stale",
                "joint_out_of_range", "joint_time", "joint_nonfinite", "joint_mismatch", "robot_fault"}
    assert not latching & set(out["faults"])
    assert json.load(open(os.path.join(logs, "session.json")))["episodes"] == 2
    check_sim_session(logs, out, tiny_export, goals, 1)        # every field as docs/DATA.md says
    contract = load_export(tiny_export)[1]
    for i in range(2):                                          # each episode's metadata, key by key
        check_episode_meta(logs, i, out, goals, contract, RunnerConfig())
    trajs = []
    for i in range(2):
        traj, meta = record.load(logs, f"episode_{i:04d}")        # the one data format
        ep = load_episode(logs, f"episode_{i:04d}")
        assert traj.obs.shape == (1, contract.horizon, 13) and traj.valid.all()
        assert meta["events_detected"] and meta["station"] == "sim" and meta["events"]["done"]
        np.testing.assert_allclose(traj.goal[0], goals[i])
        np.testing.assert_allclose(traj.launch_pos[0], meta["events"]["launch_pos"], atol=1e-6)
        assert bool(traj.hit[0]) == meta["events"]["hit"]
        assert np.all(np.isfinite(traj.landing[0])) == (meta["events"]["hit"] and meta["events"]["landed"])
        np.testing.assert_allclose(ep.extras["commands"], traj.actions[0], rtol=0, atol=1e-6)
        trajs.append(traj)
    rel = relabel(record.concat(trajs))                             # as `ttmjx train --data` will
    assert rel.obs.shape == (2, contract.horizon, 13)


def test_play_stops_in_hold_and_never_sends_an_unsafe_command(tiny_export):
    """A policy that fails mid-episode puts the runner in HOLD; play stops; every command sent
    stayed within the limits."""
    policy, contract = load_export(tiny_export)

    class Failing:
        policy_hash = "test:fails"

        def __init__(self):
            self.n = 0

        def reset(self):
            return policy.reset()

        def step(self, state, frame, frames):
            self.n += 1
            if self.n == 5:
                return state, np.full(8, np.nan)
            return policy.step(state, frame, frames)

    clock = SimClock()
    st = SimStation(CFG, contract, clock=clock, seed=2)
    runner = Runner(st.robot, st.tracker, clock, Failing(), contract)
    episodes = play(runner, st, [[0.7, 0.3], [0.5, 0.0]])
    assert len(episodes) == 1 and runner.mode == Mode.HOLD
    assert episodes[0].meta["end"].startswith("hold: policy_nonfinite")
    t, q = st.robot.command_log()
    assert count_violations(runner.limits, t, q, start=st.robot.true_at_send[0]) == NO_VIOLATIONS


def test_ttmjx_robot_run_cli(tiny_export, tmp_path, capsys):
    from ttmjx.cli import main
    main(["robot", "run", "--policy", tiny_export, "--station", "sim", "--goals", "0.7,0.3",
          "--n", "2", "--out", str(tmp_path / "logs"), "--seed", "3", "--json"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    # Against the robot's true limits nothing may be exceeded (compute time is not charged by
    # default, so the run is reproducible by seed).
    assert out["episodes"] == 2 and out["violations_true_limits"] == NO_VIOLATIONS._asdict()
    assert 0 < out["max_speed_fraction"] <= 1.0
    assert {"within_30cm", "within_20cm", "mean_dist", "hit_rate"} <= set(out["metrics"])
    assert out["latency_ms"]["p99"] < 1000 / 20
    assert sorted(os.listdir(tmp_path / "logs"))[0] == "episode_0000.deploy.npz"
    with pytest.raises(SystemExit):
        main(["robot", "run", "--policy", str(tmp_path), "--station", "sim", "--goals", "0.7,0.3"])
    assert "not a policy export" in capsys.readouterr().err


def test_robot_sweep_plays_every_point_and_its_zero_point_is_the_plain_run(tiny_export, tmp_path):
    """`ttmjx robot sweep`: every series (ball, action, jitter, all) at every point on the same
    goals and throws, the export verified and built once, the +0 point played once; saved as
    JSON and PNG; +0 ms is exactly the robot run at the trained timing (same seed); points
    beyond the trained range are marked."""
    import deploy.sim.station as station
    from deploy.sim.sweep import latency_sweep, sweep_table
    goals = np.array([[0.7, 0.3], [0.4, -0.5]])
    loads = []
    real = station.load_for_station
    station_load = lambda *a, **k: loads.append(a) or real(*a, **k)  # noqa: E731
    import deploy.sim.sweep as sweep
    sweep.load_for_station, saved_fn = station_load, sweep.load_for_station
    try:
        out = latency_sweep(tiny_export, goals, str(tmp_path / "sweep"), [0, 50], seed=1, jitter_ms=[0, 2])
    finally:
        sweep.load_for_station = saved_fn
    assert len(loads) == 1 and out["sessions_played"] == 5
    assert [(p["series"], p["added_ms"]) for p in out["points"]] == [
        ("ball", 0.0), ("ball", 50.0), ("action", 0.0), ("action", 50.0), ("jitter", 0.0), ("jitter", 2.0),
        ("all", 0.0), ("all", 50.0)]
    assert all(p["episodes"] == len(goals) for p in out["points"])
    assert [p["within_trained"] for p in out["points"]] == [True, False] * 4
    saved = json.load(open(tmp_path / "sweep" / "sweep.json"))
    assert [p["added_ms"] for p in saved["points"]] == [0.0, 50.0, 0.0, 50.0, 0.0, 2.0, 0.0, 50.0]
    assert open(tmp_path / "sweep" / "sweep.png", "rb").read(8) == b"\x89PNG\r\n\x1a\n"
    assert sweep_table(out).count("\n") == 1 + len(out["points"])
    plain = run_sim(tiny_export, goals, None, seed=1, charge_compute=False)
    for k in ("within_30cm", "within_20cm", "hit_rate"):
        assert out["points"][0][k] == out["points"][2][k] == plain["metrics"][k], k
    # every field as docs/DATA.md ("Timing sweeps") describes it
    saved = check_sweep(str(tmp_path / "sweep"), out, tiny_export, goals, 1, [0.0, 50.0], [0.0, 2.0])
    # a point off zero is the session at the base timing with its ms added (ball: tracker latency)
    from deploy.robot.runner import RunnerConfig
    from ttmjx.world.config import from_dict
    base = from_dict(Timing, saved["base_timing"])
    late = dataclasses.replace(base, ideal_timing=False, tracker_latency_s=base.tracker_latency_s + 0.05)
    again = run_sim(tiny_export, goals, None, seed=1, charge_compute=False, timing=late, allow_untrained=True,
                    config=RunnerConfig(stale_s=0.1 + 0.05))
    assert again["episodes"] == saved["points"][1]["episodes"] and again["faults"] == saved["points"][1]["faults"]
    for k in ("within_30cm", "within_20cm", "hit_rate"):
        assert saved["points"][1][k] == pytest.approx(again["metrics"][k] * again["episodes"] / len(goals)), k
