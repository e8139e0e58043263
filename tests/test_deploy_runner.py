"""The robot runner on fake hardware and fake time: pacing, interpolation, frame stack, logging,
the state machine, and fault injection (no command may ever leave the range or speed limits)."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest

from deploy.robot import (
    FAULTS,
    Contract,
    FrameStack,
    Mode,
    NoBallError,
    Runner,
    RunnerConfig,
    SampleBuffer,
    TransitionError,
    Violations,
    check_goal_region,
    contract_from_dict,
    contract_from_world,
    contract_to_dict,
    count_violations,
    episode_goals,
    goals_from_arg,
    interpolate,
    limits_from_contract,
    load_episode,
    parse_goals,
    safe_target,
)
from deploy.robot.fakes import FakeClock, FakeRobot, FakeTracker, FollowBallPolicy
from ttmjx.world import observation, record
from ttmjx.world.config import World

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CONTRACT = Contract()                      # 20 Hz, k = 8, 1.6 s -> 32 ticks
DT = CONTRACT.dt
NO_VIOLATIONS = Violations(0, 0, 0, 0, 0)
INJECTED = Counter()                       # fault kind -> injected count, over the whole module


# --------------------------------------------------------------------------- bench
class RecordingClock(FakeClock):
    """FakeClock that remembers how late each sleep returned."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.lateness = []

    def sleep_until(self, t):
        before = max(self.t, t)
        super().sleep_until(t)
        self.lateness.append(self.t - before)


def bench(jitter_s=0.0, q0=(0.1, 0.2, 0.3, 0.1, 0.0, 0.0, 0.0, 0.0), policy=None, seed=0,
          contract=CONTRACT, config=RunnerConfig()):
    clock = RecordingClock(start=10.0, jitter_s=jitter_s, seed=seed)
    robot = FakeRobot(clock, contract, q0=q0)
    tracker = FakeTracker(clock)
    policy = policy or FollowBallPolicy(contract)
    return clock, robot, tracker, Runner(robot, tracker, clock, policy, contract, config)


def violations(runner, robot) -> Violations:
    t, q = robot.command_log()
    return count_violations(runner.limits, t, q, start=robot.true_at_send[0] if len(t) else None)


def one_episode(runner, tracker, goal=(0.7, 0.3), delay=0.2):
    assert runner.move_home(), runner.sm.history
    tracker.throw_in(delay)
    return runner.run_episode(goal)


# --------------------------------------------------------------------------- pieces
def test_interpolate_is_linear_between_samples_and_holds_outside():
    t = np.array([0.0, 0.008, 0.016])
    x = np.array([[0.0, 1.0], [0.8, 1.0], [1.6, 3.0]])
    mid = interpolate(t, x, 0.012)
    np.testing.assert_allclose(mid.value, [1.2, 2.0])
    np.testing.assert_allclose(mid.slope, [100.0, 250.0])
    assert (mid.t_lo, mid.t_hi) == (0.008, 0.016)
    after = interpolate(t, x, 0.5)
    np.testing.assert_allclose(after.value, x[-1])
    assert (after.t_lo, after.t_hi) == (0.008, 0.016)
    ahead = interpolate(t, x, 0.020, max_extrapolate_s=0.002)   # 4 ms past, capped at 2 ms
    np.testing.assert_allclose(ahead.value, [1.8, 3.5])
    np.testing.assert_allclose(interpolate(t, x, -1.0).value, x[0])
    np.testing.assert_allclose(interpolate(t, x, 0.008).value, x[1])
    with pytest.raises(ValueError, match="no samples"):
        interpolate(t[:0], x[:0], 0.0)


def test_sample_buffer_keeps_the_newest_capacity_samples():
    buf = SampleBuffer(2, capacity=4)
    for i in range(11):
        buf.add(float(i), np.array([i, -i]))
    assert len(buf) >= 4 and buf.newest_time == 10.0
    np.testing.assert_allclose(buf.times[-4:], [7, 8, 9, 10])
    np.testing.assert_allclose(buf.at(9.5).value, [9.5, -9.5])


def test_frame_stack_matches_the_observation_frame_stack():
    obs = np.random.default_rng(0).normal(size=(1, 11, 13)).astype(np.float32)
    want = observation.frame_stack(obs, 8)[0]             # [T, k, 13]
    stack = FrameStack(8)
    got = np.stack([stack.push(f) for f in obs[0]])
    np.testing.assert_array_equal(got, want)


