"""The scripted demonstrator: a model-based striker, a closed-loop policy of the observation.

It produces the paper's non-goal-directed bootstrap data ("Bootstrapping from non-goal-directed
data"): it hits the thrown ball and returns it to a RANDOM point of the opponent's half, drawn
per episode; the commanded goal in the observation is ignored. Every control step it

1. estimates the ball's spin from the observed velocity change (the air model's residual is the
   Magnus force; the observation has no spin), and notes the ball's own-half bounce;
2. predicts the ball's flight with the world's air model (`ballphysics`) and a table bounce
   model (`BallModel`), and picks the hit: where the ball, after its bounce, crosses the
   episode's hitting plane x = `hit_x`;
3. solves the stroke (Newton on the blade's face normal and its speed along it) so that the
   ball, after a paddle bounce model (`BallModel`), flies with drag and Magnus to the episode's
   landing target with the episode's net clearance;
4. solves the 8-DOF inverse kinematics (damped Gauss-Newton on `forward_kinematics`, written here
   in jnp from the chain in scene.py) for the blade centre at the hit with the stroke's normal
   and the episode's random blade roll, and the joint velocities that move the blade centre at
   the stroke's velocity;
5. moves a joint-space reference toward the plan: a cubic approach to a back-swing pose, a
   constant-acceleration strike that passes the hit pose at the hit time with the hit velocity,
   then a decelerating follow-through; the command adds the position servo's velocity and
   acceleration feed-forward and respects the joint ranges and speed limits.

Per-episode randomness (drawn in `init`): landing target, net clearance, hitting plane, blade roll
and face, strike duration, and "perturb 4 of the 8 joints" (as in the paper): a constant offset
on the commands of 4 random joints and a random posture preference for the same 4 joints (which
only moves the robot within the redundancy of the 8-DOF chain).

Pure jnp, no Python control flow on traced values: runs inside the MJX rollout and, jit-compiled
and vmapped, on the MuJoCo C backend.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx import backends, ballphysics
from ttmjx.config import World
from ttmjx.env import Obs

GRAVITY = 9.81

# The arm's chain (scene.py, from the public ABB IRB 120 URDF): the offset of each body from its
# parent, in the parent's frame, for link2 .. link6; link1 sits base_z above the gantry carriage.
_LINK_OFFSETS = ((0.0, 0.0, 0.29), (0.0, 0.0, 0.27), (0.0, 0.0, 0.07), (0.302, 0.0, 0.0),
                 (0.072, 0.0, 0.0))


@dataclasses.dataclass(frozen=True)
class BallModel:
    """The ball's contacts as the striker models them (measured on the MuJoCo scene at 1 ms).

    A bounce reverses the normal relative velocity times the restitution, and removes `grip` of
    the slip velocity of the ball's contact point (a short, stick-limited friction impulse),
    which spins the (hollow) ball: dw = -(3 / 2r) n x dv_t. The paddle's restitution varies
    0.72-0.97 with where in a physics step the contact starts; the value here is what
    strikes measured (0.76 +- 0.02).
    """
    table_restitution: float = 0.89
    table_grip: float = 0.08
    paddle_restitution: float = 0.76
    paddle_grip: float = 0.13


@dataclasses.dataclass(frozen=True)
class StrikerConfig:
    """The striker's plan and its per-episode randomization (uniform ranges)."""
    # Where the returned ball should land (opponent's half, margins from the edges and the net).
    target_x: tuple = (0.25, 1.17)
    target_y: tuple = (-0.6, 0.6)
    # The return's ball-centre height above the net tape where it crosses the net (drag-free plan).
    net_clearance: tuple = (0.10, 0.40)
    min_clearance: float = 0.05     # lowered down to this when the episode's time runs short
    # The hitting plane: the ball is struck, after its bounce, where it crosses x = hit_x.
    hit_x: tuple = (-1.62, -1.42)
    # Blade roll: the angle of the extension (link6 x) in the blade plane from "pointing down"
    # (positive toward +y); the hit's y adds roll_per_y (deg/m) so that the blade reaches out
    # sideways toward a wide ball, the result clipped to roll_deg.
    roll_deg: tuple = (-80.0, 80.0)
    roll_per_y: float = 90.0
    # Posture: the gantry carriage this far behind the hit, and following this fraction of its y.
    reach_x: float = 0.45
    gantry_follow_y: float = 0.7
    # Strike: constant acceleration from rest over this time up to the hit; then a follow-through.
    strike_s: tuple = (0.12, 0.2)
    hold_s: float = 0.02          # the hit velocity is held this long before and after the hit
    follow_s: float = 0.08        # then decays with this time constant
    # Extra command lead over the servo's velocity feed-forward (coupling and the real inertia
    # lag the ideal servo a little).
    servo_lead_s: float = 0.0
    # Joint speeds the plan may use, as a fraction of the speed limits.
    hit_speed_frac: float = 0.7
    approach_speed_frac: float = 0.9
    # "Perturb 4 of the 8 joints": constant command offsets (m, rad) on `perturb_joints` random
    # joints, and the same joints' posture preference offsets (null-space only).
    perturb_joints: int = 4
    perturb: tuple = (0.01, 0.01, 0.02, 0.02, 0.02, 0.03, 0.03, 0.03)
    posture: tuple = (0.08, 0.15, 0.25, 0.15, 0.15, 0.4, 0.2, 0.4)
    # Numerics.
    predict_dt: float = 0.01
    predict_s: float = 1.25
    return_steps: int = 16
    newton_iters: int = 2
    ik_iters: int = 3
    ik_init_iters: int = 30
    model: BallModel = BallModel()


