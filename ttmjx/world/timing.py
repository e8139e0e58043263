"""The sensor and actuation timing model (config.Timing) for ONE throw, in JAX.

The same rules as the simulated station and the robot runner (deploy/sim/station.py,
deploy/robot/runner.py, deploy/robot/interp.py), written once more here for the vectorized world; the
tests compare the two on the same throws (tests/test_timing.py).

Time is counted in physics steps from the episode's start (tick 0). Each control step appends
its S physics steps' joints and ball position to a history [H, 11]; a sensor's sample m is
taken at physics step phase + m * E (E steps per sample) and delivered `latency` (+ jitter)
later. At tick n (physics step j = n * S) the policy sees, per sensor, the line through the two
newest samples delivered by the time the runner reads them, evaluated at j and followed at most
`extrapolate_s` past the newest (then held).

Start. With a tracker rate the runner's episode starts at the ball's first tracker sample, so
the ball has flown `lead` physics steps (uniform in [0, E_ball)) when the episode starts; the
runner notices the ball once its second sample is delivered, jitter included (`trigger`), and the ticks before
that (n < n_exec) are logged but not executed: the robot holds. Their frames are read like the others, from the samples delivered by the trigger (the
runner may also interpolate toward a sample taken after the tick; the world, which has not
simulated it yet, extrapolates: equal while the robot holds still and the tick falls after the
ball's second sample, as at 100 Hz with a 125 Hz tracker).
Commands: command c_n (tick n) starts its ramp `delay` steps after j and ramps over S steps.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ttmjx.world import ballphysics
from ttmjx.world.config import World, physics_steps_per_sample

BALL, JOINT = 0, 1          # sensor ids in the per-sample random draws
CANDIDATES = 4              # newest samples considered per read at least (drops skip to older ones)


def candidates(cfg: World, every: int) -> int:
    """Samples considered per read: enough to reach back past the previous tick's read."""
    return max(CANDIDATES, -(-cfg.substeps // every) + 3)


class Draw(NamedTuple):
    """One episode's timing (physics steps unless said)."""
    ball_latency: jax.Array    # float32
    joint_latency: jax.Array   # float32
    action_delay: jax.Array    # float32
    joint_phase: jax.Array     # int32 in [0, E_joint)
    lead: jax.Array            # int32: steps the ball flew before tick 0, in [0, E_ball)
    trigger: jax.Array         # float32: when the runner notices the ball
    n_exec: jax.Array          # int32: first executed tick
    key: jax.Array             # per-sample jitter and drops


def steps_per_sample(cfg: World, name: str) -> int:
    """E: physics steps per sample of timing.tracker_hz or timing.joint_hz."""
    return physics_steps_per_sample(getattr(cfg.timing, name), cfg.physics_dt, f"timing.{name}")


def history_len(cfg: World) -> int:
    """H: physics steps of history a read can reach back (the longest delay, CANDIDATES samples,
    and one control step)."""
    reach = max((candidates(cfg, e) + 1) * e for e in (steps_per_sample(cfg, "tracker_hz"),
                                                         steps_per_sample(cfg, "joint_hz")))
    return int(math.ceil(cfg.timing.max_delay_s() / cfg.physics_dt)) + reach + cfg.substeps + 2


def command_len(cfg: World) -> int:
    """K: commands kept for the delayed ramps."""
    return int(math.ceil((cfg.timing.action_delay_s + cfg.timing.spreads()[2]) / cfg.control_dt)) + 2


def draw(cfg: World, key) -> Draw:
    """The timing of one episode: fixed delays plus the per-episode randomization."""
    tm, dt = cfg.timing, cfg.physics_dt
    k_extra, k_phase, k_lead, k_sample = jax.random.split(key, 4)
    r = jnp.array(tm.spreads(), jnp.float32)          # [ball, joints, commands]
    shift = (jax.random.uniform(k_extra, (3,), minval=-1.0, maxval=1.0) * r / dt if max(tm.spreads())
             else jnp.zeros(3))
    base = jnp.array([tm.tracker_latency_s, tm.joint_latency_s, tm.action_delay_s], jnp.float32) / dt
    delays = jnp.maximum(base + shift, 0.0)            # [ball, joints, commands] in physics steps
    eb, ej = steps_per_sample(cfg, "tracker_hz"), steps_per_sample(cfg, "joint_hz")
    ball_lat = delays[0]
    lead = jax.random.randint(k_lead, (), 0, eb) if tm.tracker_hz is not None else jnp.int32(0)
    # The runner notices the ball when its second sample is delivered: physics step E_ball, its
    # latency and its own jitter (the same per-sample draw `read` uses), or the next sample kept
    # if that one was dropped.
    trigger = trigger_step(cfg, eb, ball_lat, k_sample) if tm.tracker_hz is not None else jnp.float32(0.0)
    return Draw(ball_latency=ball_lat.astype(jnp.float32),
                joint_latency=delays[1].astype(jnp.float32), action_delay=delays[2].astype(jnp.float32),
                joint_phase=jax.random.randint(k_phase, (), 0, ej).astype(jnp.int32),
                lead=jnp.asarray(lead, jnp.int32), trigger=trigger.astype(jnp.float32),
                n_exec=jnp.ceil(trigger / cfg.substeps - 1e-6).astype(jnp.int32), key=k_sample)


def trigger_sample(cfg: World, key):
    """(m, its jitter in physics steps): the ball sample whose delivery fires the runner's trigger,
    the first kept one after the first (jitter and drops drawn as `read` draws them)."""
    tm = cfg.timing
    m = jnp.arange(1, CANDIDATES + 1, dtype=jnp.int32)
    jitter = _uniform(key, BALL, m, 0) * (tm.jitter_s / cfg.physics_dt) if tm.jitter_s else jnp.zeros(m.shape)
    kept = _uniform(key, BALL, m, 1) >= tm.drop_prob if tm.drop_prob else jnp.ones(m.shape, bool)
    i = jnp.argmax(kept)          # every candidate dropped: the first (a track that rare is not modelled)
    return m[i], jitter[i]


def trigger_step(cfg: World, every: int, latency, key):
    """When the runner notices the ball (physics steps from tick 0): the delivery of the trigger's
    sample (trigger_sample), taken at m * every and delivered latency + its jitter later, so the
    ticks before the trigger are read from exactly the samples the runner holds when it fires."""
    m, jitter = trigger_sample(cfg, key)
    return (m * every + latency + jitter).astype(jnp.float32)


def first_slope(cfg: World, pos, vel, spin, key):
    """[3] per physics step: the ball's line at tick 0 as the runner draws it, through the first
    sample (pos, at tick 0) and the trigger's sample `m * E_ball` steps later, which the runner
    holds when it reads tick 0 after the trigger (the world, at tick 0, has not simulated that
    sample yet, so it flies the ball there: free flight, far from the robot)."""
    every = steps_per_sample(cfg, "tracker_hz")
    m, _ = trigger_sample(cfg, key)
    later, _ = fly(cfg, pos, vel, spin, m * every)
    return (later - pos) / (m * every).astype(jnp.float32)


def fly(cfg: World, pos, vel, spin, steps):
    """Ball position and velocity [3] after `steps` (traced int, < 64) physics steps of free
    flight (semi-implicit Euler, as MuJoCo integrates); spin is kept."""
    def one(i, pv):
        p, v = pv
        a = ballphysics.ball_acceleration(v, spin, cfg.ball)
        v_new = jnp.where(i < steps, v + a * cfg.physics_dt, v)
        return jnp.where(i < steps, p + v_new * cfg.physics_dt, p), v_new
    return jax.lax.fori_loop(0, 64, one, (pos, vel))


def _uniform(key, sensor: int, m, salt: int):
    """A uniform draw per (sensor, sample index m [C], salt): the same sample always draws the same."""
    k = jax.random.fold_in(jax.random.fold_in(key, sensor * 2 + salt), 0)
    return jax.vmap(lambda mi: jax.random.uniform(jax.random.fold_in(k, mi)))(m + (1 << 20))


def read(cfg: World, hist, j_now, avail, latency, every: int, phase, m_min, key, sensor: int,
         prev_avail=None):
    """What a sensor shows at tick time j_now, read at time `avail` (>= j_now).

    hist [H, d]: the signal at physics steps j_now - H + 1 .. j_now. Returns (value [d], slope [d]
    per physics step). Samples later than j_now are not used (the world has not simulated them).
    prev_avail: for a sensor read as "the newest sample" once per tick (the runner's
    Robot.read), the previous read's time: the line's older sample is the newest delivered by
    then (if older than the newest now), not the sample just before the newest."""
    tm = cfg.timing
    h, c = hist.shape[0], candidates(cfg, every)
    newest = jnp.floor((jnp.minimum(avail - latency, j_now) - phase) / every).astype(jnp.int32)
    m = newest - jnp.arange(c, dtype=jnp.int32)                               # [C], newest first
    j = phase + m * every
    jitter = _uniform(key, sensor, m, 0) * (tm.jitter_s / cfg.physics_dt) if tm.jitter_s else 0.0
    kept = _uniform(key, sensor, m, 1) >= tm.drop_prob if tm.drop_prob else jnp.ones(c, bool)
    ok = kept & (j + latency + jitter <= avail) & (m >= m_min)
    i1 = jnp.argmax(ok)
    older = ok & (jnp.arange(c) > i1)
    if prev_avail is not None:
        seen = older & (j + latency + jitter <= prev_avail)
        older = jnp.where(seen.any(), seen, older)
    i0 = jnp.argmax(older)
    at = lambda jj: hist[jnp.clip(h - 1 - (j_now - jj), 0, h - 1)]  # noqa: E731
    x1, x0 = at(j[i1]), at(j[i0])
    span = jnp.maximum(j[i1] - j[i0], 1).astype(jnp.float32)
    slope = jnp.where(older.any(), (x1 - x0) / span, 0.0)
    t_eval = jnp.minimum(j_now.astype(jnp.float32), j[i1] + tm.extrapolate_s / cfg.physics_dt)
    line = jnp.where(older.any(), x0 + slope * (t_eval - j[i0]), x1)
    # No sample delivered at all (every candidate dropped): the oldest candidate, held.
    value = jnp.where(ok.any(), line, at(j[-1]))
    return value, slope


def substep_targets(cfg: World, cmds, n, delay):
    """[S, 8] joint targets at the end of each physics step of tick n.

    cmds [K, 8]: the commands of ticks n-K+1 .. n (older entries: the initial target). Command
    c_m ramps from c_{m-1} to c_m over S steps starting `delay` steps after tick m."""
    s, k = cfg.substeps, cmds.shape[0]
    tau = n * s + jnp.arange(1, s + 1, dtype=jnp.float32)
    u = (tau - delay) / s
    m = jnp.ceil(u).astype(jnp.int32) - 1
    w = (u - m)[:, None]
    idx = lambda mm: jnp.clip(k - 1 - (n - mm), 0, k - 1)  # noqa: E731
    c_m, c_prev = cmds[idx(m)], cmds[idx(m - 1)]
    return c_prev + w * (c_m - c_prev)
