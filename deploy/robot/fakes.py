"""Fake hardware with simple kinematics on fake time: the runner's test bench.

FakeClock advances only when the runner sleeps (plus optional jitter) or a test advances it, so
an episode runs in milliseconds. FakeRobot moves each joint toward its target at the joint's
true speed limit and reports feedback at 250 Hz; FakeTracker reports balls at 125 Hz on a
simple path (toward the robot, turning back at the robot's end). They implement
deploy.robot.hardware's Robot, BallTracker and Clock; the simulated station (MuJoCo C + thrower) will
implement the same interfaces.
"""
from __future__ import annotations

import bisect
import math

import numpy as np

from deploy.robot.contract import Contract
from ttmjx.world import observation


class FakeClock:
    """Fake time: sleep_until(t) jumps to t plus a random lateness in [0, jitter_s)."""

    def __init__(self, start: float = 0.0, jitter_s: float = 0.0, seed: int = 0):
        self.t, self.jitter_s = float(start), float(jitter_s)
        self.rng = np.random.default_rng(seed)
        self.sleeps = 0

    def now(self) -> float:
        return self.t

    def sleep_until(self, t: float) -> None:
        late = self.rng.uniform(0.0, self.jitter_s) if self.jitter_s > 0 else 0.0
        self.t = max(self.t, float(t)) + late
        self.sleeps += 1

    def advance(self, dt: float) -> None:
        """Let dt seconds pass (computation time)."""
        if dt < 0:
            raise ValueError(f"FakeClock.advance({dt}): time cannot go back")
        self.t += dt


class FakeRobot:
    """Speed-limited first-order joints: after a command each joint moves toward its target at
    its true max speed. Feedback is the joint state at the last 250 Hz sample time before
    now - latency_s. Every command is logged (time, target, true joints at that moment)."""

    def __init__(self, clock, contract: Contract, q0=None, latency_s: float = 0.002,
                 rate_hz: float = 250.0, keep: int = 64):
        self.clock, self.latency_s, self.rate_hz, self.keep = clock, latency_s, rate_hz, keep
        self.speed = np.asarray(contract.max_speed, np.float64)
        q0 = np.asarray(contract.home if q0 is None else q0, np.float64)
        # Segments: from time t_i the joints go from q_i toward target_i.
        self._t, self._q, self._target = [-math.inf], [q0.copy()], [q0.copy()]
        self.sent_t: list[float] = []
        self.sent_q: list[np.ndarray] = []
        self.true_at_send: list[np.ndarray] = []

    @property
    def max_sample_age_s(self) -> float:
        """The oldest the newest delivered sample gets by design: one period plus the latency
        (Runner refuses a stale bound below it)."""
        return self.latency_s + 1.0 / self.rate_hz

    def true_q(self, t: float) -> np.ndarray:
        """[8] the joints at time t (t no earlier than the oldest kept segment)."""
        i = max(bisect.bisect_right(self._t, t) - 1, 0)
        q, target = self._q[i], self._target[i]
        if self._t[i] == -math.inf:
            return target.copy()
        return q + np.clip(target - q, -self.speed * (t - self._t[i]), self.speed * (t - self._t[i]))

    def read(self) -> tuple[float, np.ndarray]:
        ts = math.floor((self.clock.now() - self.latency_s) * self.rate_hz) / self.rate_hz
        return ts, self.true_q(ts)

    def send(self, q) -> None:
        q = np.asarray(q, np.float64)
        if q.shape != (8,) or not np.all(np.isfinite(q)):
            raise ValueError(f"FakeRobot.send: expected 8 finite targets, got {q!r}")
        now = self.clock.now()
        here = self.true_q(now)
        self._t.append(now)
        self._q.append(here)
        self._target.append(q.copy())
        if len(self._t) > self.keep:
            del self._t[0], self._q[0], self._target[0]
        self.sent_t.append(now)
        self.sent_q.append(q.copy())
        self.true_at_send.append(here)

    def command_log(self) -> tuple[np.ndarray, np.ndarray]:
        """(times [N], targets [N, 8]) of every command sent."""
        return np.asarray(self.sent_t), np.asarray(self.sent_q).reshape(-1, 8)