class StrikerState(NamedTuple):
    """The striker's carry for one throw."""
    # per-episode draws
    target: jax.Array       # [2] landing target (x, y)
    clearance: jax.Array    # () net clearance of the return (m)
    hit_x: jax.Array        # () hitting plane
    roll: jax.Array         # () blade roll (rad)
    face: jax.Array         # () +1 / -1: which side of the blade hits
    strike_s: jax.Array     # () strike duration (s)
    offset: jax.Array       # [8] command offsets
    posture_offset: jax.Array  # [8] offset of the IK's posture preference
    # plan
    t_hit: jax.Array        # () predicted hit time (s since launch)
    p_hit: jax.Array        # [3] ball centre at the hit
    theta: jax.Array        # [3] stroke: face normal yaw, pitch (rad), blade speed along it (m/s)
    q_hit: jax.Array        # [8] joints at the hit
    qd_hit: jax.Array       # [8] joint velocities at the hit
    # reference and command
    q_ref: jax.Array        # [8]
    v_ref: jax.Array        # [8]
    u_prev: jax.Array       # [8] last command
    # ball tracking
    v_prev: jax.Array       # [3] ball velocity at the last step
    spin: jax.Array         # [3] estimated spin (world, rad/s)
    bounced: jax.Array      # bool: the ball bounced on the robot's half
    struck: jax.Array       # bool: the strike is over (hit time passed or the ball returns)


# ----------------------------------------------------------------------------------------------
# Kinematics
# ----------------------------------------------------------------------------------------------

def _rot(axis: int, a):
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    if axis == 0:
        rows = ((o, z, z), (z, c, -s), (z, s, c))
    elif axis == 1:
        rows = ((c, z, s), (z, o, z), (-s, z, c))
    else:
        rows = ((c, -s, z), (s, c, z), (z, z, o))
    return jnp.stack([jnp.stack(r) for r in rows])