def test_safe_target_checks_finite_then_range_then_step():
    lim = limits_from_contract(CONTRACT)
    last = np.asarray(CONTRACT.home, np.float64)
    for bad in (np.full(8, np.nan), np.r_[np.zeros(7), np.inf], np.zeros(7)):
        cmd = safe_target(lim, bad, last)
        np.testing.assert_array_equal(cmd.target, last)
        assert cmd.faults == FAULTS["policy_nonfinite"]
    huge = np.full(8, 1e30)
    cmd = safe_target(lim, huge, last)
    np.testing.assert_allclose(cmd.target, np.minimum(last + lim.max_step, lim.upper))
    assert cmd.faults == FAULTS["command_range"] | FAULTS["command_step"]
    near = last + 0.5 * lim.max_step
    cmd = safe_target(lim, near, last)
    np.testing.assert_allclose(cmd.target, near)
    assert cmd.faults == 0
    # Two commands 10 ms apart may move only 10 ms worth; a slow move home a fraction of that.
    np.testing.assert_allclose(safe_target(lim, huge, last, elapsed=0.01).target - last,
                               np.minimum(lim.speed * 0.01, lim.upper - last))
    np.testing.assert_allclose(safe_target(lim, -huge, last, speed_scale=0.3).target - last,
                               -np.minimum(0.3 * lim.max_step, last - lim.lower))


def test_count_violations_finds_each_kind():
    """The checker the fault tests rely on must itself catch every kind of violation."""
    lim = limits_from_contract(CONTRACT)
    q0 = np.asarray(CONTRACT.home)
    t = np.arange(6) * DT
    q = np.tile(q0, (6, 1))
    assert count_violations(lim, t, q, start=q0) == NO_VIOLATIONS
    q_bad = q.copy()
    q_bad[1, 0] = lim.upper[0] + 0.01                     # range (and a step of 0.26 m: step, rate)
    q_bad[3, 2] += 1.01 * lim.max_step[2]                 # step and rate into 3, back out of it
    q_bad[5, 7] = np.nan
    v = count_violations(lim, t, q_bad, start=q0 + 1.0)
    assert v.range == 1 and v.nonfinite == 1 and v.first == 1
    assert v.step >= 4 and v.rate >= 4
    t_fast = t.copy()
    t_fast[2] = t_fast[1] + 0.1 * DT                      # a full step only 5 ms after the last
    q_fast = q.copy()
    q_fast[2:, 2] += 0.9 * lim.max_step[2]
    v = count_violations(lim, t_fast, q_fast)
    assert v.step == 0 and v.rate == 1


def test_contract_validates_and_round_trips():
    c = contract_from_world(World(), control_hz=60)
    assert c.dt == pytest.approx(1 / 60) and c.horizon == 96 and c.frame_stack == 8
    assert contract_from_dict(json.loads(json.dumps(contract_to_dict(c)))) == c
    assert c.home_noise == World().robot.home_noise and c.extrapolate_s == World().timing.extrapolate_s
    assert Contract(obs_size=16).obs_size == 16          # the tracker's velocity added
    with pytest.raises(ValueError, match="obs_size=15"):
        Contract(obs_size=15)
    with pytest.raises(ValueError, match="home_noise"):
        Contract(home_noise=(-0.1,) * 8)
    with pytest.raises(ValueError, match="j2 has lower"):
        Contract(lower=(-1, -1, -1, 2, -1, -1, -1, -1))
    with pytest.raises(ValueError, match="home"):
        Contract(home=(5.0,) * 8)
    with pytest.raises(ValueError, match="unknown keys"):
        contract_from_dict({"control_hz": 20, "bogus": 1})


def test_goals_come_from_a_spec_a_file_or_a_list(tmp_path):
    np.testing.assert_allclose(parse_goals("0.7,0.3; 0.4 -0.5"), [[0.7, 0.3], [0.4, -0.5]])
    np.save(tmp_path / "g.npy", np.array([[0.5, 0.1]]))
    (tmp_path / "g.csv").write_text("name,y,x\nA,0.1,0.5\nB,-0.2,1.0\n")     # the header names the columns
    np.testing.assert_allclose(goals_from_arg(str(tmp_path / "g.npy")), [[0.5, 0.1]])
    np.testing.assert_allclose(goals_from_arg(str(tmp_path / "g.csv")), [[0.5, 0.1], [1.0, -0.2]])
    (tmp_path / "g.json").write_text(json.dumps({"goals": [[0.5, 0.1]]}))
    with pytest.raises(ValueError, match=r"g.json.*expected .csv \(header x,y\) or .npy"):
        goals_from_arg(str(tmp_path / "g.json"))
    np.testing.assert_allclose(episode_goals([[1, 2], [3, 4]], 2), [[1, 2], [1, 2], [3, 4], [3, 4]])
    with pytest.raises(ValueError, match="two numbers"):
        parse_goals("0.7")
    with pytest.raises(ValueError, match="not finite"):
        parse_goals("nan,0.1")
    with pytest.raises(ValueError, match=r"goal 1 = \(-0.5, 0.0\) is off the opponent's half"):
        check_goal_region([[0.5, 0.0], [-0.5, 0.0]])


