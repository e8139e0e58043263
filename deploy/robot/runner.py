"""The physical-robot runner: a deadline-paced control loop around a numpy policy.

Timing. Tick n of an episode has the deadline t0 + n * dt (dt = 1 / contract.control_hz): the
schedule never drifts. Observations are interpolated to the deadline, not to the (jittery) wake
time, so the policy sees frames exactly dt apart as in simulation. A tick that wakes after the
NEXT deadline has passed is skipped (its row is logged from the buffered samples, its frame
still enters the frame stack, the robot holds its target, the policy is not called); lateness is
counted, never accumulated into the schedule. A command that leaves after the next deadline
counts as an overrun.

Start. t0 is the launch, where the simulation's episodes start (frame n shows the ball n * dt
after the launch; the first frame fills the stack): the thrower's announced launch time
(run_episode's t_start), or else the first sample of the incoming ball's track, found when the
trigger fires. Ticks whose deadlines passed before the episode began are logged (frames from
the buffered samples, into the stack) but not executed, and are not counted as skipped.

Inputs. Joint feedback (Robot.read) and ball samples (BallTracker.read) are validated one by
one (deploy.robot.safety.FAULTS), buffered, and linearly interpolated to each deadline.

Collector. Python's cyclic garbage collector stops every thread while it runs, and a full
collection over a large heap (a process that has loaded JAX and compiled functions) can take
longer than the stale bound (measured: docs/RESULTS.md, "Garbage-collector pauses"): the
drivers' threads would stop answering and the runner would see its own joints go stale. So the collector is off while
episodes run (_collector_paused): objects older than the session are frozen out of it, and it
runs between episodes, when nothing is timed.

Safety. See deploy/robot/safety.py for the command filter and deploy/robot/modes.py for the state machine.
"""
from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
from collections import Counter
from typing import Any, Callable, Protocol

import numpy as np

from deploy.robot.contract import REAL_OBS_SIZE, Contract, contract_to_dict
from deploy.robot.episode_log import Episode, EpisodeLog, save_episode
from deploy.robot.goals import check_goals
from deploy.robot.hardware import BallTracker, Clock, Robot
from deploy.robot.interp import Interpolated, SampleBuffer
from deploy.robot.modes import Mode, StateMachine
from deploy.robot.safety import FAULTS, LATCHING, fault_names, limits_from_contract, safe_target
from ttmjx.world import observation


class NumpyPolicy(Protocol):
    """A policy on the robot (numpy only): recurrent state and/or a frame stack."""

    def reset(self) -> Any:
        """The state at the start of an episode (e.g. zero LSTM carry; None if stateless)."""

    def step(self, state: Any, frame: np.ndarray, frames: np.ndarray) -> tuple[Any, np.ndarray]:
        """frame [O] (= frames[-1]), frames [k, O] oldest first (O = 13, ttmjx.world.observation)
        -> (state, action [8])."""