def forward_kinematics(cfg: World, q):
    """Blade centre [3] (the "paddle" site) and link6's rotation [3, 3] (columns: extension
    direction x, blade y, face normal z) for joints q [8] (JOINT_NAMES order)."""
    r = cfg.robot
    p = jnp.stack([r.base_x + q[0], r.base_y + q[1], jnp.asarray(r.base_z, q.dtype)])
    rot = _rot(2, q[2])
    for off, axis, qi in zip(_LINK_OFFSETS, (1, 1, 0, 1, 0), (q[3], q[4], q[5], q[6], q[7])):
        p = p + rot @ jnp.array(off, q.dtype)
        rot = rot @ _rot(axis, qi)
    blade = p + rot[:, 0] * (r.extension + r.blade_half_size[0])
    return blade, rot


def _limits(cfg: World, margin: float = 0.0):
    lo, hi = jnp.array(cfg.robot.lower), jnp.array(cfg.robot.upper)
    m = margin * (hi - lo)
    return lo + m, hi - m


# Per-joint regularization of the IK step (gantry in m, arm in rad): keeps the steps well posed
# and the heavy gantry quiet when the arm can do the job.
_IK_DAMPING = jnp.array([0.05, 0.05, 0.01, 0.01, 0.01, 0.01, 0.01, 0.01])
_IK_POSTURE = jnp.array([2e-3, 2e-3, 2e-4, 2e-4, 2e-4, 2e-4, 2e-4, 2e-4])
_W_NORMAL, _W_ROLL = 0.4, 0.1    # m per unit direction error: the normal matters, the roll less


# Room the IK leaves at each joint's limits for the back-swing and the follow-through (m, rad).
_SWING_ROOM = (0.03, 0.05, 0.3, 0.3, 0.3, 0.4, 0.35, 0.5)


def solve_ik(cfg: World, q, pos, normal, ext, q_pref, iters: int):
    """Damped Gauss-Newton: joints [8] putting the blade centre at pos [3] with link6's z axis
    along normal [3] and its x axis near ext [3], preferring q_pref [8]; starts from q. The
    joints stay `_SWING_ROOM` inside their limits."""
    lo, hi = _limits(cfg)
    lo, hi = lo + jnp.array(_SWING_ROOM), hi - jnp.array(_SWING_ROOM)

    def residual(qq):
        p, rot = forward_kinematics(cfg, qq)
        return jnp.concatenate([p - pos, _W_NORMAL * (rot[:, 2] - normal), _W_ROLL * (rot[:, 0] - ext)])

    def step(_, qq):
        r = residual(qq)
        jac = jax.jacfwd(residual)(qq)
        a = jac.T @ jac + jnp.diag(_IK_DAMPING + _IK_POSTURE)
        b = jac.T @ r + _IK_POSTURE * (qq - q_pref)
        dq = -jnp.linalg.solve(a, b)
        return jnp.clip(qq + jnp.clip(dq, -0.5, 0.5), lo, hi)

    return jax.lax.fori_loop(0, iters, step, q)


def blade_joint_velocity(cfg: World, q, vel, speed_frac: float):
    """Joint velocities [8] moving the blade centre at vel [3] with the least speed relative to
    the limits (the gantry counted 3x), scaled down as a whole to stay within speed_frac of them."""
    vmax = jnp.array(cfg.robot.max_speed)
    w = (vmax / jnp.array([3.0, 3.0, 1, 1, 1, 1, 1, 1])) ** 2      # inverse cost
    jac = jax.jacfwd(lambda qq: forward_kinematics(cfg, qq)[0])(q)   # [3, 8]
    jw = jac * w[None, :]
    qd = jw.T @ jnp.linalg.solve(jw @ jac.T + 1e-4 * jnp.eye(3), vel)
    scale = jnp.minimum(1.0, jnp.min(speed_frac * vmax / jnp.maximum(jnp.abs(qd), 1e-9)))
    return qd * scale


# ----------------------------------------------------------------------------------------------
# Ball model
# ----------------------------------------------------------------------------------------------

def _accel(cfg: World, v, w):
    return ballphysics.ball_acceleration(v, w, cfg.ball, GRAVITY)