# --------------------------------------------------------------------------- state machine
def test_state_machine_allows_only_documented_transitions():
    clock, robot, tracker, runner = bench()
    assert runner.mode == Mode.IDLE
    with pytest.raises(TransitionError, match="run_episode.. needs mode armed, but the runner is idle"):
        runner.run_episode((0.7, 0.3))
    with pytest.raises(TransitionError, match="release"):
        runner.release()
    assert runner.move_home() and runner.mode == Mode.ARMED
    with pytest.raises(TransitionError, match="move_home"):
        runner.move_home()
    runner.hold("operator")
    assert runner.mode == Mode.HOLD
    with pytest.raises(TransitionError, match="call release.. or move_home.. first"):
        runner.run_episode((0.7, 0.3))
    runner.release()
    assert runner.mode == Mode.IDLE
    ep = one_episode(runner, tracker)
    assert runner.mode == Mode.IDLE and ep.meta["end"] == "done"
    assert [h[1:3] for h in runner.sm.history][-3:] == [
        ("homing", "armed"), ("armed", "running"), ("running", "idle")]
    assert violations(runner, robot) == NO_VIOLATIONS


def test_fakes_implement_the_hardware_interfaces():
    from deploy.robot import BallTracker, Clock, Robot
    clock, robot, tracker, runner = bench()
    assert isinstance(clock, Clock) and isinstance(robot, Robot) and isinstance(tracker, BallTracker)


def test_command_line_runs_goals_from_a_spec_and_rejects_bad_ones(tmp_path, capsys):
    from deploy.robot.cli import main
    main(["robot", "run", "--station", "fake", "--goals", "0.7,0.3;0.4,-0.5", "--out", str(tmp_path), "--json"])
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["episodes"] == 2
    assert load_episode(str(tmp_path), "episode_0001").meta["goal"] == pytest.approx([0.4, -0.5])
    with pytest.raises(SystemExit) as ex:
        main(["robot", "run", "--station", "fake", "--goals", "3.0,0.0"])
    assert ex.value.code == 2 and "off the opponent's half" in capsys.readouterr().err


# A robot's computer: the simulator's packages cannot be imported at all.
NO_SIMULATOR = """
import importlib.abc, sys
class NoSimulator(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name.split(".")[0] in ("jax", "jaxlib", "mujoco", "flax", "optax", "orbax", "brax", "matplotlib",
                                  "tensorboardX", "tqdm"):
            raise ImportError(f"No module named {name!r} (a robot's computer)", name=name)
sys.meta_path.insert(0, NoSimulator())
sys.argv = ["ttmjx", *sys.argv[1:]]
from ttmjx.entry import main
main()
"""


def ttmjx_without_simulator(*args, tmp_path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", NO_SIMULATOR, *args], capture_output=True, text=True, timeout=120,
                          cwd=tmp_path, env={**os.environ, "PYTHONPATH": ROOT})