@dataclasses.dataclass(frozen=True)
class RunnerConfig:
    """Bounds and tolerances of the runner (the contract holds rates and joint limits)."""
    stale_s: float = 0.1            # joint or ball data older than this -> hold
    future_s: float = 0.005         # stamped later than its read ended + this: rejected
    jump_factor: float = 1.5        # feedback may move at most jump_factor * max_speed ...
    jump_tolerance: float = 0.02    # ... + this between two samples (m or rad)
    range_tolerance: float = 0.02   # feedback this far outside the ranges is a fault
    settle_reads: int = 3           # agreeing fresh joint samples before the first command
    home_speed: float = 0.3         # fraction of the command speed limits used to move home
    home_tolerance: float = 0.02    # |q - home| per joint that counts as home
    home_timeout_s: float = 10.0
    arm_timeout_s: float = 10.0     # waiting for a ball
    arm_poll_s: float = 0.001       # the tracker is read this often while waiting for a ball
    trigger_speed: float = 1.0      # m/s toward the robot (-x) that starts an episode
    ball_box: tuple = ((-4.0, 4.0), (-3.0, 3.0), (0.0, 4.0))   # plausible ball x, y, z (m)
    max_ball_speed: float = 40.0    # m/s between two ball samples
    # Follow the last two samples this far past the newest: the world's timing model does the same
    # (ttmjx.world.config.Timing.extrapolate_s), so training sees what the runner feeds the policy.
    # None: the contract's (the export's training world's).
    max_extrapolate_s: float | None = None
    # Homing after an episode takes the joints as settled only from samples stamped this long
    # after the episode's last command: the command delay and the servos' lag (a robot still
    # catching up with its last command is not a robot moved by hand: without the wait, a few ms
    # of extra command delay end a session in a false joint_mismatch HOLD).
    command_settle_s: float = 0.1

    def __post_init__(self):
        if not self.command_settle_s >= 0:
            raise ValueError(f"RunnerConfig.command_settle_s={self.command_settle_s}, expected >= 0")
        for name in ("stale_s", "future_s", "jump_factor", "home_timeout_s", "arm_timeout_s",
                     "arm_poll_s", "max_ball_speed"):
            if not getattr(self, name) > 0:
                raise ValueError(f"RunnerConfig.{name}={getattr(self, name)}, expected > 0")
        if not 0 < self.home_speed <= 1:
            raise ValueError(f"RunnerConfig.home_speed={self.home_speed}, expected in (0, 1]")
        if self.max_extrapolate_s is not None and not self.max_extrapolate_s >= 0:
            raise ValueError(f"RunnerConfig.max_extrapolate_s={self.max_extrapolate_s}, expected >= 0")
        if self.settle_reads < 1:
            raise ValueError(f"RunnerConfig.settle_reads={self.settle_reads}, expected >= 1")


# Two ball samples more than this many newest sampling intervals apart belong to different tracks
# (a dropped sample or two is not a gap).
TRACK_GAP = 2.5


class NoBallError(TimeoutError):
    """No ball came toward the robot within arm_timeout_s (the runner stays ARMED)."""


@contextlib.contextmanager
def _collector_paused():
    """The cyclic garbage collector off (module docstring, "Collector"); yields whether this
    call paused it (False inside an outer pause, or if the caller had switched it off: their
    choice stands). The episode's own garbage is freed by reference counting; cycles wait for
    the collection between episodes (run_episodes)."""
    if not gc.isenabled():
        yield False
        return
    froze = gc.get_freeze_count() == 0      # a caller's own freeze (serve's) is left as it is
    if froze:
        gc.freeze()     # what exists now is never traversed again (not collected first: that
    gc.disable()        # full pass is the pause avoided here, and the drivers already run)
    try:
        yield True
    finally:
        gc.enable()
        if froze:
            gc.unfreeze()


def frame_of(joints: np.ndarray, ball: np.ndarray, goal: np.ndarray,
             ball_vel: np.ndarray | None = None) -> np.ndarray:
    """joints [8], ball position [3], goal [2] (and the ball velocity [3] for 16-value frames)
    -> [13 or 16] float32 frame (ttmjx.world.observation)."""
    return observation.make_frame(joints, ball, goal, ball_vel).astype(np.float32)


class FrameStack:
    """The last k frames [k, size], oldest first; the first push fills every row (the padding
    of ttmjx.world.observation.frame_stack), one push per control tick."""

    def __init__(self, k: int, size: int = REAL_OBS_SIZE):
        self.frames = np.zeros((k, size), np.float32)
        self._empty = True

    def push(self, frame: np.ndarray) -> np.ndarray:
        """Add a frame [size]; returns a copy of the stack [k, size]."""
        if self._empty:
            self.frames[:] = frame
            self._empty = False
        else:
            self.frames[:-1] = self.frames[1:]
            self.frames[-1] = frame
        return self.frames.copy()


def _missing(dim: int) -> Interpolated:
    nan = np.full(dim, np.nan)
    return Interpolated(nan, np.zeros(dim), np.nan, np.nan, nan, nan)