def _spin_decay(cfg: World, w):
    _, torque = ballphysics.air_force_torque(jnp.zeros(3, w.dtype), w, cfg.ball)
    return torque / cfg.ball.hollow_inertia


def _flight_step(cfg: World, p, v, w, dt):
    """One midpoint (RK2) step of free flight: (p, v, w) after dt."""
    a1 = _accel(cfg, v, w)
    vm = v + 0.5 * dt * a1
    a2 = _accel(cfg, vm, w)
    return p + dt * vm, v + dt * a2, w + dt * _spin_decay(cfg, w)


def bounce(v, w, normal, surface_vel, restitution, grip, radius):
    """Ball velocity and spin after a bounce on a surface with unit normal (pointing toward the
    ball) moving at surface_vel [3] (BallModel)."""
    rel = v - surface_vel
    rel_n = jnp.dot(rel, normal) * normal
    rel_t = rel - rel_n
    slip = rel_t - radius * jnp.cross(w, normal)
    dv_t = -grip * slip
    v_out = surface_vel - restitution * rel_n + rel_t + dv_t
    w_out = w - (1.5 / radius) * jnp.cross(normal, dv_t)
    return v_out, w_out


def predict(cfg: World, scfg: StrikerConfig, p, v, w, bounced):
    """Ball states after each of n predict_dt steps: positions [n, 3], velocities [n, 3], spins
    [n, 3], and whether the ball has bounced on the robot's half by then [n] (bool)."""
    tab, b, mdl = cfg.table, cfg.ball, scfg.model
    h = tab.top_z + b.radius
    dt = scfg.predict_dt
    up = jnp.array([0.0, 0.0, 1.0])

    def step(c, _):
        p, v, w, bounced = c
        p1, v1, w1 = _flight_step(cfg, p, v, w, dt)
        on_table = (jnp.abs(p1[0]) <= tab.half_length) & (jnp.abs(p1[1]) <= tab.half_width)
        hit = (p1[2] < h) & (v1[2] < 0.0) & on_table
        vb, wb = bounce(v1, w1, up, jnp.zeros(3), mdl.table_restitution, mdl.table_grip, b.radius)
        p1 = jnp.where(hit, p1.at[2].set(2.0 * h - p1[2]), p1)
        v1, w1 = jnp.where(hit, vb, v1), jnp.where(hit, wb, w1)
        bounced = bounced | (hit & (p1[0] < 0.0))
        return (p1, v1, w1, bounced), (p1, v1, w1, bounced)

    n = int(math.ceil(scfg.predict_s / dt))
    _, out = jax.lax.scan(step, (p, v, w, bounced), None, length=n)
    return out


def estimate_spin(cfg: World, v_prev, v, dt):
    """Spin [3] (its part across the velocity) from the velocity change over dt: the residual of
    gravity and drag is the Magnus force, net of the added-mass term, k (w x v)."""
    b = cfg.ball
    vm = 0.5 * (v_prev + v)
    resid = (v - v_prev) / dt - _accel(cfg, vm, jnp.zeros(3, v.dtype))
    k = (b.magnus_coefficient - 0.5) * b.air_density * (4.0 / 3.0 * math.pi * b.radius**3) / b.mass
    return jnp.cross(vm, resid) / (k * jnp.maximum(jnp.dot(vm, vm), 1e-6)), resid


# ----------------------------------------------------------------------------------------------
# The stroke
# ----------------------------------------------------------------------------------------------

def _direction(yaw, pitch):
    return jnp.stack([jnp.cos(pitch) * jnp.cos(yaw), jnp.cos(pitch) * jnp.sin(yaw), jnp.sin(pitch)])