def test_the_robot_side_runs_where_jax_and_mujoco_cannot_be_imported(tmp_path):
    """`ttmjx robot run` on the fake station and `ttmjx robot bench` through the console script's
    entry on a machine without the simulator's packages; a command that needs them says so, and
    `ttmjx --help` lists what this install runs and how to get the rest."""
    for argv in (["--help"], ["robot", "-h"]):
        done = ttmjx_without_simulator(*argv, tmp_path=tmp_path)
        assert done.returncode == 0 and "pip install 'ttmjx[sim]'" in done.stdout, (argv, done.stdout, done.stderr)
        assert "robot run" in done.stdout and "robot bench" in done.stdout and "train " not in done.stdout, done.stdout
    out = tmp_path / "logs"
    done = ttmjx_without_simulator("robot", "run", "--station", "fake", "--goals", "five", "--out", str(out), "--json",
                                   tmp_path=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert json.loads(done.stdout.strip().splitlines()[-1])["episodes"] == 5
    done = ttmjx_without_simulator("robot", "bench", "--hidden", "64", "--steps", "50", "--json", tmp_path=tmp_path)
    assert done.returncode == 0 and json.loads(done.stdout.strip().splitlines()[-1])["p50_ms"] > 0, done.stderr[-2000:]
    done = ttmjx_without_simulator("train", "--preset", "tiny", tmp_path=tmp_path)
    assert done.returncode == 2 and "pip install 'ttmjx[sim]'" in done.stderr and done.stderr.count("\n") == 1, done.stderr
    done = ttmjx_without_simulator("robot", "run", "--station", "sim", "--policy", str(tmp_path), "--goals", "five",
                                   tmp_path=tmp_path)
    assert done.returncode == 2 and "ttmjx[sim]" in done.stderr and done.stderr.count("\n") == 1, done.stderr


def test_no_ball_leaves_the_runner_armed():
    clock, robot, tracker, runner = bench(config=RunnerConfig(arm_timeout_s=1.0))
    assert runner.move_home()
    t = clock.now()
    with pytest.raises(NoBallError, match="no ball"):
        runner.run_episode((0.7, 0.3))
    INJECTED["tracker_missing"] += 1
    assert runner.mode == Mode.ARMED and 1.0 <= clock.now() - t <= 1.0 + 2 * DT
    runner.disarm()
    assert runner.mode == Mode.IDLE


# --------------------------------------------------------------------------- timing and data
def test_clean_episode_is_on_the_grid_and_observes_the_interpolated_world():
    clock, robot, tracker, runner = bench()
    ep = one_episode(runner, tracker)
    x, T = ep.extras, CONTRACT.horizon
    # Tick 0 is the first 125 Hz sample of the throw (its launch, as in simulation). Its deadline
    # has passed when the trigger sees the ball coming (a sample later), so it is logged, not
    # executed (as the world's timing model has it); every later tick runs on time.
    assert ep.meta["end"] == "done" and ep.traj.valid.all()
    assert not x["executed"][0] and x["executed"][1:].all()
    t0, t_launch = ep.meta["t0"], tracker.throws[-1][0]
    assert t0 == pytest.approx(np.ceil(t_launch * 125 - 1e-9) / 125)
    np.testing.assert_allclose(x["t_grid"], t0 + np.arange(T) * DT, atol=1e-9)
    np.testing.assert_allclose(x["latency"][1:], 0.0, atol=1e-9)
    # Observed joints: interpolated 250 Hz feedback (2 ms late) vs the true joints at each deadline.
    true_q = np.stack([robot.true_q(t) for t in x["t_grid"]])
    err = np.abs(ep.traj.obs[0, :, :8] - true_q)
    assert np.all(err <= np.asarray(CONTRACT.max_speed) * 0.0061 + 1e-5), err.max(0)
    # Observed ball: interpolated 125 Hz samples vs the true path at each deadline (< 2 cm: across
    # a bounce, following the newest samples, up to 12 ms old, cuts the corner).
    vis, xyz = tracker.positions(x["t_grid"])
    assert vis.all() and np.abs(observation.ball_pos(ep.traj.obs[0]) - xyz).max() < 0.02
    np.testing.assert_allclose(observation.goal(ep.traj.obs[0]), np.tile([0.7, 0.3], (T, 1)), atol=1e-6)
    # The record's actions are exactly what the robot received during the episode.
    sent_t, sent_q = robot.command_log()
    in_ep = (sent_t >= t0) & (sent_t <= x["t_grid"][-1])
    np.testing.assert_allclose(sent_q[in_ep], ep.traj.actions[0, 1:], atol=1e-6)
    np.testing.assert_allclose(ep.traj.actions[0], x["commands"], atol=1e-6)
    assert violations(runner, robot) == NO_VIOLATIONS


def test_jitter_below_a_tick_never_shifts_the_deadlines():
    clock, robot, tracker, runner = bench(jitter_s=0.9 * DT, seed=1)
    eps = [one_episode(runner, tracker) for _ in range(3)]
    INJECTED["clock_jitter"] += sum(l >= DT / 4 for l in clock.lateness)
    for ep in eps:
        x = ep.extras
        np.testing.assert_allclose(x["t_grid"], ep.meta["t0"] + np.arange(CONTRACT.horizon) * DT, atol=1e-9)
        # Ticks whose deadlines passed before the trigger are logged, not executed (the first
        # sleep, to a deadline already passed, may also be late by the jitter: one skip).
        first = int(np.argmax(x["executed"]))
        assert x["executed"][first:].all() and np.all((x["faults"][:first] & ~FAULTS["skipped"]) == 0)
        assert np.all(x["t_wake"][first:] >= x["t_grid"][first:])
        assert np.all(x["latency"][first:] < DT) and ep.meta["end"] == "done"
    assert runner.skipped <= len(eps) and runner.overruns == 0
    assert violations(runner, robot) == NO_VIOLATIONS


class SlowPolicy(FollowBallPolicy):
    """Takes `slow_s` of (fake) time on every `every`-th step; counts its steps in the state."""

    def __init__(self, contract, clock, slow_s, every):
        super().__init__(contract)
        self.clock, self.slow_s, self.every = clock, slow_s, every

    def reset(self):
        return 0

    def step(self, state, frame, frames):
        if state % self.every == self.every - 1:
            self.clock.advance(self.slow_s)
            INJECTED["policy_slow"] += 1
        return state + 1, super().step(None, frame, frames)[1]


@pytest.mark.parametrize("slow_s", [1.3 * DT, 2.6 * DT])
def test_overruns_are_counted_and_skipped_not_accumulated(slow_s):
    clock = RecordingClock(start=10.0)
    policy = SlowPolicy(CONTRACT, clock, slow_s, every=4)
    robot, tracker = FakeRobot(clock, CONTRACT), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, policy, CONTRACT)
    ep = one_episode(runner, tracker)
    x, T = ep.extras, CONTRACT.horizon
    assert ep.meta["end"] == "done" and ep.traj.valid.all()
    np.testing.assert_allclose(x["t_grid"], ep.meta["t0"] + np.arange(T) * DT, atol=1e-9)
    # Tick 0's deadline passed before the episode began: logged, not executed, not a skip.
    assert not x["executed"][0] and not x["faults"][0] & FAULTS["skipped"]
    skipped = ~x["executed"]
    skipped[0] = False
    # 1.3 ticks late: the next tick runs late; 2.6 ticks late: the next deadline is skipped.
    assert runner.overruns > 0 and skipped.sum() == runner.skipped
    assert (runner.skipped > 0) == (slow_s > 2 * DT)
    assert np.all(x["latency"][x["executed"]] < DT + slow_s)
    assert np.all((x["faults"][skipped] & FAULTS["skipped"]) != 0)
    assert np.all(np.isnan(x["raw_actions"][skipped])) and np.all(np.isnan(x["t_wake"][skipped]))
    # The episode ends on the grid: lateness was not carried forward.
    assert clock.now() - ep.meta["t0"] < T * DT + slow_s
    # Every row of a skipped tick holds the previous command.
    for n in np.flatnonzero(skipped):
        np.testing.assert_array_equal(x["commands"][n], x["commands"][n - 1])
    assert violations(runner, robot) == NO_VIOLATIONS


