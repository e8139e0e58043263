"""The task for ONE throw, as pure functions of an immutable state (batched by vmap).

The physics lives in ttmjx/world/backends.py (MJX or MuJoCo C); everything here is identical for
both: command clipping, events detected from the ball's per-physics-step state, observation
and frame stack. Events come from the ball alone (plus the paddle's position, a sensor), so
the two backends give the same events from the same motion:

* a contact is a physics step whose ball velocity change is not free flight (gravity + air);
* it is the paddle's if the ball is within reach of the blade, else the net's if the ball is at
  the net, else the table's.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx.world import ballphysics, goalfile, observation, timing
from ttmjx.world.config import Table, World
from ttmjx.world.goals import goals_from_unit

# A velocity change this far from free flight within one physics step is a contact. Free-flight
# changes are < 0.02 m/s per 1 ms step (gravity 0.0098, air < 0.01); the lightest contacts that
# matter (a table bounce at 1 m/s normal speed, COR 0.9) change velocity by > 0.1 m/s per step.
CONTACT_DV = 0.05


def net_zone(cfg: World) -> float:
    """|x| (m) within which a contact low enough is the net's, not the table's (contact_kinds):
    a ball bouncing on the table this close to the net touches it."""
    return cfg.table.net_thickness / 2 + cfg.ball.radius + 0.01


class Events(NamedTuple):
    """Per-throw events (scalars)."""
    hit: jax.Array            # bool: paddle touched the ball
    hit_step: jax.Array       # int32: control step of the first paddle contact, -1 if none
    bounce_own: jax.Array     # bool: bounced on the robot's half before the hit
    net: jax.Array            # bool: touched the net
    landed: jax.Array         # bool: landing point defined (table contact or fall after the hit)
    landing: jax.Array        # [2] landing (x, y); NaN until landed
    on_opponent: jax.Array    # bool: first table contact after the hit was on the opponent's half
    done: jax.Array           # bool: episode over (landed, fell below the table, time limit)
    done_step: jax.Array      # int32: control step at which the episode ended, -1 while running


class Obs(NamedTuple):
    """What a policy sees at one control step (one throw)."""
    frame: jax.Array      # [O] joints (8), ball position (3), [ball velocity (3)], goal (2)
    ball_vel: jax.Array   # [3]
    frames: jax.Array     # [k, O] frame stack, oldest first
    t: jax.Array          # int32 control step


class State(NamedTuple):
    """Immutable per-throw state."""
    qpos: jax.Array       # [nq]
    qvel: jax.Array       # [nv]
    target: jax.Array     # [8] last commanded joint targets
    goal: jax.Array       # [2]
    t: jax.Array          # int32 control steps taken
    events: Events
    frames: jax.Array     # [k, O] frame stack of observations up to now
    aim: jax.Array        # [2] thrower's aim (kept for the record)
    launch: jax.Array     # [9] launch position, velocity, spin (kept for the record)
    hist: jax.Array       # [H, 11] joints and ball position per physics step ([1, 11] if timing is ideal)
    cmds: jax.Array       # [K, 8] the last K commands, newest last ([1, 8] if timing is ideal)
    timing: timing.Draw   # this episode's sensor and actuation timing (ttmjx.world.timing)


class Policy(NamedTuple):
    """Anything that acts in the task, for ONE throw (batched by vmap): the trained networks
    (models.policy), the scripted striker, the ES policy, a hold policy."""
    init: Callable      # (params, key) -> carry
    apply: Callable     # (params, carry, Obs, key) -> (carry, action [8] joint targets)


class Layout(NamedTuple):
    """Static qpos/qvel addresses (from the MuJoCo model, looked up by name once)."""
    ball_qpos: int
    ball_qvel: int
    robot_qpos: tuple
    robot_qvel: tuple
    qpos0: tuple


def layout(m) -> Layout:
    from ttmjx.world import scene
    i = scene.ids(m)
    return Layout(i.ball_qpos, i.ball_qvel, tuple(int(x) for x in i.robot_qpos),
                  tuple(int(x) for x in i.robot_qvel), tuple(float(x) for x in m.qpos0))


def no_events() -> Events:
    f = jnp.array(False)
    return Events(hit=f, hit_step=jnp.int32(-1), bounce_own=f, net=f, landed=f,
                  landing=jnp.full(2, jnp.nan, jnp.float32), on_opponent=f, done=f,
                  done_step=jnp.int32(-1))


def frame(cfg: World, lay: Layout, qpos, qvel, goal):
    """[O] observation frame (ttmjx.world.observation): joints, ball position, [ball velocity], goal."""
    vel = qvel[lay.ball_qvel:lay.ball_qvel + 3] if cfg.ball_velocity_obs else None
    return observation.make_frame(qpos[jnp.array(lay.robot_qpos)], qpos[lay.ball_qpos:lay.ball_qpos + 3],
                                  goal, vel, xp=jnp).astype(jnp.float32)


def home_pose(cfg: World, key):
    """[8] home pose with a small uniform perturbation, inside the joint ranges."""
    r = cfg.robot
    noise = jax.random.uniform(key, (8,), minval=-1.0, maxval=1.0) * jnp.array(r.home_noise)
    return jnp.clip(jnp.array(r.home) + noise, jnp.array(r.lower), jnp.array(r.upper))


def timing_key(key):
    """The key of an episode's timing draw, from its reset key (folded in: the home pose keeps
    the reset key itself, so adding the timing model changed no ideal-timing rollout)."""
    return jax.random.fold_in(key, 7)


def reset(cfg: World, lay: Layout, key, launch_pos, launch_vel, launch_spin, aim, goal) -> State:
    """State at the episode's start: robot near home, ball at the thrower with its velocity (with
    a tracker rate, `lead` physics steps of free flight later: the first tracker sample)."""
    joints = home_pose(cfg, key)
    draw = timing.draw(cfg, timing_key(key))
    pos, vel = launch_pos, launch_vel
    if not cfg.timing.ideal:
        pos, vel = timing.fly(cfg, launch_pos, launch_vel, launch_spin, draw.lead)
    qpos = jnp.array(lay.qpos0, jnp.float32)
    qpos = qpos.at[jnp.array(lay.robot_qpos)].set(joints)
    qpos = qpos.at[lay.ball_qpos:lay.ball_qpos + 7].set(
        jnp.concatenate([pos, jnp.array([1.0, 0.0, 0.0, 0.0])]))
    nv = len(lay.qpos0) - 1  # one free joint: nq = nv + 1
    qvel = jnp.zeros(nv, jnp.float32)
    # Identity orientation at launch, so the local angular velocity equals the world spin.
    qvel = qvel.at[lay.ball_qvel:lay.ball_qvel + 6].set(jnp.concatenate([vel, launch_spin]))
    f0 = frame(cfg, lay, qpos, qvel, goal)
    h, k = (1, 1) if cfg.timing.ideal else (timing.history_len(cfg), timing.command_len(cfg))
    row = jnp.concatenate([joints, pos]).astype(jnp.float32)
    state = State(qpos=qpos, qvel=qvel, target=joints, goal=jnp.asarray(goal, jnp.float32),
                  t=jnp.int32(0), events=no_events(),
                  frames=jnp.broadcast_to(f0, (cfg.frame_stack, f0.shape[0])),
                  aim=jnp.asarray(aim, jnp.float32),
                  launch=jnp.concatenate([launch_pos, launch_vel, launch_spin]).astype(jnp.float32),
                  hist=jnp.broadcast_to(row, (h, 11)), cmds=jnp.broadcast_to(joints, (k, 8)), timing=draw)
    if cfg.timing.ideal:
        return state
    f0 = sensed_frame(cfg, state)
    if cfg.ball_velocity_obs and cfg.timing.tracker_hz is not None:
        # The runner reads tick 0 after its trigger, through the trigger's sample taken after the
        # tick: the line's slope, not the single sample's zero (the frame pads the whole stack).
        slope = timing.first_slope(cfg, pos, vel, launch_spin, draw.key)
        f0 = f0.at[observation.BALL_VEL].set(slope / cfg.physics_dt)
    return state._replace(frames=jnp.broadcast_to(f0, (cfg.frame_stack, f0.shape[0])))


def sensed_frame(cfg: World, state: State):
    """[O] the frame the policy sees at tick state.t under the timing model (state.hist holds the
    physics up to this tick): each sensor's samples delivered by the later of the tick and the
    runner's trigger (ttmjx.world.timing.read)."""
    d = state.timing
    s = cfg.substeps
    j_now = state.t * s
    avail = jnp.maximum(j_now.astype(jnp.float32), d.trigger)
    # The runner reads the newest joint sample once per tick (every 1 ms while it waits for the
    # ball, so up to the trigger its samples are dense); the ball tracker hands over every sample.
    prev = jnp.maximum((j_now - s).astype(jnp.float32), d.trigger)
    joints, _ = timing.read(cfg, state.hist[:, :8], j_now, avail, d.joint_latency,
                            timing.steps_per_sample(cfg, "joint_hz"), d.joint_phase, -(1 << 20), d.key,
                            timing.JOINT, prev_avail=prev)
    ball, slope = timing.read(cfg, state.hist[:, 8:], j_now, avail, d.ball_latency,
                              timing.steps_per_sample(cfg, "tracker_hz"), jnp.int32(0), 0, d.key, timing.BALL)
    vel = slope / cfg.physics_dt if cfg.ball_velocity_obs else None
    return observation.make_frame(joints, ball, state.goal, vel, xp=jnp).astype(jnp.float32)