def return_time(cfg: World, p_hit, target, clearance):
    """Drag-free flight time (s) of a return from p_hit [3] landing at target [2] that crosses
    the net `clearance` above the tape."""
    tab, r = cfg.table, cfg.ball.radius
    z_land = tab.top_z + r
    h = tab.top_z + tab.net_height + r + clearance
    s = jnp.clip(-p_hit[0] / jnp.maximum(target[0] - p_hit[0], 1e-3), 0.05, 0.95)
    rise = jnp.maximum(h - p_hit[2] - s * (z_land - p_hit[2]), 0.01)
    return jnp.sqrt(2.0 * rise / (GRAVITY * s * (1.0 - s)))


def fly_for(cfg: World, p, v, w, duration, steps: int):
    """Ball position [3] after `duration` s of free flight (steps RK2 steps)."""
    dt = duration / steps

    def step(c, _):
        return _flight_step(cfg, *c, dt), None

    (p, _, _), _ = jax.lax.scan(step, (p, v, w), None, length=steps)
    return p


def stroke_guess(cfg: World, scfg: StrikerConfig, p_hit, v_in, target, duration):
    """[3] stroke (normal yaw, pitch, blade speed) of the drag-free, frictionless return."""
    z_land = cfg.table.top_z + cfg.ball.radius
    v_out = jnp.concatenate([(target - p_hit[:2]) / duration * 1.08,
                             ((z_land - p_hit[2]) / duration + 0.5 * GRAVITY * duration)[None]])
    n = v_out - v_in
    n = n / jnp.linalg.norm(n)
    e = scfg.model.paddle_restitution
    s = (jnp.dot(v_out, n) + e * jnp.dot(v_in, n)) / (1.0 + e)
    return jnp.stack([jnp.arctan2(n[1], n[0]), jnp.arcsin(jnp.clip(n[2], -1.0, 1.0)), s])


def solve_stroke(cfg: World, scfg: StrikerConfig, theta, p_hit, v_in, w_in, target, duration):
    """Newton on theta [3] so that the ball struck at p_hit lands on target [2] after duration."""
    mdl = scfg.model
    goal = jnp.concatenate([target, jnp.array([cfg.table.top_z + cfg.ball.radius])])

    def resid(th):
        n = _direction(th[0], th[1])
        v_out, w_out = bounce(v_in, w_in, n, th[2] * n, mdl.paddle_restitution, mdl.paddle_grip,
                              cfg.ball.radius)
        return fly_for(cfg, p_hit, v_out, w_out, duration, scfg.return_steps) - goal

    def step(_, th):
        r = resid(th)
        jac = jax.jacfwd(resid)(th)
        d = -jnp.linalg.solve(jac.T @ jac + 1e-4 * jnp.eye(3), jac.T @ r)
        return th + jnp.clip(d, jnp.array([-0.2, -0.2, -1.0]), jnp.array([0.2, 0.2, 1.0]))

    return jax.lax.fori_loop(0, scfg.newton_iters, step, theta)


def blade_frame(normal, roll, face):
    """Target link6 z [3] (face * normal) and x [3]: the extension rotated `roll` in the blade
    plane from its downward direction."""
    down = jnp.array([0.0, 0.0, -1.0]) - normal * (-normal[2])
    down = down / jnp.maximum(jnp.linalg.norm(down), 1e-6)
    side = jnp.cross(normal, down)
    return face * normal, jnp.cos(roll) * down + jnp.sin(roll) * side


# ----------------------------------------------------------------------------------------------
# Reference trajectory
# ----------------------------------------------------------------------------------------------

def hermite(q0, v0, q1, v1, span, tau):
    """Cubic Hermite from (q0, v0) to (q1, v1) over span, evaluated at tau in [0, span]:
    position, velocity, acceleration."""
    span = jnp.maximum(span, 1e-4)
    s = jnp.clip(tau / span, 0.0, 1.0)
    d = q1 - q0
    a0 = v0
    a2 = (3.0 * d / span - 2.0 * v0 - v1) / span
    a3 = (-2.0 * d / span + v0 + v1) / span**2
    t = s * span
    return (q0 + a0 * t + a2 * t**2 + a3 * t**3, a0 + 2 * a2 * t + 3 * a3 * t**2, 2 * a2 + 6 * a3 * t)