class FakeTracker:
    """Balls on a simple path: launched at `pos` with velocity `vel` (x toward the robot), the
    ball bounces along at the table top's height, turns back at x = turn_x at half speed (as if
    returned), stops at x = 3 and stays visible for visible_s. Samples every 1/rate_hz s, delivered latency_s late."""

    def __init__(self, clock, rate_hz: float = 125.0, latency_s: float = 0.004,
                 table_z: float = 0.78, bounce_s: float = 0.5, turn_x: float = -1.5,
                 visible_s: float = 2.5, noise_m: float = 0.0, seed: int = 0):
        self.clock, self.rate_hz, self.latency_s = clock, rate_hz, latency_s
        self.table_z, self.bounce_s, self.turn_x, self.visible_s = table_z, bounce_s, turn_x, visible_s
        self.noise_m, self.rng = noise_m, np.random.default_rng(seed)
        self.throws: list[tuple[float, np.ndarray, np.ndarray]] = []
        self._next_k = math.floor((clock.now() - latency_s) * rate_hz) + 1

    @property
    def max_sample_age_s(self) -> float:
        """The oldest the newest delivered sample gets by design: one period plus the latency
        (Runner refuses a stale bound below it)."""
        return self.latency_s + 1.0 / self.rate_hz

    def throw(self, t_launch: float, pos=(1.75, 0.35, 0.95), vel=(-7.0, -0.3, 0.0)) -> None:
        self.throws.append((float(t_launch), np.asarray(pos, np.float64), np.asarray(vel, np.float64)))

    def throw_in(self, delay_s: float, **kw) -> None:
        self.throw(self.clock.now() + delay_s, **kw)

    def positions(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(visible [n] bool, xyz [n, 3]) of the ball at times t [n]."""
        t = np.asarray(t, np.float64)
        vis, xyz = np.zeros(len(t), bool), np.zeros((len(t), 3))
        for t_launch, pos, vel in self.throws:
            s = t - t_launch
            on = (s >= 0) & (s < self.visible_s)
            x = pos[0] + vel[0] * s
            # Returned at the robot's end at half speed, caught at the thrower's end.
            x = np.minimum(np.where(x < self.turn_x, self.turn_x + 0.5 * (self.turn_x - x), x), 3.0)
            y = pos[1] + vel[1] * s
            z = self.table_z + (pos[2] - self.table_z) * np.abs(np.cos(np.pi * s / self.bounce_s))
            xyz[on] = np.stack([x, y, z], -1)[on]
            vis |= on
        return vis, xyz

    def read(self) -> tuple[np.ndarray, np.ndarray]:
        k1 = math.floor((self.clock.now() - self.latency_s) * self.rate_hz)
        ks = np.arange(self._next_k, k1 + 1)
        self._next_k = max(self._next_k, k1 + 1)
        t = ks / self.rate_hz
        vis, xyz = self.positions(t)
        if self.noise_m > 0:
            xyz = xyz + self.rng.normal(0.0, self.noise_m, xyz.shape)
        return t[vis], xyz[vis]


class FollowBallPolicy:
    """A stateless scripted policy for dry runs: the gantry follows the ball across the table
    and the arm swings as the ball comes close. Actions are absolute joint targets [8]."""
    policy_hash = "scripted:follow-ball"

    def __init__(self, contract: Contract):
        self.home = np.asarray(contract.home, np.float64)

    def reset(self):
        return None

    def step(self, state, frame, frames):
        ball = observation.ball_pos(frame)
        a = self.home.copy()
        a[1] = np.clip(ball[1], -0.6, 0.6)
        a[2] = 0.8 * np.tanh(-ball[0] - 0.5)
        return state, a