def observe(cfg: World, lay: Layout, state: State) -> Obs:
    """What the policy sees; ball_vel is the frame's velocity (sensed) where it has one."""
    f = state.frames[-1]
    vel = f[observation.BALL_VEL] if cfg.ball_velocity_obs else state.qvel[lay.ball_qvel:lay.ball_qvel + 3]
    return Obs(frame=f, ball_vel=vel, frames=state.frames, t=state.t)


def command(cfg: World, state: State, action):
    """[8] joint targets actually sent: the action clipped to the joint ranges and to what the
    speed limits allow in one control step from the last target. Non-finite actions hold, and so
    does every action before the runner would act (timing: t < n_exec)."""
    r = cfg.robot
    action = jnp.where(jnp.isfinite(action), action, state.target)
    if not cfg.timing.ideal:
        action = jnp.where(state.t < state.timing.n_exec, state.target, action)
    target = jnp.clip(action, jnp.array(r.lower), jnp.array(r.upper))
    max_step = jnp.array(r.max_speed) * r.speed_margin * cfg.control_dt
    return state.target + jnp.clip(target - state.target, -max_step, max_step)


def contact_kinds(cfg: World, ball_prev, ball, paddle):
    """Classify each physics step of one control step.

    ball_prev: [6] ball position and velocity before the first physics step.
    ball: [S, 6] ball position and velocity after each physics step.
    paddle: [S, 3] blade centre at each physics step.
    Returns (contact [S] bool, kind [S] int32: 0 paddle, 1 net, 2 table).
    """
    t, r = cfg.table, cfg.ball.radius
    vel_before = jnp.concatenate([ball_prev[None, 3:], ball[:-1, 3:]])
    accel = jax.vmap(lambda v: ballphysics.ball_acceleration(v, jnp.zeros(3), cfg.ball))(vel_before)
    dv = ball[:, 3:] - vel_before - accel * cfg.physics_dt
    contact = jnp.linalg.norm(dv, axis=-1) > CONTACT_DV
    pos = ball[:, :3]
    reach = float(np.hypot(*cfg.robot.blade_half_size)) + r + 0.03
    near_paddle = jnp.linalg.norm(pos - paddle, axis=-1) < reach
    near_net = (jnp.abs(pos[:, 0]) < net_zone(cfg)) & (pos[:, 2] < t.top_z + t.net_height + r + 0.01)
    kind = jnp.where(near_paddle, 0, jnp.where(near_net, 1, 2)).astype(jnp.int32)
    return contact, kind