def stale_bound_error(stale_s: float, ages, whose: str = "this station's",
                      why: str | dict = "by design (a sample period plus the latency)") -> str | None:
    """The one-line refusal of a stale bound (`--stale-ms`) below the oldest that a station's
    newest sample gets by design (ages: [(seconds, 'joint' | 'ball')]; why: the reason, or one
    per kind; the runner would hold before any episode played), or None when the bound covers
    every age."""
    if not ages:
        return None
    age, what = max(ages)
    if stale_s >= age - 1e-9:
        return None
    why = why[what] if isinstance(why, dict) else why
    return (f"--stale-ms {stale_s * 1e3:g}: {whose} {what} samples are up to {age * 1e3:.3g} ms old {why}, so the "
            f"runner would hold before any episode played; expected at least {math.ceil(age * 1e4 - 1e-6) / 10:g} ms")


class Runner:
    """Runs episodes of `policy` on `robot` with balls from `tracker`, paced by `clock`."""

    def __init__(self, robot: Robot, tracker: BallTracker, clock: Clock, policy: NumpyPolicy,
                 contract: Contract, config: RunnerConfig = RunnerConfig(),
                 policy_hash: str | None = None, seed: int = 0):
        # Start poses: the contract's home perturbed per episode within +-home_noise, as the
        # policy was trained (paper: "the initial pose is perturbed"); exact home without noise.
        self.pose_rng = np.random.default_rng([int(seed), 11])
        self.robot, self.tracker, self.clock, self.policy = robot, tracker, clock, policy
        self.contract, self.config = contract, config
        ages = [(age, what) for what, sensor in (("joint", robot), ("ball", tracker))
                for age in [getattr(sensor, "max_sample_age_s", None)] if isinstance(age, (int, float))]
        error = stale_bound_error(config.stale_s, ages)         # where the station states them
        if error:
            raise ValueError(error)
        self.policy_hash = policy_hash or getattr(policy, "policy_hash", None) or "unknown"
        self.limits = limits_from_contract(contract)
        self.true_speed = np.asarray(contract.max_speed, np.float64)
        self.home = np.asarray(contract.home, np.float64)
        self._home = self.home                          # where this homing goes (move_home)
        self.sm = StateMachine()
        self.joints, self.ball = SampleBuffer(8), SampleBuffer(3)
        self.last_target: np.ndarray | None = None     # the last command sent [8]
        self.t_last_sent: float | None = None
        self.fault_counts: Counter = Counter()          # fault name -> ticks (or samples) with it
        self.overruns = self.skipped = self.episodes = 0
        self._log: EpisodeLog | None = None

    @property
    def mode(self) -> Mode:
        return self.sm.mode

    # ------------------------------------------------------------------ commands
    def hold(self, reason: str) -> None:
        """Enter HOLD (from any mode): re-send the last safe target once, then send nothing."""
        now = self.clock.now()
        if self.last_target is not None:
            self._send(self.last_target, now)
        self.sm.to(Mode.HOLD, now, reason)

    def release(self) -> None:
        """HOLD -> IDLE (an operator's explicit command)."""
        self.sm.require(Mode.HOLD, action="release()")
        self.sm.to(Mode.IDLE, self.clock.now(), "release")

    def disarm(self) -> None:
        """ARMED -> IDLE (e.g. after NoBallError)."""
        self.sm.require(Mode.ARMED, action="disarm()")
        self.sm.to(Mode.IDLE, self.clock.now(), "disarm")

    def start_pose(self) -> np.ndarray | None:
        """[8] the next episode's start pose: home + U(-1, 1) * contract.home_noise, within the
        joint ranges; None (exact home) if the contract has no noise."""
        noise = np.asarray(self.contract.home_noise, np.float64)
        if not noise.any():
            return None
        q = self.home + self.pose_rng.uniform(-1.0, 1.0, 8) * noise
        return np.clip(q, self.limits.lower, self.limits.upper)

    def move_home(self, pose=None) -> bool:
        """IDLE or HOLD -> HOMING -> ARMED (True), or -> HOLD on a fault or timeout (False).

        pose [8]: where to wait for the ball this time (default: the contract's home), e.g. the
        perturbed home poses the simulation starts its episodes from; within the joint ranges."""
        self.sm.require(Mode.IDLE, Mode.HOLD, action="move_home()")
        self._home = self._check_pose(pose)
        with self._hold_on_error():
            return self._move_home()

    def _check_pose(self, pose) -> np.ndarray:
        if pose is None:
            return self.home
        q = np.asarray(pose, np.float64)
        lim = self.limits
        if q.shape != (8,) or not np.all(np.isfinite(q)) or np.any((q < lim.lower) | (q > lim.upper)):
            raise ValueError(f"move_home: pose must be 8 finite joint values within the ranges, got {pose!r}")
        return q

    def run_episode(self, goal, t_start: float | None = None) -> Episode | None:
        """ARMED: wait for a ball, then run one episode toward goal [2].

        t_start: the launch time, where the thrower announces it (a launcher this computer
        fires): tick 0 is then at t_start, as a simulated episode starts at the launch (the
        tracker must deliver its launch sample by then, i.e. without latency, as the simulated
        station's `zero` timing does; else tick 0 finds the ball stale and the runner holds).
        Without it tick 0 is at the first sample of the incoming ball's track (_track_start),
        found when the tracker sees the ball coming.
        Returns the Episode (mode then IDLE, or HOLD after a fault), or None if a fault while
        waiting put the runner in HOLD. Raises NoBallError (still ARMED) if no ball came.
        """
        goal = check_goals(goal)
        if goal.shape[0] != 1:
            raise ValueError(f"run_episode takes one goal (x, y), got {goal.shape[0]}")
        self.sm.require(Mode.ARMED, action="run_episode()")
        with _collector_paused(), self._hold_on_error():
            if not self._wait_for_ball(t_start):
                return None
            return self._run(goal[0], self._track_start() if t_start is None else float(t_start))

    def run_episodes(self, goals, out_dir: str | None = None,
                     on_armed: Callable[[int], float | None] | None = None,
                     prefix: str = "episode",
                     complete: Callable[[int, Episode], Episode] | None = None,
                     on_no_ball: Callable[[int], None] | None = None,
                     poses=None) -> list[Episode]:
        """One episode per goal [N, 2]: move home (to poses[i] [8] if given), (on_armed(i)), run,
        (complete(i, ep)), save as `<prefix>_<i:04d>` under out_dir. on_armed may return the
        launch time of the throw it started (run_episode's t_start). Stops early (returning
        what ran) if the runner ends up in HOLD, since only an operator may clear a hold. With
        on_no_ball, a ball that never came (NoBallError) calls on_no_ball(i) and moves on to
        the next goal; without, it raises."""
        episodes = []
        with _collector_paused() as paused:
            for i, goal in enumerate(check_goals(goals)):
                pose = self.start_pose() if poses is None else poses[i]
                if self.mode == Mode.HOLD or not self.move_home(pose):
                    break
                t_start = on_armed(i) if on_armed is not None else None
                try:
                    ep = self.run_episode(goal, t_start)
                except NoBallError:
                    if on_no_ball is None:
                        raise
                    on_no_ball(i)
                    continue
                if ep is None:
                    break
                if complete is not None:
                    ep = complete(i, ep)
                ep.meta["episode"] = i
                if out_dir is not None:
                    save_episode(out_dir, f"{prefix}_{i:04d}", ep)
                episodes.append(ep)
                if self.mode == Mode.HOLD:
                    break
                if paused:
                    gc.collect()            # between episodes: only what the session made
        return episodes

    # ------------------------------------------------------------------ inputs
    def _poll_joints(self, now: float) -> int:
        """Read the robot once; returns fault bits (joint_stale if the newest accepted sample
        is too old)."""
        t, q = self.robot.read()
        q = np.asarray(q, np.float64)
        if q.shape != (8,):
            raise ValueError(f"Robot.read() returned joints of shape {q.shape}, expected (8,)")
        t = float(t)
        faults = self._joint_faults(t, q, self._after_read(now))
        repeat = faults == 0 and t == self.joints.newest_time   # the same sample read again
        if not repeat:
            if self._log is not None:
                self._log.add_joint(t, q, faults == 0)
            if faults == 0:
                self.joints.add(t, q)
        if now - self.joints.newest_time > self.config.stale_s:
            faults |= FAULTS["joint_stale"]
        return faults | self._robot_fault()

    def _robot_fault(self) -> int:
        """robot_fault if the robot's drivers report a device fault (hardware.Robot: optional
        fault()); the reads that saw it are counted under `robot_fault:<name>` too."""
        report = getattr(self.robot, "fault", None)
        name = report() if report is not None else None
        if not name:
            return 0
        self.fault_counts[f"robot_fault:{name}"] += 1
        return FAULTS["robot_fault"]

    def _after_read(self, now: float) -> float:
        """The time a sensor read ended: what its samples' times are checked against (a driver
        thread may stamp a sample on this clock after the tick's `now` and before the read)."""
        return max(now, float(self.clock.now()))

    def _joint_faults(self, t: float, q: np.ndarray, now: float) -> int:
        """Fault bits of one new joint sample (0 = accept); now: when it was read."""
        cfg, lim = self.config, self.limits
        if not (np.isfinite(t) and np.all(np.isfinite(q))):
            return FAULTS["joint_nonfinite"]
        newest = self.joints.newest_time
        if t > now + cfg.future_s or t < newest:
            return FAULTS["joint_time"]
        if np.any((q < lim.lower - cfg.range_tolerance) | (q > lim.upper + cfg.range_tolerance)):
            return FAULTS["joint_out_of_range"]
        if len(self.joints):    # (at equal times only jump_tolerance is allowed)
            allowed = cfg.jump_factor * self.true_speed * (t - newest) + cfg.jump_tolerance
            if np.any(np.abs(q - self.joints.newest) > allowed):
                return FAULTS["joint_jump"]
        return 0

    def _poll_ball(self, now: float) -> int:
        """Read the tracker once; accepted samples are buffered. Returns ball_dropped if any
        sample was rejected (not a latching fault: staleness decides)."""
        ts, xyz = self.tracker.read()
        ts = np.asarray(ts, np.float64).reshape(-1)
        xyz = np.asarray(xyz, np.float64)
        if xyz.shape != (len(ts), 3):
            raise ValueError(f"BallTracker.read() returned {len(ts)} times and positions of shape "
                             f"{xyz.shape}, expected ({len(ts)}, 3)")
        faults, read_at = 0, self._after_read(now)
        for t, x in zip(ts, xyz):
            ok = self._ball_ok(float(t), x, read_at)
            if self._log is not None:
                self._log.add_ball(float(t), x, ok)
            if ok:
                self.ball.add(float(t), x)
            else:
                faults |= FAULTS["ball_dropped"]
                self.fault_counts["ball_dropped_samples"] += 1
        return faults

    def _ball_ok(self, t: float, x: np.ndarray, now: float) -> bool:
        cfg = self.config
        if not (np.isfinite(t) and np.all(np.isfinite(x))):
            return False
        newest = self.ball.newest_time
        if t > now + cfg.future_s or t <= newest:
            return False
        box = np.asarray(cfg.ball_box)
        if np.any((x < box[:, 0]) | (x > box[:, 1])):
            return False
        if len(self.ball) and np.linalg.norm(x - self.ball.newest) > cfg.max_ball_speed * (t - newest):
            return False
        return True

    def _ball_stale(self, now: float) -> int:
        return FAULTS["ball_stale"] if now - self.ball.newest_time > self.config.stale_s else 0

    def _at(self, buf: SampleBuffer, t: float) -> Interpolated:
        ext = self.contract.extrapolate_s if self.config.max_extrapolate_s is None else self.config.max_extrapolate_s
        return buf.at(t, ext) if len(buf) else _missing(buf.dim)

    def _frame(self, joint: Interpolated, ball: Interpolated, goal: np.ndarray) -> np.ndarray:
        """The policy's frame: a 16-value contract adds the tracker's ball velocity, the slope of
        the line the ball's position was read from (what the training world shows)."""
        vel = ball.slope if self.contract.obs_size == 16 else None
        return frame_of(joint.value, ball.value, goal, vel)

    # ------------------------------------------------------------------ output
    def _send(self, target: np.ndarray, now: float) -> None:
        # The send time is read at the moment of sending (not when the tick decided): the step
        # limit of the next tick then measures its elapsed time from the real send, so the
        # interval between two sends is never shorter than the one the limit allowed for.
        sent_at = self.clock.now()
        self.robot.send(target.copy())
        self.last_target, self.t_last_sent = target.copy(), sent_at

    def _elapsed(self, now: float) -> float | None:
        return None if self.t_last_sent is None else now - self.t_last_sent

    @contextlib.contextmanager
    def _hold_on_error(self):
        """Any exception (driver error, bad shape, Ctrl-C) leaves the robot in HOLD."""
        try:
            yield
        except NoBallError:
            raise                       # not a fault: the robot waits at home, still ARMED
        except BaseException as e:
            self._log = None
            if self.mode != Mode.HOLD:
                with contextlib.suppress(Exception):
                    self.hold(f"error: {type(e).__name__}: {e}")
            raise

    def _count(self, bits: int) -> None:
        for name in fault_names(bits):
            self.fault_counts[name] += 1

    # ------------------------------------------------------------------ loops
    def _paced(self, timeout_s: float, dt: float | None = None):
        """Yield (n, now) on the deadline grid t0 + n * dt (default: the control period),
        skipping deadlines already passed, until timeout_s; then yield (-1, now) once."""
        dt, t0 = dt or self.contract.dt, self.clock.now()
        n = 0
        while True:
            self.clock.sleep_until(t0 + n * dt)
            now = self.clock.now()
            if now - t0 > timeout_s:
                yield -1, now
                return
            yield n, now
            n = max(n + 1, int(np.floor((self.clock.now() - t0) / dt)) + 1)

    def _move_home(self) -> bool:
        cfg = self.config
        self.sm.to(Mode.HOMING, self.clock.now(), "move_home")
        settle, settled = [], False   # fresh agreeing joint samples before the first command
        for n, now in self._paced(cfg.home_timeout_s):
            if n < 0:
                self.hold("homing timeout")
                return False
            before = self.joints.newest_time
            faults = self._poll_joints(now) & LATCHING
            self._poll_ball(now)
            if faults:
                self._count(faults)
                self.hold("homing: " + ",".join(fault_names(faults)))
                return False
            if not settled:
                fresh = self.joints.newest_time > before
                caught_up = (self.t_last_sent is None
                             or self.joints.newest_time >= self.t_last_sent + cfg.command_settle_s)
                if fresh and caught_up:
                    settle.append(self.joints.newest)
                here = self._agreeing(settle)
                if here is None:
                    continue
                settled = True
                if not self._resume_from(here):
                    return False
            if self._step_home(now):
                return True
        raise AssertionError("unreachable")

    def _agreeing(self, settle: list) -> np.ndarray | None:
        """The joints [8], clipped to the ranges, once the last settle_reads fresh samples
        [8] agree within jump_tolerance; None before."""
        cfg = self.config
        if len(settle) < cfg.settle_reads:
            return None
        recent = np.array(settle[-cfg.settle_reads:])
        if np.any(recent.max(0) - recent.min(0) > cfg.jump_tolerance):
            return None
        return np.clip(recent[-1], self.limits.lower, self.limits.upper)

    def _resume_from(self, here: np.ndarray) -> bool:
        """Command from the settled joints here [8]: this runner's first command starts where
        the robot is; later, a robot far from its last command is a fault (HOLD, False)."""
        if self.last_target is None:
            self.last_target = here
        elif np.any(np.abs(here - self.last_target) > self.limits.max_step + self.config.jump_tolerance):
            self._count(FAULTS["joint_mismatch"])
            self.hold("homing: joint_mismatch (the robot is not where it was last "
                      "commanded; restart the runner after moving it by hand)")
            return False
        return True

    def _step_home(self, now: float) -> bool:
        """Send one slow, speed-limited command toward home; at home: ARMED (True)."""
        cfg = self.config
        cmd = safe_target(self.limits, self._home, self.last_target, self._elapsed(now), cfg.home_speed)
        self._send(cmd.target, now)
        if (np.array_equal(cmd.target, self._home)
                and np.all(np.abs(self.joints.newest - self._home) <= cfg.home_tolerance)):
            self.sm.to(Mode.ARMED, now, "at home")
            return True
        return False

    def _wait_for_ball(self, t_start: float | None = None) -> bool:
        """ARMED until a fresh ball moves toward the robot, or (t_start given) until the last
        tick before the launch (True); HOLD on a fault (False)."""
        if t_start is not None:
            return self._wait_until(float(t_start))
        cfg = self.config
        for n, now in self._paced(cfg.arm_timeout_s, cfg.arm_poll_s):
            if n < 0:
                raise NoBallError(f"no ball moving toward the robot faster than "
                                  f"{cfg.trigger_speed} m/s within {cfg.arm_timeout_s} s")
            if not self._armed_poll(now):
                return False
            if self._ball_coming(now):
                return True
        raise AssertionError("unreachable")

    def _wait_until(self, t_start: float) -> bool:
        """ARMED, polling every control period, until less than one is left before t_start."""
        now = self.clock.now()
        while now + self.contract.dt < t_start:
            self.clock.sleep_until(now + self.contract.dt)
            now = self.clock.now()
            if not self._armed_poll(now):
                return False
        return True

    def _armed_poll(self, now: float) -> bool:
        """Read both sensors while ARMED; a latching joint fault -> HOLD (False)."""
        faults = self._poll_joints(now) & LATCHING
        if faults:
            self._count(faults)
            self.hold("armed: " + ",".join(fault_names(faults)))
            return False
        self._poll_ball(now)
        return True

    def _ball_coming(self, now: float) -> bool:
        """The two newest ball samples are fresh, at most stale_s apart, and move toward the
        robot (-x) fast enough."""
        if len(self.ball) < 2 or self._ball_stale(now):
            return False
        dt = self.ball.times[-1] - self.ball.times[-2]
        dx = self.ball.values[-1, 0] - self.ball.values[-2, 0]
        return dt <= self.config.stale_s and dx < -self.config.trigger_speed * dt

    def _track_start(self) -> float:
        """The time of the first sample of the incoming ball's track: the oldest of the newest
        samples that each moved toward the robot faster than trigger_speed since the one before,
        with no gap (at most TRACK_GAP times the newest sampling interval) in between."""
        t, x = self.ball.times, self.ball.values[:, 0]
        dt = np.diff(t)
        coming = (dt <= TRACK_GAP * dt[-1]) & (np.diff(x) < -self.config.trigger_speed * dt)
        not_coming = np.flatnonzero(~coming)
        return float(t[not_coming[-1] + 1 if len(not_coming) else 0])

    def _run(self, goal: np.ndarray, t0: float) -> Episode:
        c = self.contract
        T, dt = c.horizon, c.dt
        log = self._log = EpisodeLog(T, goal, c.obs_size)
        stack = FrameStack(c.frame_stack, c.obs_size)
        self.sm.to(Mode.RUNNING, self.clock.now(), "ball in play")
        history_start = len(self.sm.history) - 1
        self._state, reset_fault = None, 0
        try:
            self._state = self.policy.reset()
        except Exception:
            reset_fault = FAULTS["policy_error"]
        # Every tick whose deadline has passed when the episode begins is logged, not executed:
        # executing one late would start its command off the tick grid (the world's timing model
        # acts from the first tick after the trigger, ttmjx.world.timing).
        end, n = "done", min(T, max(0, int(np.ceil((self.clock.now() - t0) / dt - 1e-9))))
        for m in range(n):                                     # before the episode began
            self._record_past(log, stack, m, t0 + m * dt, goal)
        while n < T:
            self.clock.sleep_until(t0 + n * dt)
            wake = self.clock.now()
            faults = (self._poll_joints(wake) | self._poll_ball(wake) | self._ball_stale(wake)
                      | reset_fault)
            latest = min(T, int(np.floor((wake - t0) / dt)))   # the newest deadline passed
            for m in range(n, latest):                         # deadlines missed entirely
                self._record_skipped(log, stack, m, t0 + m * dt, goal)
            n = max(n, latest)
            if n >= T:
                break
            faults |= self._tick(log, stack, n, t0 + n * dt, wake, goal, faults)
            if faults & LATCHING:
                end = "hold: " + ",".join(fault_names(faults & LATCHING))
                break
            n += 1
        self._log = None
        if end == "done":
            self.sm.to(Mode.IDLE, self.clock.now(), "episode done")
        else:
            self.hold(end)
        self.episodes += 1
        return Episode(log.trajectories(), log.extras(), self._meta(log, goal, t0, end, history_start))

    def _record_skipped(self, log: EpisodeLog, stack: FrameStack, m: int, t_grid: float,
                        goal: np.ndarray) -> None:
        self._record_past(log, stack, m, t_grid, goal, FAULTS["skipped"])
        self.skipped += 1
        self._count(FAULTS["skipped"])

    def _record_past(self, log: EpisodeLog, stack: FrameStack, m: int, t_grid: float,
                     goal: np.ndarray, faults: int = 0) -> None:
        """Log tick m, whose deadline has passed, from the buffered samples; its frame enters
        the stack; the robot holds its target."""
        joint, ball = self._at(self.joints, t_grid), self._at(self.ball, t_grid)
        frame = self._frame(joint, ball, goal)
        stack.push(frame)
        log.tick(m, t_grid=t_grid, frame=frame, ball=ball, joint=joint, command=self.last_target,
                 faults=faults, executed=False)

    def _tick(self, log: EpisodeLog, stack: FrameStack, n: int, t_grid: float, wake: float,
              goal: np.ndarray, faults: int) -> int:
        """One executed tick: frame -> policy -> filter -> send. Returns its fault bits."""
        joint, ball = self._at(self.joints, t_grid), self._at(self.ball, t_grid)
        frame = self._frame(joint, ball, goal)
        frames = stack.push(frame)
        raw = None
        if not faults & LATCHING:
            raw, faults = self._policy_action(frame, frames, faults)
        now = self.clock.now()
        t_sent = np.nan
        if not faults & LATCHING:
            cmd = safe_target(self.limits, raw, self.last_target, self._elapsed(now))
            faults |= cmd.faults
            if not faults & LATCHING:
                self._send(cmd.target, now)
                t_sent = now
                faults = self._prepare(faults)
        if now > t_grid + self.contract.dt:
            faults |= FAULTS["overrun"]
            self.overruns += 1
        log.tick(n, t_grid=t_grid, frame=frame, ball=ball, joint=joint, command=self.last_target,
                 faults=faults, executed=True, t_wake=wake, t_sent=t_sent, raw_action=raw)
        self._count(faults)
        return faults

    def _prepare(self, faults: int) -> int:
        """After the command is out: let the policy precompute the observation-independent part
        of its next step (numpy LSTM: the recurrent matmuls), off the latency-critical path."""
        prep = getattr(self.policy, "prepare", None)
        if prep is None:
            return faults
        try:
            prep(self._state)
        except Exception:
            return faults | FAULTS["policy_error"]
        return faults

    def _policy_action(self, frame, frames, faults) -> tuple[np.ndarray | None, int]:
        """The policy's raw action [8] (None if it failed) and the updated fault bits; the new
        recurrent state is kept in self._state."""
        try:
            self._state, action = self.policy.step(self._state, frame.copy(), frames)
            raw = np.asarray(action, np.float64)
        except Exception:
            return None, faults | FAULTS["policy_error"]
        if raw.shape != (8,):
            return None, faults | FAULTS["policy_error"]
        if not np.all(np.isfinite(raw)):
            faults |= FAULTS["policy_nonfinite"]
        return raw, faults

    def _meta(self, log: EpisodeLog, goal, t0: float, end: str, history_start: int) -> dict:
        lat = log.t_sent - log.t_grid
        per_fault = {name: int(np.sum((log.faults & bit) != 0)) for name, bit in FAULTS.items()}
        return {
            "source": "deploy.robot.runner", "policy_hash": self.policy_hash,
            "episode": self.episodes, "goal": [float(g) for g in goal], "t0": float(t0),
            "end": end, "ticks": int(log.valid.sum()), "executed": int(log.executed.sum()),
            "faults": per_fault,
            "max_latency_s": float(np.nanmax(lat)) if np.any(np.isfinite(lat)) else None,
            "events_detected": False,   # hit/landing are not measured by the runner
            "contract": contract_to_dict(self.contract),
            "runner": dataclasses.asdict(self.config),
            "transitions": [list(h) for h in self.sm.history[history_start:]],
        }