def test_recurrent_state_is_threaded_and_reset_per_episode():
    class Counting(FollowBallPolicy):
        def reset(self):
            return {"steps": 0}

        def step(self, state, frame, frames):
            assert frames.shape == (8, 13)
            np.testing.assert_array_equal(frames[-1], frame)
            return {"steps": state["steps"] + 1}, np.full(8, float(state["steps"]))

    clock, robot, tracker, runner = bench(policy=Counting(CONTRACT))
    for _ in range(2):
        ep = one_episode(runner, tracker)
        # Tick 0 is logged before the episode began (no policy call); the state starts fresh at tick 1.
        assert np.isnan(ep.extras["raw_actions"][0]).all()
        np.testing.assert_array_equal(ep.extras["raw_actions"][1:, 0], np.arange(CONTRACT.horizon - 1))


def test_the_garbage_collector_is_off_while_episodes_run_and_back_after():
    """A full collection stops every thread (the drivers' too) for longer than the stale bound in
    a process that has loaded JAX; the runner keeps it off during episodes (deploy/robot/runner.py)."""
    import gc

    class Watching(FollowBallPolicy):
        seen: list = []

        def step(self, state, frame, frames):
            self.seen.append(gc.isenabled())
            return super().step(state, frame, frames)

    policy = Watching(CONTRACT)
    clock, robot, tracker, runner = bench(policy=policy)
    assert gc.isenabled()
    frozen = gc.get_freeze_count()      # an earlier test in this worker may have frozen objects
    eps = runner.run_episodes([[0.7, 0.3], [0.4, -0.5]], on_armed=lambda i: tracker.throw_in(0.2))
    assert len(eps) == 2 and policy.seen and not any(policy.seen)
    assert gc.isenabled() and gc.get_freeze_count() == frozen       # as it found it
    one_episode(runner, tracker)                       # run_episode alone pauses it too
    assert len(policy.seen) > 2 * (CONTRACT.horizon - 2) and not any(policy.seen) and gc.isenabled()


def test_episodes_are_saved_as_trajectory_records(tmp_path):
    clock, robot, tracker, runner = bench()
    runner.policy_hash = "sha256:abc123"
    eps = runner.run_episodes([[0.7, 0.3], [0.4, -0.5]], out_dir=str(tmp_path),
                              on_armed=lambda i: tracker.throw_in(0.2))
    assert len(eps) == 2 and runner.mode == Mode.IDLE
    for i, ep in enumerate(eps):
        back = load_episode(str(tmp_path), f"episode_{i:04d}")
        record.validate(back.traj)
        assert back.traj.obs.shape == (1, CONTRACT.horizon, 13)
        np.testing.assert_array_equal(back.traj.actions, ep.traj.actions)
        np.testing.assert_allclose(back.traj.goal[0], [[0.7, 0.3], [0.4, -0.5]][i], atol=1e-6)
        assert back.meta["policy_hash"] == "sha256:abc123" and back.meta["episode"] == i
        assert back.meta["contract"]["control_hz"] == CONTRACT.control_hz
        x = back.extras
        for key, shape in {"t_grid": (32,), "latency": (32,), "raw_actions": (32, 8),
                           "commands": (32, 8), "ball_used_xyz": (32, 2, 3),
                           "joint_used_q": (32, 2, 8), "faults": (32,)}.items():
            assert x[key].shape == shape, key
        assert x["ball_xyz"].shape[1] == 3 and x["ball_ok"].all() and len(x["ball_t"]) > 100
        # (one new joint sample a tick; the late tick 0 rereads the trigger's last one)
        assert x["joint_q"].shape[1] == 8 and len(x["joint_t"]) >= CONTRACT.horizon - 2
        # The observation is reproducible from the two logged samples it came from.
        (lo, hi), (t_lo, t_hi) = x["ball_used_xyz"].transpose(1, 0, 2), x["ball_used_t"].T
        ext = CONTRACT.extrapolate_s   # RunnerConfig.max_extrapolate_s None: the contract's
        s = (np.clip(x["t_grid"], t_lo, t_hi + ext) - t_lo) / (t_hi - t_lo)
        np.testing.assert_allclose(observation.ball_pos(back.traj.obs[0]), lo + s[:, None] * (hi - lo), atol=1e-5)
    with pytest.raises(FileExistsError):
        from deploy.robot import save_episode
        save_episode(str(tmp_path), "episode_0000", eps[0])