def update_events(cfg: World, ev: Events, t, ball_prev, ball, paddle) -> Events:
    """Fold one control step's physics steps into the events (in time order).

    t: int32 control step index of this step; shapes as in contact_kinds.
    """
    tab = cfg.table
    contact, kind = contact_kinds(cfg, ball_prev, ball, paddle)
    prev_pos = jnp.concatenate([ball_prev[None, :3], ball[:-1, :3]])
    height = tab.top_z + cfg.ball.radius

    def one(ev: Events, xs):
        c, k, pos, ppos = xs
        live = ~ev.done
        is_hit = live & c & (k == 0)
        is_table = live & c & (k == 2)
        first_hit = is_hit & ~ev.hit
        own_bounce = is_table & ~ev.hit & (pos[0] < 0)
        land = is_table & ev.hit & ~ev.landed
        # A hit ball that misses the table: where it falls through table height outside the
        # table's footprint (inside it, the table contact itself is the landing).
        off_table = (jnp.abs(pos[0]) > tab.half_length) | (jnp.abs(pos[1]) > tab.half_width)
        crossing = live & ev.hit & ~ev.landed & (ppos[2] >= height) & (pos[2] < height) & off_table & ~is_table
        frac = jnp.clip((ppos[2] - height) / jnp.maximum(ppos[2] - pos[2], 1e-9), 0.0, 1.0)
        cross_xy = ppos[:2] + frac * (pos[:2] - ppos[:2])
        new_landed = land | crossing
        landing = jnp.where(land, pos[:2], jnp.where(crossing, cross_xy, ev.landing))
        fell = live & (pos[2] < tab.top_z - 0.05)
        done_now = live & (new_landed | fell)
        ev = Events(
            hit=ev.hit | is_hit,
            hit_step=jnp.where(first_hit, t, ev.hit_step),
            bounce_own=ev.bounce_own | own_bounce,
            net=ev.net | (live & c & (k == 1)),
            landed=ev.landed | new_landed,
            landing=landing.astype(jnp.float32),
            on_opponent=ev.on_opponent | (land & (pos[0] > 0)),
            done=ev.done | done_now,
            done_step=jnp.where(done_now, t, ev.done_step),
        )
        return ev, None

    ev, _ = jax.lax.scan(one, ev, (contact, kind, ball[:, :3], prev_pos))
    return ev