# ----------------------------------------------------------------------------------------------
# The policy
# ----------------------------------------------------------------------------------------------

def _uniform(key, lo_hi, shape=()):
    return jax.random.uniform(key, shape, minval=lo_hi[0], maxval=lo_hi[1])


def _nominal_hit(cfg: World):
    """A typical hit (ball centre) and incoming ball velocity, the plan before any prediction."""
    return jnp.array([-1.52, 0.0, 1.0]), jnp.array([-4.0, 0.0, 0.0])


def striker_policy(cfg: World, scfg: StrikerConfig = StrikerConfig()) -> backends.Policy:
    """The scripted demonstrator as a Policy for ONE throw (params unused, pass None)."""
    r, b = cfg.robot, cfg.ball
    dt = cfg.control_dt
    vmax = jnp.array(r.max_speed)
    lo, hi = _limits(cfg)
    lo_m, hi_m = _limits(cfg, 0.01)
    contact_offset = b.radius + r.blade_thickness / 2
    omega = r.servo_omega
    zeta = getattr(r, "servo_damping", 1.0)   # kv / kp = 2 zeta / omega (scene.py)

    def posture(p_hit, roll, face):
        """The IK's posture preference for a hit: gantry behind and partly under the ball, the
        forearm level and pointing forward, the wrist pitched so that the extension hangs down
        (j5 near 90 deg), then rolled sideways by j4 and the face chosen by j6."""
        gx = jnp.clip(p_hit[0] - scfg.reach_x - r.base_x, r.lower[0], r.upper[0])
        gy = jnp.clip(scfg.gantry_follow_y * (p_hit[1] - r.base_y), r.lower[1], r.upper[1])
        j6 = jnp.where(face > 0, 0.0, math.pi)
        return jnp.stack([gx, gy, 0.0, 0.2, -0.4, roll, 0.5 * math.pi - 0.3, j6])

    def roll_at(roll, p_hit):
        deg = math.pi / 180.0
        return jnp.clip(roll + scfg.roll_per_y * deg * (p_hit[1] - r.base_y),
                        scfg.roll_deg[0] * deg, scfg.roll_deg[1] * deg)

    def flight_time(p_hit, t_hit, target, clearance):
        """The return's flight time: from its net clearance, but landing within the episode."""
        t_left = cfg.episode_s - t_hit - 2 * dt
        t_min = return_time(cfg, p_hit, target, jnp.asarray(scfg.min_clearance))
        return jnp.maximum(jnp.minimum(return_time(cfg, p_hit, target, clearance), t_left), t_min)

    def plan_hit(carry: StrikerState, p, v, w, t_now):
        """(t_hit, p_hit, v_in, w_in, found) from the predicted flight."""
        ps, vs, ws, bs = predict(cfg, scfg, p, v, w, carry.bounced)
        ps = jnp.concatenate([p[None], ps])
        vs = jnp.concatenate([v[None], vs])
        ws = jnp.concatenate([w[None], ws])
        bs = jnp.concatenate([carry.bounced[None], bs])
        cross = bs & (ps[:, 0] < carry.hit_x)
        k = jnp.argmax(cross)
        found = jnp.any(cross) & (k > 0)
        k = jnp.maximum(k, 1)
        x0, x1 = ps[k - 1, 0], ps[k, 0]
        f = jnp.clip((x0 - carry.hit_x) / jnp.where(x0 == x1, 1.0, x0 - x1), 0.0, 1.0)
        lerp = lambda a: a[k - 1] + f * (a[k] - a[k - 1])
        t_hit = t_now + (k - 1 + f) * scfg.predict_dt
        return t_hit, lerp(ps), lerp(vs), lerp(ws), found

    def init(params, key):
        keys = jax.random.split(key, 10)
        target = jnp.stack([_uniform(keys[0], scfg.target_x), _uniform(keys[1], scfg.target_y)])
        roll = _uniform(keys[2], scfg.roll_deg) * (math.pi / 180.0)
        face = jnp.where(jax.random.bernoulli(keys[3]), 1.0, -1.0)
        chosen = jnp.zeros(8).at[jax.random.permutation(keys[4], 8)[:scfg.perturb_joints]].set(1.0)
        offset = chosen * jax.random.uniform(keys[5], (8,), minval=-1.0, maxval=1.0) * jnp.array(scfg.perturb)
        pref_off = chosen * jax.random.uniform(keys[6], (8,), minval=-1.0, maxval=1.0) * jnp.array(scfg.posture)
        hit_x = _uniform(keys[7], scfg.hit_x)
        p_nom, v_nom = _nominal_hit(cfg)
        p_nom = p_nom.at[0].set(hit_x)
        clearance = _uniform(keys[8], scfg.net_clearance)
        duration = return_time(cfg, p_nom, target, clearance)
        theta = stroke_guess(cfg, scfg, p_nom, v_nom, target, duration)
        normal = _direction(theta[0], theta[1])
        z_t, x_t = blade_frame(normal, roll, face)
        q_pref = posture(p_nom, roll, face) + pref_off
        q_hit = solve_ik(cfg, q_pref, p_nom - contact_offset * normal, z_t, x_t, q_pref,
                         scfg.ik_init_iters)
        z8 = jnp.zeros(8)
        return StrikerState(
            target=target, clearance=clearance, hit_x=hit_x, roll=roll, face=face,
            strike_s=_uniform(keys[9], scfg.strike_s), offset=offset, posture_offset=pref_off,
            t_hit=jnp.asarray(0.65), p_hit=p_nom, theta=theta, q_hit=q_hit, qd_hit=z8,
            q_ref=z8, v_ref=z8, u_prev=z8, v_prev=jnp.zeros(3), spin=jnp.zeros(3),
            bounced=jnp.array(False), struck=jnp.array(False))

    def apply(params, carry: StrikerState, obs: Obs, key):
        tab = cfg.table
        first = obs.t == 0
        t_now = obs.t.astype(jnp.float32) * dt
        joints = obs.frame[:8]
        p, v = obs.frame[8:11], obs.ball_vel
        # -- initial reference: where the robot is
        q_ref = jnp.where(first, joints, carry.q_ref)
        v_ref = jnp.where(first, 0.0, carry.v_ref)
        u_prev = jnp.where(first, joints, carry.u_prev)
        v_prev = jnp.where(first, v, carry.v_prev)

        # -- ball tracking: own-half bounce, spin, the returning ball
        bounce_now = (v_prev[2] < 0.0) & (v[2] > 0.0) & (p[0] < 0.0) & (p[2] < tab.top_z + 0.2)
        spin_est, resid = estimate_spin(cfg, v_prev, v, dt)
        _, spin_bounce = bounce(v_prev, carry.spin, jnp.array([0.0, 0.0, 1.0]), jnp.zeros(3),
                                scfg.model.table_restitution, scfg.model.table_grip, b.radius)
        free = ~first & ~bounce_now & (jnp.linalg.norm(resid) < 20.0)
        spin = jnp.where(bounce_now, spin_bounce, jnp.where(free, spin_est, carry.spin))
        bounced = carry.bounced | bounce_now
        returning = bounced & (v[0] > 0.0)
        struck = carry.struck | returning | (~first & (t_now >= carry.t_hit))

        # -- the hit and the stroke
        t_hit, p_hit, v_in, w_in, found = plan_hit(carry, p, v, spin, t_now)
        duration = flight_time(p_hit, t_hit, carry.target, carry.clearance)
        guess = stroke_guess(cfg, scfg, p_hit, v_in, carry.target, duration)
        theta = solve_stroke(cfg, scfg, jnp.where(first, guess, carry.theta), p_hit, v_in, w_in,
                             carry.target, duration)
        theta = jnp.where(jnp.all(jnp.isfinite(theta)), theta, guess)
        normal = _direction(theta[0], theta[1])
        roll = roll_at(carry.roll, p_hit)
        z_t, x_t = blade_frame(normal, roll, carry.face)
        q_pref = posture(p_hit, roll, carry.face) + carry.posture_offset
        q_hit = solve_ik(cfg, carry.q_hit, p_hit - contact_offset * normal, z_t, x_t, q_pref,
                         scfg.ik_iters)
        qd_hit = blade_joint_velocity(cfg, q_hit, theta[2] * normal, scfg.hit_speed_frac)
        update = found & ~struck
        keep = lambda new, old: jnp.where(update, new, old)
        t_hit, p_hit, theta = keep(t_hit, carry.t_hit), keep(p_hit, carry.p_hit), keep(theta, carry.theta)
        q_hit, qd_hit = keep(q_hit, carry.q_hit), keep(qd_hit, carry.qd_hit)

        # -- the reference: approach -> strike -> hold through the hit -> follow-through
        t_next = t_now + dt
        hold = scfg.hold_s
        t_hold = t_hit - hold                        # the hit velocity is reached here
        t_strike = t_hold - carry.strike_s           # the strike starts from rest here
        q_hold = q_hit - hold * qd_hit
        q_back = jnp.clip(q_hold - 0.5 * carry.strike_s * qd_hit, lo_m, hi_m)
        ap = hermite(q_ref, v_ref, q_back, jnp.zeros(8), t_strike - t_now, dt)
        st = hermite(q_ref, v_ref, q_hold, qd_hit, t_hold - t_now, jnp.minimum(dt, t_hold - t_now))
        extra = jnp.maximum(t_next - t_hold, 0.0)    # the hold starts within this step
        st = (st[0] + st[1] * extra, st[1], jnp.where(extra > 0.0, 0.0, st[2]))
        ho = (q_hit + qd_hit * (t_next - t_hit), qd_hit, jnp.zeros(8))
        fv = v_ref * jnp.exp(-dt / scfg.follow_s)
        fo = (q_ref + 0.5 * (v_ref + fv) * dt, fv, (fv - v_ref) / dt)
        phase = jnp.where(t_now >= t_hit + hold, 3, jnp.where(t_now >= t_hold, 2,
                                                               jnp.where(t_next >= t_strike, 1, 0)))
        pick = lambda i: jnp.select([phase == 0, phase == 1, phase == 2], [ap[i], st[i], ho[i]], fo[i])
        q_new, v_new, a_new = pick(0), pick(1), pick(2)
        # speed limits on the reference itself
        vlim = scfg.approach_speed_frac * vmax
        v_new = jnp.clip(v_new, -vlim, vlim)
        q_new = jnp.clip(q_new, q_ref - vlim * dt, q_ref + vlim * dt)
        v_new = jnp.where(((q_new <= lo) & (v_new < 0)) | ((q_new >= hi) & (v_new > 0)), 0.0, v_new)
        q_new = jnp.clip(q_new, lo, hi)

        # -- the command: servo feed-forward, the per-episode joint offsets, limits
        u = q_new + (2.0 * zeta / omega + scfg.servo_lead_s) * v_new + a_new / omega**2 + carry.offset
        u = jnp.clip(u, lo, hi)
        step_max = vmax * r.speed_margin * dt
        u = jnp.clip(u, u_prev - step_max, u_prev + step_max)

        carry = carry._replace(t_hit=t_hit, p_hit=p_hit, theta=theta, q_hit=q_hit, qd_hit=qd_hit,
                               q_ref=q_new, v_ref=v_new, u_prev=u, v_prev=v, spin=spin,
                               bounced=bounced, struck=struck)
        return carry, u

    return backends.Policy(init=init, apply=apply)