# --------------------------------------------------------------------------- fault injection
class FaultyPolicy:
    """Wraps a policy; each step, with probability p, returns a corrupted action."""
    KINDS = ("nan", "inf", "huge", "beyond", "flip", "shape", "raise")

    def __init__(self, base, clock, rng, p=0.0, kinds=KINDS):
        self.base, self.clock, self.rng, self.p, self.kinds = base, clock, rng, p, kinds
        self.lower, self.upper = np.asarray(CONTRACT.lower), np.asarray(CONTRACT.upper)

    def reset(self):
        return self.base.reset()

    def step(self, state, frame, frames):
        state, a = self.base.step(state, frame, frames)
        if self.rng.random() >= self.p:
            return state, a
        kind = self.kinds[self.rng.integers(len(self.kinds))]
        INJECTED["policy_" + kind] += 1
        a = np.array(a, np.float64)
        j = self.rng.integers(8)
        if kind == "nan":
            a[j] = np.nan
        elif kind == "inf":
            a[j] = self.rng.choice([np.inf, -np.inf])
        elif kind == "huge":
            a = self.rng.choice([-1.0, 1.0], 8) * 10.0 ** self.rng.uniform(3, 30, 8)
        elif kind == "beyond":
            a[j] = self.upper[j] + 1.0 if self.rng.random() < 0.5 else self.lower[j] - 1.0
        elif kind == "flip":
            a = np.where(self.rng.random(8) < 0.5, self.lower, self.upper)
        elif kind == "shape":
            a = a[:7]
        elif kind == "raise":
            raise FloatingPointError("injected policy failure")
        return state, a


class FaultyRobot:
    """Wraps a FakeRobot; each read, with probability p, returns corrupted feedback."""
    KINDS = ("jump", "nan", "future", "backwards", "out_of_range", "freeze")

    def __init__(self, base, rng, p=0.0, kinds=KINDS):
        self.base, self.rng, self.p, self.kinds = base, rng, p, kinds
        self._frozen_until, self._frozen = -np.inf, None

    def send(self, q):
        self.base.send(q)

    def read(self):
        t, q = self.base.read()
        if t < self._frozen_until:
            return self._frozen
        if self.rng.random() >= self.p:
            return t, q
        kind = self.kinds[self.rng.integers(len(self.kinds))]
        INJECTED["joint_" + kind] += 1
        q = q.copy()
        j = self.rng.integers(8)
        if kind == "jump":
            q[j] += self.rng.choice([-1.0, 1.0]) * self.rng.uniform(0.3, 2.0)
        elif kind == "nan":
            q[j] = np.nan
        elif kind == "future":
            t += 0.5
        elif kind == "backwards":
            t -= 0.1
        elif kind == "out_of_range":
            q[j] = CONTRACT.upper[j] + 0.5
        elif kind == "freeze":                    # the feedback stops updating for 0.3 s
            self._frozen_until, self._frozen = t + 0.3, (t, q)
        return t, q


class FaultyTracker:
    """Wraps a FakeTracker; corrupts single samples with probability p and can black out."""
    KINDS = ("nan", "future", "outlier", "backwards", "floor")

    def __init__(self, base, rng, p=0.0, kinds=KINDS):
        self.base, self.rng, self.p, self.kinds = base, rng, p, kinds
        self.blackout = (np.inf, np.inf)          # [start, end) of times with no samples at all

    def throw_in(self, delay, **kw):
        self.base.throw_in(delay, **kw)

    def read(self):
        t, xyz = self.base.read()
        t, xyz = t.copy(), xyz.copy()
        keep = ~((t >= self.blackout[0]) & (t < self.blackout[1]))
        INJECTED["ball_blackout"] += int(np.sum(~keep))
        t, xyz = t[keep], xyz[keep]
        for i in np.flatnonzero(self.rng.random(len(t)) < self.p):
            kind = self.kinds[self.rng.integers(len(self.kinds))]
            INJECTED["ball_" + kind] += 1
            if kind == "nan":
                xyz[i, self.rng.integers(3)] = np.nan
            elif kind == "future":
                t[i] += 1.0
            elif kind == "outlier":
                xyz[i, 1] += self.rng.choice([-1.0, 1.0]) * 3.0
            elif kind == "backwards":
                t[i] -= 0.2
            elif kind == "floor":
                xyz[i, 2] = -0.5
        return t, xyz


def faulty_bench(seed=0, jitter_s=0.0, **kw):
    rng = np.random.default_rng(seed)
    clock = RecordingClock(start=10.0, jitter_s=jitter_s, seed=seed)
    robot, tracker = FakeRobot(clock, CONTRACT), FakeTracker(clock)
    frobot, ftracker = FaultyRobot(robot, rng), FaultyTracker(tracker, rng)
    fpolicy = FaultyPolicy(FollowBallPolicy(CONTRACT), clock, rng)
    runner = Runner(frobot, ftracker, clock, fpolicy, CONTRACT, RunnerConfig(**kw))
    return clock, robot, runner, frobot, ftracker, fpolicy


@pytest.mark.parametrize("kind,fault", [("nan", "policy_nonfinite"), ("inf", "policy_nonfinite"),
                                        ("shape", "policy_error"), ("raise", "policy_error")])