def controls(cfg: World, state: State, target):
    """The physics' targets for this control step: ([S, 8] per physics step, the command history
    to keep). Ideal timing: the ramp from the last target to `target` (ttmjx.world.backends)."""
    if cfg.timing.ideal:
        return None, state.cmds
    cmds = jnp.concatenate([state.cmds[1:], target[None]])
    return timing.substep_targets(cfg, cmds, state.t, state.timing.action_delay), cmds


def advance(cfg: World, lay: Layout, state: State, target, qpos, qvel, ball, paddle, joints=None,
            cmds=None) -> State:
    """The state after one control step whose physics produced qpos, qvel and the per-physics-
    step ball [S, 6], paddle [S, 3] and joints [S, 8] tracks (joints and cmds, from controls(),
    are needed only with a timing model)."""
    ball_prev = jnp.concatenate([state.qpos[lay.ball_qpos:lay.ball_qpos + 3],
                                 state.qvel[lay.ball_qvel:lay.ball_qvel + 3]])
    ev = update_events(cfg, state.events, state.t, ball_prev, ball, paddle)
    timeout = ~ev.done & (state.t + 1 >= cfg.horizon)
    ev = ev._replace(done=ev.done | timeout, done_step=jnp.where(timeout, state.t, ev.done_step))
    if cfg.timing.ideal:
        f = frame(cfg, lay, qpos, qvel, state.goal)
        frames = jnp.concatenate([state.frames[1:], f[None]])
        return state._replace(qpos=qpos.astype(jnp.float32), qvel=qvel.astype(jnp.float32),
                              target=target, t=state.t + 1, events=ev, frames=frames)
    rows = jnp.concatenate([joints, ball[:, :3]], axis=-1).astype(jnp.float32)
    hist = jnp.concatenate([state.hist[rows.shape[0]:], rows])
    state = state._replace(qpos=qpos.astype(jnp.float32), qvel=qvel.astype(jnp.float32), target=target,
                           t=state.t + 1, events=ev, hist=hist, cmds=cmds)
    f = sensed_frame(cfg, state)
    return state._replace(frames=jnp.concatenate([state.frames[1:], f[None]]))


def uniform_goals(key, n: int, table: Table, margin: float = 0.0):
    """[n, 2] goals uniform over the opponent's half (extended by `margin`, goals_from_unit) from a
    JAX key (jittable; n static): the draw practice and evaluation share; evaluation keeps
    margin=0 (goals on the table)."""
    return goals_from_unit(jax.random.uniform(key, (n, 2)), table, jnp, margin)


def check_goals(goals, n: int | None = None) -> np.ndarray:
    """[B, 2] finite float32 user goals (ttmjx.world.goalfile.check_goals; practice may aim beyond
    the table), one per throw when n is given; ValueError names the problem."""
    g = goalfile.check_goals(goals)
    if n is not None and g.shape[0] != n:
        raise ValueError(f"goals has {g.shape[0]} rows, expected one per throw ({n})")
    return g


def check_actions(actions, batch: int) -> np.ndarray:
    """Validate a batch of actions: [B, 8] finite. Raises ValueError naming the problem."""
    a = np.asarray(actions, dtype=np.float64)
    if a.shape != (batch, 8):
        raise ValueError(f"actions must have shape [{batch}, 8] (one target per joint), got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = np.argwhere(~np.isfinite(a))[0]
        raise ValueError(f"actions[{bad[0]}, {bad[1]}] = {a[tuple(bad)]} is not finite")
    return a.astype(np.float32)
