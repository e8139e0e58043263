"""The simulated station: the robot, the ball tracker and the clock of deploy/robot/hardware.py on
MuJoCo C physics, so the robot runner plays whole episodes exactly as against hardware.

* Physics: `ttmjx.world.scene.model(cfg)` (MuJoCo's ellipsoid fluid model flies the ball) stepped at
  cfg.physics_dt, lazily: every call into the station (a joint read, a command, a tracker read)
  first advances the physics to `clock.now()`. The clock is injectable: `SimClock` (fake time
  that jumps on sleep_until, so an episode runs much faster than real time; optionally charging
  the runner's own computation time) or deploy.robot.hardware.MonotonicClock (real time).
* Robot: the 8 position actuators are driven toward the sent targets, each target ramped in
  linearly over `ramp_s` (default: one control period, as the simulation ramps its targets over
  a control step). Joint feedback is sampled every 1/joint_hz s and delivered
  joint_latency_s late, timestamped on the clock's time base. Every command is logged (time,
  target, true joints), as deploy.robot.fakes.FakeRobot does, for deploy.robot.safety.count_violations.
* Ball: launched by `ttmjx.world.thrower.sample_throws` (throw_in, which returns the launch time,
  on a physics step); the tracker samples it every 1/tracker_hz s (125 Hz), from the launch
  instant on when it falls on the tracker's rate, timestamped, delivered tracker_latency_s late.
  `TIMING` names sensor profiles: nominal (the defaults above) and zero (every physics step
  sampled, no latency: with SimClock(charge_compute=False) and episodes started at the launch
  the runner sees what the simulation's policy sees, scripts/dev/runner_vs_eval.py). Before a launch and
  after `finish_throw` the ball is parked out of sight (the tracker reports nothing). The room
  keeps a ball in view (a real lab is enclosed): it bounces off the floor and stops at barriers
  (|x| = room_x, |y| = room_y), so a missed ball does not vanish from the tracker mid-episode.
* Events (`ThrowEvents`): the world's one definition, ttmjx.world.env.update_events, applied to
  the ball's motion one physics step at a time (`fold_physics_steps`): each step's ball state
  before and after it and the blade centre, so the times of the hit and the landing are
  resolved to the physics step and the room's corrections of the ball (below) are never taken
  for contacts. hit = first paddle contact; bounce_own = a table contact on the robot's half
  before the hit; net = any net contact; landing = the first table contact after the hit, or
  where a hit ball falls through table height outside the table; on_opponent = that table
  contact has x > 0; the throw is over when it landed or the ball fell below the table top.

* Truth: every physics step of a throw in flight, from its launch until it is parked, the
  ball's true centre and its time (`true_ball`), which the logs keep apart from the tracker's
  samples (`with_truth`).

`play(runner, station, goals, out_dir)` runs episodes like Runner.run_episodes, but completes each
logged episode with the station's events (hit, hit_step, landing, on_opponent, ..., the true
launch) and the true ball (`with_truth`) before saving it, so the logs relabel like simulation
data (`ttmjx train --data`) and their landings can be recomputed from the truth.
`run_sim(policy_dir, goals, ...)` is `ttmjx robot run --station sim`.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import math
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from deploy.robot.contract import Contract
from deploy.robot.episode_log import Episode
from deploy.robot.goals import check_goals
from deploy.robot.outcomes import ThrowEvents, complete_episode, goal_summary, latency_ms  # noqa: F401 (re-exported)
from deploy.robot.runner import Runner, RunnerConfig
from deploy.robot.safety import count_violations
from deploy.robot.session import StationHooks, run_session
from ttmjx.world import env, files, scene
from ttmjx.world.config import TIMING_PROFILES, Timing, World, physics_steps_per_sample

# The robot's two controllers, in joint order: the gantry (Modbus) and the arm (EGM).
PARTS = {"gantry": slice(0, 2), "arm": slice(2, 8)}
# Ball parked out of sight between throws (no contacts, the tracker reports nothing).
PARK = np.array([0.0, 0.0, -5.0])
# Physics steps folded into the events per compiled call (shorter runs are padded).
FOLD_CHUNK = 64


@functools.partial(jax.jit, static_argnums=0)
def _fold_chunk(cfg: World, ev: env.Events, steps, prev, ball, paddle, valid) -> env.Events:
    """env.update_events over FOLD_CHUNK physics steps one at a time; valid [C] False: padding."""
    def one(ev, xs):
        step, p, b, q, ok = xs
        new = env.update_events(cfg, ev, step, p, b[None], q[None])
        return jax.tree.map(lambda n, o: jnp.where(ok, n, o), new, ev), None

    return jax.lax.scan(one, ev, (steps, prev, ball, paddle, valid))[0]


def fold_physics_steps(cfg: World, ev: env.Events, steps, prev, ball, paddle) -> env.Events:
    """One throw's events after S more physics steps, each folded in by ttmjx.world.env.update_events
    as its own step (so `hit_step` and `done_step` are physics-step indices).

    steps [S] int: the index of each step; prev [S, 6]: the ball's position and velocity just
    before the step; ball [S, 6]: just after it; paddle [S, 3]: the blade centre at the step.
    """
    arrays = [np.asarray(steps, np.int32)] + [np.asarray(x, np.float32) for x in (prev, ball, paddle)]
    for i in range(0, len(arrays[0]), FOLD_CHUNK):
        chunk = [x[i:i + FOLD_CHUNK] for x in arrays]
        n = len(chunk[0])
        padded = [np.concatenate([x, np.repeat(x[:1], FOLD_CHUNK - n, 0)]) for x in chunk]
        ev = _fold_chunk(cfg, ev, *padded, np.arange(FOLD_CHUNK) < n)
    return ev


class SimClock:
    """Fake time on the runner's time base: sleep_until(t) jumps to t at once.

    charge_compute=True: wall time spent between clock calls (the runner's own work: the policy,
    the filter, logging) also passes, so latencies and overruns are as on hardware; time spent
    inside `excluded()` (the station's physics) does not.
    """

    def __init__(self, start: float = 0.0, charge_compute: bool = False):
        self.t, self.charge_compute = float(start), charge_compute
        self._mark = time.perf_counter()
        self.sleeps = 0

    def _charge(self) -> None:
        if self.charge_compute:
            w = time.perf_counter()
            self.t += w - self._mark
            self._mark = w

    def now(self) -> float:
        self._charge()
        return self.t

    def sleep_until(self, t: float) -> None:
        self._charge()
        self.t = max(self.t, float(t))
        self.sleeps += 1
        self._mark = time.perf_counter()

    def advance(self, dt: float) -> None:
        if dt < 0:
            raise ValueError(f"SimClock.advance({dt}): time cannot go back")
        self._charge()
        self.t += dt

    @contextlib.contextmanager
    def excluded(self):
        """Wall time spent inside does not pass on this clock."""
        self._charge()
        try:
            yield
        finally:
            self._mark = time.perf_counter()





class SimRobot:
    """deploy.robot.hardware.Robot of a SimStation."""

    def __init__(self, station: "SimStation"):
        self.s = station
        self.max_sample_age_s = station.max_sample_age_s(joint=True)     # Runner checks its stale bound
        self.sent_t: list[float] = []
        self.sent_q: list[np.ndarray] = []
        self.true_at_send: list[np.ndarray] = []

    def read(self) -> tuple[float, np.ndarray]:
        s = self.s
        now = s.sync()
        for t, q, due in reversed(s.joint_samples):
            if due <= now + 1e-12:
                return t, q.copy()
        t, q, _ = s.joint_samples[0]
        return t, q.copy()

    def send(self, q) -> None:
        q = np.asarray(q, np.float64)
        if q.shape != (8,) or not np.all(np.isfinite(q)):
            raise ValueError(f"SimRobot.send: expected 8 finite targets, got {q!r}")
        s = self.s
        now = s.sync()
        s.set_target(q, now)
        self.sent_t.append(now)
        self.sent_q.append(q.copy())
        self.true_at_send.append(s.joints().copy())

    def command_log(self) -> tuple[np.ndarray, np.ndarray]:
        """(times [N], targets [N, 8]) of every command sent."""
        return np.asarray(self.sent_t), np.asarray(self.sent_q).reshape(-1, 8)


class SimTracker:
    """deploy.robot.hardware.BallTracker of a SimStation: samples since the previous read."""

    def __init__(self, station: "SimStation"):
        self.s = station
        self.max_sample_age_s = station.max_sample_age_s(joint=False)    # Runner checks its stale bound
        self._last = -math.inf

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.s
        now = s.sync()
        ts, xs = [], []
        for t, x, due in s.ball_samples:
            if self._last < t and due <= now + 1e-12:
                ts.append(t)
                xs.append(x)
        if ts:
            self._last = ts[-1]
        return np.asarray(ts, np.float64), np.asarray(xs, np.float64).reshape(-1, 3)


# Sensor and actuation timing profiles by name (ttmjx.world.config.TIMING_PROFILES, the one timing
# model of the training world and this station). zero: ideal sensors, every physics step sampled
# and delivered at once, so the runner sees the state the simulation's policy sees (with
# SimClock(charge_compute=False) and episodes started at the launch: scripts/dev/runner_vs_eval.py).
TIMING = TIMING_PROFILES


class SimStation:
    """Robot, tracker and clock on MuJoCo C physics (module docstring). joint_hz / tracker_hz
    None: a sample every physics step."""

    def __init__(self, cfg: World = World(), contract: Contract | None = None, clock=None,
                 seed: int = 0, timing: Timing = TIMING_PROFILES["nominal"],
                 tracker_noise_m: float = 0.0, ramp_s: float | None = None, q0=None,
                 throws_per_batch: int = 16, room_x: float = 3.5, room_y: float = 2.5):
        if not isinstance(timing, Timing):
            raise TypeError(f"SimStation: timing must be a ttmjx.world.config.Timing (profiles: "
                            f"{sorted(TIMING_PROFILES)}), got {timing!r}")
        self.cfg, self.timing = cfg, timing
        self.clock = clock if clock is not None else SimClock()
        self.m = scene.model(cfg, fluid=True)
        self.d = mujoco.MjData(self.m)
        self.ids = scene.ids(self.m)
        self.dt = float(self.m.opt.timestep)
        self.joint_every = self._steps_per(timing.joint_hz, "joint_hz")
        self.ball_every = self._steps_per(timing.tracker_hz, "tracker_hz")
        self.joint_latency_s, self.tracker_latency_s = timing.joint_latency_s, timing.tracker_latency_s
        self.action_delay_s = timing.action_delay_s
        # A timing with per-episode spreads (Timing.spreads) drifts: each throw draws its latencies
        # and command delay as the training world does (ttmjx.world.timing.draw), from its own
        # stream so that a fixed timing's session is unchanged.
        self._drift_rng = np.random.default_rng([seed, 7])
        self.delays_log: list[tuple[float, float, float]] = []
        self.joint_offset = 0      # joint samples at physics steps n = joint_offset (mod joint_every)
        self.noise_m, self.rng = tracker_noise_m, np.random.default_rng(seed)
        self.ramp_s = float(ramp_s if ramp_s is not None else (contract.dt if contract else cfg.control_dt))
        self.room = (room_x, room_y)
        self.seed, self.throws_per_batch = seed, throws_per_batch
        self._throws, self._throw_i, self._batch = None, 0, 0

        self.events: ThrowEvents | None = None       # the throw in flight (or the last one)
        self._world_events = env.no_events()           # its events as the world keeps them
        self._track: list = []                         # its steps not yet folded into them
        self._truth: list = []                         # its (time, true ball centre [3]) per physics step
        q0 = self._place_robot(q0)
        self.t_origin = float(self.clock.now())
        self.n = 0                                        # physics steps taken
        # Samples as (time, value, delivery time); dropped samples are never stored.
        self.joint_samples = collections.deque([(self.t_origin, q0.copy(), self.t_origin)], maxlen=256)
        self.ball_samples = collections.deque(maxlen=512)
        self.in_flight = False
        self.pending: tuple | None = None                  # (t_launch, (pos, vel, spin, aim))
        self.throw_log: list[ThrowEvents] = []
        self.physics_steps = 0
        self.trace: list | None = None     # set to [] to record (ball [6], blade centre [3]) per step
        self.robot, self.tracker = SimRobot(self), SimTracker(self)

    def _place_robot(self, q0) -> np.ndarray:
        """Put the robot at q0 [8] (default: home with the world's reset noise), holding it
        there, and the ball out of sight; returns q0."""
        r = self.cfg.robot
        if q0 is None:
            noise = self.rng.uniform(-1.0, 1.0, 8) * np.asarray(r.home_noise)
            q0 = np.clip(np.asarray(r.home) + noise, r.lower, r.upper)
        q0 = np.asarray(q0, np.float64)
        self.d.qpos[self.ids.robot_qpos] = q0
        self.d.ctrl[:] = q0
        # Commands as ramps (start time, from, to) per part (PARTS), oldest first; a command
        # starts its ramp action_delay_s after it was sent.
        self._ramps = {part: collections.deque([(-math.inf, q0[p].copy(), q0[p].copy())], maxlen=64)
                       for part, p in PARTS.items()}
        self._park()
        mujoco.mj_forward(self.m, self.d)
        return q0

    def max_sample_age_s(self, joint: bool) -> float:
        """The oldest the newest delivered joint (or ball) sample gets by design: one sample
        period, plus the latency at the top of its per-throw spread, plus the jitter (drops aside)."""
        tm = self.timing
        every, latency = ((self.joint_every, tm.joint_latency_s) if joint else
                          (self.ball_every, tm.tracker_latency_s))
        return every * self.dt + latency + tm.spreads()[1 if joint else 0] + tm.jitter_s

    def _steps_per(self, hz: float | None, name: str) -> int:
        return physics_steps_per_sample(hz, self.cfg.physics_dt, name)

    # ---------------------------------------------------------------------- state
    @property
    def time(self) -> float:
        """Physics time on the clock's time base."""
        return self.t_origin + self.n * self.dt

    def joints(self) -> np.ndarray:
        return self.d.qpos[self.ids.robot_qpos].copy()

    def ball(self) -> np.ndarray:
        """[6] ball position and velocity (world)."""
        bq, bv = self.ids.ball_qpos, self.ids.ball_qvel
        return np.concatenate([self.d.qpos[bq:bq + 3], self.d.qvel[bv:bv + 3]])

    def true_ball(self) -> tuple[np.ndarray, np.ndarray]:
        """(times [P], true centre [P, 3]) of the last throw's ball, on the clock's time base: at
        its launch and after every physics step until it was parked (empty before a launch)."""
        t = np.array([x[0] for x in self._truth], np.float64)
        return t, np.array([x[1] for x in self._truth], np.float64).reshape(-1, 3)

    def set_target(self, q: np.ndarray, now: float, part: str | None = None) -> None:
        """A command sent at `now` (all 8 joints, or `part` of PARTS alone: the arm and the
        gantry are separate controllers): each part's ramp starts action_delay_s later, from
        where that part's earlier commands have its target then."""
        q = np.asarray(q, np.float64)
        for name in PARTS if part is None else (part,):
            # A shorter delay drawn for a new throw never starts a command before an earlier one.
            start = max(now + self.action_delay_s, self._ramps[name][-1][0])
            p = PARTS[name]
            q_p = q[p] if part is None else q
            lo, hi = np.asarray(self.cfg.robot.lower)[p], np.asarray(self.cfg.robot.upper)[p]
            self._ramps[name].append((start, self._part_at(name, start), np.clip(q_p, lo, hi)))

    def _part_at(self, part: str, t: float) -> np.ndarray:
        """The target of one part at time t: its newest ramp started by then."""
        for t0, q_from, q_to in reversed(self._ramps[part]):
            if t0 <= t + 1e-12:
                break
        w = 1.0 if self.ramp_s <= 0 else float(np.clip((t - t0) / self.ramp_s, 0.0, 1.0))
        return q_from + w * (q_to - q_from)

    def _ctrl_at(self, t: float) -> np.ndarray:
        """[8] the target at time t."""
        return np.concatenate([self._part_at(name, t) for name in PARTS])

    def part_targets(self) -> dict:
        """{part: its newest target} (what the controllers were last told)."""
        return {name: r[-1][2].copy() for name, r in self._ramps.items()}

    def _delivery(self, t: float, latency: float) -> float | None:
        """When a sample taken at t is delivered (latency + jitter), None if it is dropped."""
        tm = self.timing
        if tm.drop_prob and self.rng.random() < tm.drop_prob:
            return None
        return t + latency + (self.rng.uniform(0.0, tm.jitter_s) if tm.jitter_s else 0.0)

    # ---------------------------------------------------------------------- throws
    def prefetch(self) -> None:
        """Sample (and so compile) the throws and the event rules now rather than at the first
        throw_in."""
        with self._excluded():
            self._ensure_throws()
            z = np.zeros((1, 6))
            fold_physics_steps(self.cfg, env.no_events(), [0], z, z, z[:, :3])

    def _ensure_throws(self) -> None:
        if self._throws is None or self._throw_i >= self.throws_per_batch:
            from ttmjx.world.thrower import sample_throws
            key = jax.random.fold_in(jax.random.key(self.seed), self._batch)
            th = sample_throws(key, self.cfg, self.throws_per_batch)
            self._throws = jax.tree.map(lambda x: np.asarray(x, np.float64), th)
            self._throw_i, self._batch = 0, self._batch + 1

    def _next_throw(self):
        self._ensure_throws()
        th, i = self._throws, self._throw_i
        self._throw_i += 1
        return th.launch_pos[i], th.launch_vel[i], th.launch_spin[i], th.aim[i]

    def throw_in(self, delay_s: float = 0.3, throw=None) -> float:
        """Launch the next sampled throw at the first physics step delay_s or more from now (a
        throw in flight is removed); returns the launch time.

        throw: (launch_pos [3], launch_vel [3], launch_spin [3], aim [2]) to launch instead of
        a sampled one (tests, or replaying a logged launch)."""
        if throw is None:
            with self._excluded():              # sampling (JAX) is the station's time, not the runner's
                throw = self._next_throw()
        else:
            throw = tuple(np.asarray(x, np.float64).reshape(n) for x, n in zip(throw, (3, 3, 3, 2)))
        now = self.sync()
        if self.in_flight:
            self._park()
        self._draw_delays()
        step = max(math.ceil((now + float(delay_s) - self.t_origin) / self.dt - 1e-9), self.n)
        t_launch = self.t_origin + step * self.dt
        self.pending = (t_launch, throw)
        if self._launch_if_due():
            self._sample_ball(self.time)
        return t_launch

    def _draw_delays(self) -> None:
        """This throw's tracker latency, joint latency and command delay: the timing's centre,
        each shifted by a uniform draw within its spread (Timing.spreads), never below zero."""
        tm = self.timing
        spreads = np.asarray(tm.spreads())
        if spreads.max() > 0:
            base = np.array([tm.tracker_latency_s, tm.joint_latency_s, tm.action_delay_s])
            ball, joint, act = np.maximum(base + self._drift_rng.uniform(-1.0, 1.0, 3) * spreads, 0.0)
            self.tracker_latency_s, self.joint_latency_s, self.action_delay_s = float(ball), float(joint), float(act)
        self.delays_log.append((self.tracker_latency_s, self.joint_latency_s, self.action_delay_s))

    def _launch(self, t: float) -> None:
        self._fold_track()
        _, (pos, vel, spin, aim) = self.pending
        self.pending = None
        bq, bv = self.ids.ball_qpos, self.ids.ball_qvel
        self.d.qpos[bq:bq + 7] = np.concatenate([pos, [1.0, 0.0, 0.0, 0.0]])
        # Identity orientation at launch: the local angular velocity equals the world spin.
        self.d.qvel[bv:bv + 6] = np.concatenate([vel, spin])
        self.in_flight = True
        self._truth = [(t, np.asarray(pos, np.float64).copy())]
        self.events = ThrowEvents(t, pos.copy(), vel.copy(), spin.copy(), aim.copy())
        self._world_events = env.no_events()
        self.throw_log.append(self.events)

    def _park(self) -> None:
        self._fold_track()
        bq, bv = self.ids.ball_qpos, self.ids.ball_qvel
        self.d.qpos[bq:bq + 7] = np.concatenate([PARK, [1.0, 0.0, 0.0, 0.0]])
        self.d.qvel[bv:bv + 6] = 0.0
        self.in_flight = False

    def finish_throw(self, max_s: float = 3.0, poll_s: float = 0.02) -> ThrowEvents | None:
        """Let time pass (the robot holding its target) until the throw is over (landed, or
        fell below the table) or max_s; then park the ball. Returns the throw's events."""
        ev = self.events
        t_end = self.sync() + max_s
        while self.pending is not None or (self.in_flight and ev is not None and not ev.done):
            now = self.clock.now()
            if now >= t_end:
                break
            self.clock.sleep_until(min(now + poll_s, t_end))
            self.sync()
            ev = self.events
        self._park()
        self.pending = None
        return self.events

    # ---------------------------------------------------------------------- physics
    def sync(self) -> float:
        """Advance the physics to the clock's now; returns now."""
        now = float(self.clock.now())
        target = int(math.floor((now - self.t_origin) / self.dt + 1e-9))
        if target > self.n:
            with self._excluded():
                while self.n < target:
                    self._step()
                self._fold_track()
        return now

    def _excluded(self):
        """The clock's `excluded()` (SimClock with charge_compute) or a no-op."""
        excluded = getattr(self.clock, "excluded", None)
        return excluded() if excluded is not None else contextlib.nullcontext()

    def _step(self) -> None:
        """One physics step; a launch due at its end happens then, before the sensors sample
        (so the tracker can see the ball leave the thrower)."""
        t = self.time
        self.d.ctrl[:] = self._ctrl_at(t + self.dt)       # the ramped target at the end of the step
        prev = self.ball()
        mujoco.mj_step(self.m, self.d)
        self.n += 1
        self.physics_steps += 1
        if self.in_flight:
            self._track_step(prev)
            self._room()
            self._truth.append((self.time, self.ball()[:3]))
        else:
            self._park()
        self._launch_if_due()
        self._sample(self.time)

    def _launch_if_due(self) -> bool:
        """Launch the pending throw if its time has come (True)."""
        if self.pending is None or self.time < self.pending[0] - 1e-12:
            return False
        self._launch(self.time)
        return True

    def _sample(self, t: float) -> None:
        """The joint feedback and the ball tracker, each at its rate."""
        if (self.n - self.joint_offset) % self.joint_every == 0:
            due = self._delivery(t, self.joint_latency_s)
            if due is not None:
                self.joint_samples.append((t, self.joints(), due))
        if self.in_flight:
            self._sample_ball(t)

    def _sample_ball(self, t: float) -> None:
        """The tracker's sample at t (physics step self.n), if it falls on its rate."""
        if self.n % self.ball_every:
            return
        x = self.ball()[:3]
        if self.noise_m > 0:
            x = x + self.rng.normal(0.0, self.noise_m, 3)
        due = self._delivery(t, self.tracker_latency_s)
        if due is not None:
            self.ball_samples.append((t, x, due))

    def _track_step(self, prev: np.ndarray) -> None:
        """Keep the step just taken (ball [6] before it, ball [6] and blade centre [3] after) for
        the events (and the trace)."""
        ball, paddle = self.ball(), self.d.sensordata[:3].copy()
        self._track.append((self.n, prev, ball, paddle))
        if self.trace is not None:
            self.trace.append((ball, paddle))

    def _fold_track(self) -> None:
        """Fold the kept steps into the throw's events (the world's rules, ttmjx.world.env)."""
        if not self._track:
            return
        steps, prev, ball, paddle = (np.asarray(x) for x in zip(*self._track))
        self._track = []
        if self.events is None or self.events.done:
            return
        self._world_events = fold_physics_steps(self.cfg, self._world_events, steps, prev, ball, paddle)
        self.events.take(self._world_events, self.t_origin, self.dt)

    def _room(self) -> None:
        """Floor and barriers: the ball stays in the tracked volume."""
        d, bq, bv = self.d, self.ids.ball_qpos, self.ids.ball_qvel
        r = self.cfg.ball.radius
        pos, vel = d.qpos[bq:bq + 3], d.qvel[bv:bv + 6]
        if pos[2] < r:
            pos[2] = r
            if vel[2] < 0:
                vel[2] = -0.5 * vel[2]
            vel[:2] *= 0.7
            vel[3:] = 0.0
        for axis, lim in ((0, self.room[0]), (1, self.room[1])):
            if abs(pos[axis]) > lim:
                pos[axis] = math.copysign(lim, pos[axis])
                vel[0:2] = 0.0
                vel[3:] = 0.0


# --------------------------------------------------------------------------------------------
# Episodes
# --------------------------------------------------------------------------------------------



def play(runner: Runner, station: SimStation, goals, out_dir: str | None = None,
         prefix: str = "episode", throw_delay_s: float = 0.3, finish_s: float = 3.0,
         throws=None, poses=None, sync_launch: bool = False) -> list[Episode]:
    """One episode per goal [N, 2], as Runner.run_episodes (move home, throw, run, save
    `<prefix>_<i:04d>`; stop if the runner ends in HOLD), with each episode completed by the
    station's events before it is saved. A throw that never reached the robot (NoBallError)
    disarms and moves on to the next goal.

    throws: N launches (SimStation.throw_in's `throw`) instead of sampled ones; poses [N, 8]:
    each episode's start pose (Runner.move_home); sync_launch: each episode starts at the
    launch time the station announces (Runner.run_episode's t_start), not on the ball trigger."""
    return runner.run_episodes(goals, out_dir, prefix=prefix, poses=poses,
                               **station_hooks(runner, station, throw_delay_s, finish_s, throws,
                                               sync_launch).episode_callbacks())


def station_hooks(runner: Runner, station: SimStation, throw_delay_s: float = 0.3, finish_s: float = 3.0,
                  throws=None, sync_launch: bool = False, summary=None) -> StationHooks:
    """The simulated station's part of each episode (play's arguments): episode i's throw
    launched throw_delay_s after it is armed, the episode completed with the throw's events,
    a ball that never came disarmed and finished."""
    def armed(i):
        t_launch = station.throw_in(throw_delay_s, None if throws is None else throws[i])
        return t_launch if sync_launch else None

    def no_ball(i):
        runner.disarm()
        station.finish_throw(finish_s)

    def complete(i, ep):
        ev = station.finish_throw(finish_s)
        return with_truth(complete_episode(ep, ev, runner.contract), station)

    return StationHooks(armed=armed, no_ball=no_ball, summary=summary, complete=complete)


def with_truth(ep: Episode, station: SimStation) -> Episode:
    """The episode with the station's true ball among its runner arrays, named apart from the
    tracker's samples (`ball_t`, `ball_xyz`, `ball_used_*`) and from what the policy saw (the
    record's `obs`): `true_ball_t` [P] and `true_ball_xyz` [P, 3], the ball's centre (table frame,
    m) at its launch and after every physics step until the throw was over (landing included);
    `true_ball_pos` [T, 3], that centre at each tick's `t_grid` (linear between physics steps;
    NaN for a tick outside the throw). Call after the throw is finished (finish_throw)."""
    t, xyz = station.true_ball()
    grid = np.asarray(ep.extras["t_grid"], np.float64)
    at = np.full(grid.shape + (3,), np.nan)
    if len(t):
        inside = np.isfinite(grid) & (grid >= t[0] - 1e-12) & (grid <= t[-1] + 1e-12)
        at[inside] = np.stack([np.interp(grid[inside], t, xyz[:, k]) for k in range(3)], -1)
    return Episode(ep.traj, {**ep.extras, "true_ball_t": t, "true_ball_xyz": xyz, "true_ball_pos": at}, ep.meta)


def command_safety(runner: Runner, station: SimStation) -> dict:
    """Every command sent, checked (deploy.robot.safety.count_violations) on the times it reached the
    station: against the contract's filtered limits (speed_margin x the speed limits), and
    against the robot's true speed limits (`violations_true_limits`, and `max_speed_fraction`:
    the fastest commanded change as a fraction of them), which is what the robot experienced."""
    t, q = station.robot.command_log()
    start = station.robot.true_at_send[0] if len(t) else None
    true_speed = np.asarray(runner.contract.max_speed, np.float64)
    speed_frac = 0.0
    if len(t) > 1:
        dt = np.minimum(np.diff(t), runner.limits.dt)[:, None]
        speed_frac = float(np.max(np.abs(np.diff(q, axis=0)) / np.maximum(true_speed * dt, 1e-12)))
    return {"violations": count_violations(runner.limits, t, q, start=start)._asdict(),
            "violations_true_limits": count_violations(runner.limits._replace(speed=true_speed), t, q,
                                                       start=start)._asdict(),
            "max_speed_fraction": speed_frac, "commands": int(len(t))}





def summarize(runner: Runner, station: SimStation, episodes: list[Episode], wall_s: float) -> dict:
    """The simulated station's fields of a session's summary (deploy.robot.session.run_session
    has the rest): goal metrics (goal_summary), command safety (command_safety), landings,
    latencies and simulated time.

    `violations` are all zero on a fake-time clock. With the runner's computation time charged
    (SimClock(charge_compute=True), `--charge-compute`) the runner's decision-to-send time (~0.1 ms
    of Python) can make two commands arrive slightly closer than the runner reckoned, which the
    strict rate check counts (< 1% over the margin); `violations_true_limits` must be zero and
    `max_speed_fraction` <= 1."""
    sim_s = station.time - station.t_origin
    return files.json_safe({
        "metrics": goal_summary(episodes), **command_safety(runner, station),
        "landings": [[float(x) for x in e.traj.landing[0]] for e in episodes],
        "latency_ms": latency_ms(episodes), "sim_s": float(sim_s),
        "realtime_factor": float(sim_s / wall_s) if wall_s > 0 else None,
    })


@dataclasses.dataclass
class Loaded:
    """An export verified and built once (deploy.robot.exported.load_export: manifest, hashes, contract,
    golden self-test) with its training world and timing record: what every session of
    `ttmjx robot run` and every point of `ttmjx robot sweep` plays."""
    policy_dir: str
    policy: object
    contract: Contract
    cfg: World
    timing: dict          # deploy.robot.timing_check.trained_timing: the contract's timing record


def load_for_station(policy_dir: str, distribution: str | None = None) -> Loaded:
    """Verify and build an export once (every check of load_export, then its timing record:
    an export without one is refused, TimingError)."""
    from deploy.robot.exported import export_world, load_export
    from deploy.robot.timing_check import trained_timing
    policy, contract = load_export(policy_dir)
    record = trained_timing(policy.contract_doc, policy_dir)
    cfg = export_world(policy.contract_doc)
    if distribution:
        cfg = cfg.with_throws(distribution)
    return Loaded(policy_dir, policy, contract, cfg, record)


def resolve_timing(loaded: Loaded, timing: str | Timing | None, allow_untrained: bool = False,
                   source: str | None = None) -> tuple[Timing, dict]:
    """(the station's Timing, the summary's `timing` object): None or 'export' plays the trained
    timing's centre, a name a TIMING_PROFILES profile, a Timing itself (`source` names it). A
    timing outside the trained ranges is a TimingError unless allow_untrained."""
    from deploy.robot.timing_check import check_station, station_timing
    if isinstance(timing, Timing):
        tm, src = timing, source or "given"
    else:
        tm, src = station_timing(loaded.timing, timing)
    return tm, check_station(loaded.timing, tm, src, allow_untrained)


def play_session(loaded: Loaded, goals, out_dir: str | None = None, seed: int = 0, realtime: bool = False,
                 charge_compute: bool = False, throw_delay_s: float = 0.3,
                 config: RunnerConfig = RunnerConfig(), timing: str | Timing | None = None,
                 sync_launch: bool = False, allow_untrained: bool = False,
                 timing_source: str | None = None) -> dict:
    """One session of a loaded export on a fresh simulated station (run_sim's work after the
    load). The policy is reset at every episode by the runner, so one build serves any number
    of sessions."""
    from deploy.robot.hardware import MonotonicClock
    tm, timing_info = resolve_timing(loaded, timing, allow_untrained, timing_source)
    goals = check_goals(goals)
    clock = MonotonicClock() if realtime else SimClock(charge_compute=charge_compute)
    station = SimStation(loaded.cfg, loaded.contract, clock=clock, seed=seed, timing=tm)
    runner = Runner(station.robot, station.tracker, clock, loaded.policy, loaded.contract, config, seed=seed)
    station.prefetch()

    def summary(episodes, wall_s):
        return {**summarize(runner, station, episodes, wall_s),
                "policy": loaded.policy_dir, "self_test_error": loaded.policy.self_test_error,
                "distribution": loaded.cfg.throws.name, "seed": seed,
                "timing": files.json_safe(timing_info),
                # each throw's (tracker latency, joint latency, command delay), s: drawn per throw
                # within the timing's spreads, or its fixed values
                "throw_delays_s": [list(d) for d in station.delays_log]}
    return run_session(runner, goals, out_dir, station_hooks(runner, station, throw_delay_s, sync_launch=sync_launch,
                                                             summary=summary))


def run_sim(policy_dir: str, goals, out_dir: str | None = None, seed: int = 0,
            distribution: str | None = None, realtime: bool = False, charge_compute: bool = False,
            throw_delay_s: float = 0.3, config: RunnerConfig = RunnerConfig(),
            timing: str | Timing | None = None, sync_launch: bool = False,
            allow_untrained: bool = False) -> dict:
    """Load an export (every check of deploy.robot.exported.load_export, and its timing record), build
    the simulated station in the export's World (throws from `distribution` if given) and play
    one episode per goal [N, 2] (sync_launch: as `play`); returns the summary (summarize), the
    export's self-test error and the session's `timing` (deploy.robot.timing_check.timing_summary).

    timing: None (or 'export'): the timing the policy was trained under, without its
    randomization; a TIMING profile name; or a Timing. A timing outside the trained ranges is
    refused (deploy.robot.timing_check.TimingError) unless allow_untrained, and the summary says so."""
    loaded = load_for_station(policy_dir, distribution)
    return play_session(loaded, goals, out_dir, seed=seed, realtime=realtime, charge_compute=charge_compute,
                        throw_delay_s=throw_delay_s, config=config, timing=timing, sync_launch=sync_launch,
                        allow_untrained=allow_untrained)