def test_a_broken_policy_output_holds_the_last_target(kind, fault):
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench()
    assert runner.move_home()
    fpolicy.p, fpolicy.kinds = 0.2, (kind,)
    ftracker.throw_in(0.2)
    ep = runner.run_episode((0.7, 0.3))
    assert runner.mode == Mode.HOLD and ep.meta["end"] == f"hold: {fault}"
    n = ep.meta["ticks"] - 1
    x = ep.extras
    np.testing.assert_array_equal(x["commands"][n], x["commands"][n - 1] if n else CONTRACT.home)
    assert not ep.traj.valid[0, n + 1:].any()
    assert violations(runner, robot) == NO_VIOLATIONS
    # Only an explicit command leaves HOLD; then the runner works again.
    fpolicy.p = 0.0
    assert runner.move_home()
    ftracker.throw_in(0.2)
    assert runner.run_episode((0.7, 0.3)).meta["end"] == "done"
    assert violations(runner, robot) == NO_VIOLATIONS


def test_huge_and_out_of_range_targets_are_clamped_every_tick():
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench(seed=3)
    fpolicy.p, fpolicy.kinds = 1.0, ("huge", "beyond", "flip")
    for _ in range(3):
        assert runner.move_home()
        ftracker.throw_in(0.2)
        ep = runner.run_episode((0.7, 0.3))
        assert ep.meta["end"] == "done"
        assert ep.meta["faults"]["command_range"] + ep.meta["faults"]["command_step"] >= CONTRACT.horizon
    assert violations(runner, robot) == NO_VIOLATIONS


def test_a_tracker_blackout_holds_within_the_staleness_bound():
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench()
    assert runner.move_home()
    ftracker.throw_in(0.2)
    t_out = clock.now() + 0.8
    ftracker.blackout = (t_out, np.inf)
    ep = runner.run_episode((0.7, 0.3))
    assert runner.mode == Mode.HOLD and ep.meta["end"] == "hold: ball_stale"
    t_hold = runner.sm.history[-1][0]
    t_last = ep.extras["ball_t"][ep.extras["ball_ok"]].max()
    assert t_out - 0.008 <= t_last < t_out
    assert t_last + 0.1 < t_hold <= t_last + 0.1 + DT     # the first tick after the bound
    assert violations(runner, robot) == NO_VIOLATIONS


def test_a_device_fault_the_robot_names_holds_with_good_joints():
    """Robot.fault() (hardware.Robot's optional method: a driver's latched motors-off or drive
    fault) holds the runner on robot_fault although the joints still read finite and in range;
    no command leaves after it."""
    class Faulting(FakeRobot):
        t_fault = np.inf

        def fault(self):
            return "drive_fault" if self.clock.now() >= self.t_fault else None

    clock = RecordingClock(start=10.0)
    robot, tracker = Faulting(clock, CONTRACT), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, FollowBallPolicy(CONTRACT), CONTRACT)
    assert runner.move_home()
    tracker.throw_in(0.2)
    robot.t_fault = clock.now() + 0.5
    ep = runner.run_episode((0.7, 0.3))
    assert runner.mode == Mode.HOLD and ep.meta["end"] == "hold: robot_fault", ep.meta["end"]
    assert runner.fault_counts["robot_fault:drive_fault"] >= 1
    assert np.all(np.isfinite(ep.extras["joint_q"][ep.extras["joint_ok"].astype(bool)]))
    sent = ep.extras["t_sent"][np.isfinite(ep.extras["t_sent"])]
    assert len(sent) and sent.max() < robot.t_fault
    assert violations(runner, robot) == NO_VIOLATIONS


@pytest.mark.parametrize("kind,faults", [
    ("jump", ("joint_jump", "joint_out_of_range")),   # a big jump may also leave the range
    ("nan", ("joint_nonfinite",)), ("future", ("joint_time",)), ("backwards", ("joint_time",)),
    ("out_of_range", ("joint_out_of_range",)), ("freeze", ("joint_stale",))])
def test_bad_joint_feedback_holds(kind, faults):
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench()
    assert runner.move_home()
    ftracker.throw_in(0.2)
    frobot.p, frobot.kinds = 0.1, (kind,)
    ep = runner.run_episode((0.7, 0.3))
    reason = runner.sm.history[-1][3]                # "armed: ..." or "hold: ..."
    assert runner.mode == Mode.HOLD and reason.split(": ")[1] in faults, reason
    assert ep is None or ep.meta["end"] == reason    # None: the fault came while armed
    assert violations(runner, robot) == NO_VIOLATIONS


def test_a_driver_exception_leaves_the_robot_in_hold():
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench()
    assert runner.move_home()
    ftracker.throw_in(0.2)

    def broken_read():
        raise ConnectionError("EGM socket closed")
    runner.robot = type("Broken", (), {"read": staticmethod(broken_read), "send": robot.send})()
    with pytest.raises(ConnectionError):
        runner.run_episode((0.7, 0.3))
    INJECTED["driver_exception"] += 1
    assert runner.mode == Mode.HOLD and "ConnectionError" in runner.sm.history[-1][3]
    assert violations(runner, robot) == NO_VIOLATIONS


def test_fault_campaign_never_sends_a_command_outside_the_limits():
    """>= 1,000 injected faults of every kind, mixed at random over ~100 episodes, with clock
    jitter up to 2.5 ticks: zero range or speed violations in every command sent."""
    clock, robot, runner, frobot, ftracker, fpolicy = faulty_bench(seed=7)
    rng = np.random.default_rng(11)
    start = sum(INJECTED.values())
    before = Counter(INJECTED)
    ends = Counter()
    for ep_i in range(100):
        clock.jitter_s = float(rng.choice([0.0, 0.02, 0.08, 0.125]))
        fpolicy.p = float(rng.choice([0.0, 0.05, 0.5]))
        fpolicy.kinds = FaultyPolicy.KINDS if rng.random() < 0.3 else ("huge", "beyond", "flip")
        frobot.p = float(rng.choice([0.0, 0.0, 0.02]))
        ftracker.p = float(rng.choice([0.0, 0.1, 0.3]))
        if runner.mode == Mode.HOLD:                          # an operator looks, then clears it
            clock.advance(rng.uniform(0.5, 2.0))
            if rng.random() < 0.5:
                runner.release()
        if not runner.move_home():
            ends["homing_hold"] += 1
            continue
        no_throw = rng.random() < 0.05                       # the thrower never throws
        runner.config = dataclasses.replace(runner.config, arm_timeout_s=0.5 if no_throw else 10.0)
        if not no_throw:
            ftracker.throw_in(0.2)
        if rng.random() < 0.1:
            ftracker.blackout = (clock.now() + rng.uniform(0.2, 1.5), clock.now() + 3.0)
        goal = (rng.uniform(0.2, 1.2), rng.uniform(-0.6, 0.6))
        try:      # (with no throw, a ball still in flight from a cut-short episode may start one)
            ep = runner.run_episode(goal)
        except NoBallError:
            INJECTED["tracker_missing"] += 1
            ends["no_ball"] += 1
            runner.disarm()
            continue
        finally:
            ftracker.blackout = (np.inf, np.inf)
        ends[ep.meta["end"] if ep else "armed_hold"] += 1
        assert ep is None or ep.traj.valid[0, 0]
    INJECTED["clock_jitter"] += sum(l >= DT / 4 for l in clock.lateness)
    injected = sum(INJECTED.values()) - start
    v = violations(runner, robot)
    print(f"\ncampaign: {injected} injected faults "
          f"{dict(INJECTED - before)}, {len(robot.sent_t)} commands, ends {dict(ends)}, {v}")
    assert injected >= 1000 and injected - (INJECTED - before)["clock_jitter"] >= 1000
    assert v == NO_VIOLATIONS
    assert ends["done"] >= 10 and sum(n for k, n in ends.items() if k.startswith("hold")) >= 10


class _DelayedRobot(FakeRobot):
    """A FakeRobot whose commands start acting delay_s after they are sent (a cell's command delay)."""
    delay_s = 0.05

    def send(self, q) -> None:
        q = np.asarray(q, np.float64)
        now = self.clock.now()
        start = now + self.delay_s
        here = self.true_q(start)
        self._t.append(start)
        self._q.append(here)
        self._target.append(q.copy())
        if len(self._t) > self.keep:
            del self._t[0], self._q[0], self._target[0]
        self.sent_t.append(now)
        self.sent_q.append(q.copy())
        self.true_at_send.append(self.true_q(now))


class _LastTicksAway:
    """Holds home, then in the episode's last executed ticks steps joint j1 away (as a policy may)."""
    policy_hash = "test:last-ticks-away"

    def __init__(self, contract):
        self.home, self.horizon = np.asarray(contract.home, np.float64), contract.horizon

    def reset(self):
        return 0

    def step(self, state, frame, frames):
        q = self.home.copy()
        if state >= self.horizon - 5:
            q[2] += 0.3
        return state + 1, q


@pytest.mark.parametrize("settle_s, held", [(0.0, True), (RunnerConfig().command_settle_s, False)])
def test_homing_after_an_episode_waits_for_the_delayed_last_commands(settle_s, held):
    """With a command delay the robot is still where it was when the episode's last commands
    leave; homing took it as settled far from the last command (a false joint_mismatch, HOLD,
    seen in a timing sweep); it now reads the joints command_settle_s after the last command."""
    contract = dataclasses.replace(CONTRACT, control_hz=100.0)
    clock = FakeClock(start=10.0)
    robot, tracker = _DelayedRobot(clock, contract), FakeTracker(clock)
    runner = Runner(robot, tracker, clock, _LastTicksAway(contract), contract,
                    RunnerConfig(command_settle_s=settle_s))
    eps = runner.run_episodes([[0.7, 0.3], [0.4, -0.5]], on_armed=lambda i: tracker.throw_in(0.2))
    assert (runner.fault_counts.get("joint_mismatch", 0) > 0) == held, dict(runner.fault_counts)
    assert len(eps) == (1 if held else 2)
