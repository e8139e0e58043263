"""The scripted demonstrator: a model-based striker, a closed-loop policy of the observation.

It plays two demonstration sources (ttmjx/tools/demos.py), neither of them the paper's
procedure (that is the `paper` source, training/bootstrap_paper.py): `oracle`, which returns
every ball toward a RANDOM point of the opponent's half drawn per episode (its landings are its
targets: imitating it is nearly goal reaching, an upper bound), and `striker` (called `paper`
in datasets without a source_version), aimed at one fixed point with 4 joints perturbed. It hits the thrown ball
after its bounce; the commanded goal in the observation is ignored. Every control step (`striker_step`) runs four stages:

1. predict the ball (`track_ball`, `predict_hit`): its own-half bounce, and its spin, estimated
   from the observed velocity change (the residual of gravity and drag is the Magnus force; the
   observation has no spin); then its flight with the world's air model (`ballphysics`, RK2 at
   `predict_dt`) and the table `Surface` bounce model, up to the hit: after the bounce, where the
   ball crosses the episode's hitting plane x = hit_x (or earlier: before it falls too low, or
   late in the episode, so that the return can land in time);
2. choose the strike (`choose_stroke`): Newton on the face normal (yaw, pitch) and the blade
   speed along it, so that the ball, after the paddle `Surface` bounce, flies with drag and
   Magnus from the hit to the landing target in the flight time that clears the net by the
   episode's clearance;
3. solve the pose (`solve_pose`, `hit_joint_velocity`): the 8-DOF inverse kinematics (damped
   Gauss-Newton on `forward_kinematics`, the chain of scene.py in jnp, warm-started from the last
   step) for the blade centre one ball radius plus half a blade behind the hit, with the stroke's
   normal and the episode's blade roll, and the joint velocities that move the blade centre at
   the stroke's velocity (`blade_joint_velocity`);
4. time the swing (`swing_reference`, `limit_reference`, `servo_command`): a joint-space
   reference: a cubic approach to a back-swing pose, a constant-acceleration strike that reaches
   the hit velocity `hold_s` before the hit, a constant-velocity hold through it, then a decaying
   follow-through. The command is the reference plus the position servo's velocity and
   acceleration feed-forward, kept inside the joint ranges and the speed clipping of
   `env.command` (the environment never has to clip it).

Per-episode randomness, drawn in `init` (`draw_episode`): landing target, net clearance,
hitting plane, blade roll (size and side) and face, strike duration, and "perturb 4 of the 8
joints" (as in the paper): a constant offset on the commands of 4 random joints, and a random
posture preference for the same 4 joints (the posture only moves the robot within the redundancy
of the 8-DOF chain).

Pure jnp with no Python control flow on traced values: it runs inside the jit-compiled MJX rollout
and, jit-compiled and vmapped, between the MuJoCo C backend's physics calls.
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx.world import backends, ballphysics, observation
from ttmjx.world.config import World
from ttmjx.world.env import Obs

GRAVITY = 9.81

# The arm's chain (scene.py, from the public ABB IRB 120 URDF): the offset of each body from its
# parent, in the parent's frame, for link2 .. link6; link1 sits base_z above the gantry carriage.
_LINK_OFFSETS = ((0.0, 0.0, 0.29), (0.0, 0.0, 0.27), (0.0, 0.0, 0.07), (0.302, 0.0, 0.0),
                 (0.072, 0.0, 0.0))


@dataclasses.dataclass(frozen=True)
class Surface:
    """A bounce as the striker models it, in the frame of the surface (unit normal n toward the
    ball), with the ball's velocity v and spin w relative to it (`bounce`):

        v_n' = -restitution v_n
        dv_t = -(grip + grip_per_speed |v_n|) v_t + spin_grip r (w x n)
        dw   = -spin_gain (3 / 2r) n x dv_t          (the friction impulse spins the hollow ball)

    Fitted by `measure_surface` on the MuJoCo scene (oblique impacts over arrival phases)."""
    restitution: float
    grip: float
    grip_per_speed: float
    spin_grip: float
    spin_gain: float


# Measured on the default World by `measure_surface` (tests/test_striker.py re-measures them).
TABLE = Surface(restitution=0.893, grip=0.078, grip_per_speed=0.0036, spin_grip=0.082, spin_gain=0.85)
PADDLE = Surface(restitution=0.760, grip=0.164, grip_per_speed=0.0060, spin_grip=0.168, spin_gain=0.87)


@dataclasses.dataclass(frozen=True)
class BallModel:
    """The ball's contacts as the striker models them."""
    table: Surface = TABLE
    paddle: Surface = PADDLE


@dataclasses.dataclass(frozen=True)
class StrikerConfig:
    """The striker's plan and its per-episode randomization (uniform ranges)."""
    # Where the returned ball should land (opponent's half, margins from the edges and the net).
    target_x: tuple = (0.18, 1.2)
    target_y: tuple = (-0.62, 0.62)
    # The return's ball-centre height above the net tape where it crosses the net (drag-free plan).
    net_clearance: tuple = (0.10, 0.40)
    min_clearance: float = 0.05     # lowered down to this when the episode's time runs short
    return_reserve_s: float = 0.55  # a slow ball is struck this long before the episode ends
    hit_min_height: float = 0.1     # a falling ball is struck before it drops this close to the
                                    # table top's height
    # The hitting plane: the ball is struck, after its bounce, where it crosses x = hit_x.
    hit_x: tuple = (-1.62, -1.42)
    # Blade roll: the angle of the extension (link6 x) in the blade plane from "pointing down",
    # positive toward +y. Its size is drawn per episode; its sign too, except for a ball wider
    # than roll_side_y, where the blade reaches out toward the ball's side (decided on the first
    # predicted hit).
    # A high hit raises the size to keep the wrist (the blade hangs below it) below wrist_max_z.
    roll_deg: tuple = (0.0, 100.0)
    roll_side_y: float = 0.25
    roll_plus_prob: float = 0.5     # P(positive roll) for a ball not wider than roll_side_y
    back_face_prob: float = 0.5     # P(the blade's back face hits)
    wrist_max_z: float = 1.2
    # Posture: the gantry carriage this far behind the hit, and following this fraction of its y.
    reach_x: float = 0.45
    gantry_follow_y: float = 0.7
    # Strike: constant acceleration from rest over this time up to the hit; then a follow-through.
    strike_s: tuple = (0.12, 0.2)
    hold_s: float = 0.02          # the hit velocity is held this long before and after the hit
    follow_s: float = 0.08        # then decays with this time constant
    # Joint speeds the plan may use, as a fraction of the speed limits.
    hit_speed_frac: float = 0.7
    blade_turn_cost: float = 0.03     # (rad/s)^-2, see blade_joint_velocity
    approach_speed_frac: float = 0.9
    # "Perturb 4 of the 8 joints": constant command offsets (m, rad, up to `perturb`) on
    # `perturb_joints` random joints, and offsets of the same joints' posture preference (up to
    # `posture`; the IK keeps the blade's pose, so these only move the robot in its redundancy).
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
    ik_restart_err: float = 0.02    # m
    ik_restart_steps: int = 8
    model: BallModel = BallModel()

    def __post_init__(self):
        for name in ("perturb", "posture"):
            if len(getattr(self, name)) != 8:
                raise ValueError(f"StrikerConfig.{name} must have 8 entries (one per joint), "
                                 f"got {getattr(self, name)}")
        if not 0 <= self.perturb_joints <= 8:
            raise ValueError(f"StrikerConfig.perturb_joints must be in 0..8, got {self.perturb_joints}")
        for name in ("target_x", "target_y", "net_clearance", "hit_x", "roll_deg", "strike_s"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise ValueError(f"StrikerConfig.{name} must be a (low, high) range, got {(lo, hi)}")


class StrikerState(NamedTuple):
    """The striker's carry for one throw."""
    # per-episode draws
    target: jax.Array       # [2] landing target (x, y)
    clearance: jax.Array    # () net clearance of the return (m)
    hit_x: jax.Array        # () hitting plane
    roll: jax.Array         # () blade roll size (rad)
    roll_sign: jax.Array    # () +1 / -1
    side_set: jax.Array     # bool: roll_sign has been decided from a predicted hit
    face: jax.Array         # () +1 / -1: which side of the blade hits
    strike_s: jax.Array     # () strike duration (s)
    offset: jax.Array       # [8] command offsets
    posture_offset: jax.Array  # [8] offset of the IK's posture preference
    # plan
    t_hit: jax.Array        # () predicted hit time (s since launch)
    p_hit: jax.Array        # [3] ball centre at the hit
    theta: jax.Array        # [3] stroke: face normal yaw, pitch (rad), blade speed along it (m/s)
    q_hit: jax.Array        # [8] joints at the hit
    q_seed: jax.Array       # [8] the IK's next warm start
    ik_age: jax.Array       # int32: steps since the IK last restarted from the posture
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


def blade_joint_velocity(cfg: World, q, vel, speed_frac: float, turn_cost: float = 0.0):
    """Joint velocities [8] moving the blade centre at vel [3] with the least speed relative to
    the limits (the gantry counted 3x) plus turn_cost times the blade's squared angular velocity
    ((rad/s)^-2: a turning blade makes the face normal depend on the exact contact time), scaled
    down as a whole to stay within speed_frac of the limits."""
    vmax = jnp.array(cfg.robot.max_speed)
    cost = (jnp.array([3.0, 3.0, 1, 1, 1, 1, 1, 1]) / vmax) ** 2
    jp, jr = jax.jacfwd(lambda qq: forward_kinematics(cfg, qq))(q)  # [3, 8], [3, 3, 8]
    rot = forward_kinematics(cfg, q)[1]
    # angular velocity in the world frame from d(rot)/dq: skew(w) = dR R^T
    skew = jnp.einsum("ijk,lj->ilk", jr, rot)                        # [3, 3, 8]
    jw = jnp.stack([skew[2, 1], skew[0, 2], skew[1, 0]])             # [3, 8]
    a = jnp.diag(cost) + turn_cost * jw.T @ jw
    ainv_jt = jnp.linalg.solve(a, jp.T)                              # [8, 3]
    qd = ainv_jt @ jnp.linalg.solve(jp @ ainv_jt + 1e-6 * jnp.eye(3), vel)
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


def bounce(surf: Surface, v, w, normal, surface_vel, radius):
    """Ball velocity [3] and spin [3] after a bounce (`Surface`) on a surface with unit normal
    [3] (pointing toward the ball) moving at surface_vel [3]."""
    rel = v - surface_vel
    vn = jnp.dot(rel, normal)
    rel_t = rel - vn * normal
    dv_t = (-(surf.grip + surf.grip_per_speed * jnp.abs(vn)) * rel_t
            + surf.spin_grip * radius * jnp.cross(w, normal))
    v_out = surface_vel - surf.restitution * vn * normal + rel_t + dv_t
    w_out = w - surf.spin_gain * (1.5 / radius) * jnp.cross(normal, dv_t)
    return v_out, w_out


def measure_surface(cfg: World, surface: str, phases: int = 6) -> Surface:
    """Fit a `Surface` to oblique impacts on the MuJoCo scene (C, no air, no gravity): normal
    speeds 2-8 m/s, tangential 0-3 m/s, spin 0 / +-30 rad/s, each at `phases` sub-step arrival
    offsets. surface: "table" (its top) or "paddle" (the blade held facing +x)."""
    import mujoco

    from ttmjx.world import scene
    if surface not in ("table", "paddle"):
        raise ValueError(f"surface must be 'table' or 'paddle', got {surface!r}")
    m = mujoco.MjModel.from_xml_string(scene.mjcf(cfg, fluid=False))   # a copy: gravity goes off
    m.opt.gravity[:] = 0.0
    ids = scene.ids(m)
    d = mujoco.MjData(m)
    r = cfg.ball.radius
    q_blade = np.array([0, 0, 0, 0, 0, 0, 0.5 * np.pi, 0.0])
    rows = []
    for vn, vt, spin, ph in itertools.product((2.0, 4.0, 6.0, 8.0), (0.0, 1.0, 3.0), (0.0, -30.0, 30.0),
                                              range(phases)):
        mujoco.mj_resetData(m, d)
        d.qpos[ids.robot_qpos] = q_blade
        d.ctrl[:] = q_blade
        mujoco.mj_forward(m, d)
        if surface == "paddle":
            n = d.site_xmat[ids.paddle_site].reshape(3, 3)[:, 2].copy()
            face = d.site_xpos[ids.paddle_site] + n * (r + cfg.robot.blade_thickness / 2)
        else:
            n = np.array([0.0, 0.0, 1.0])
            face = np.array([-0.5, 0.0, cfg.table.top_z + r])
        v = -vn * n + vt * np.cross(n, [0.0, 1.0, 0.0])        # tangent in the x-z plane
        w = spin * np.array([0.0, 1.0, 0.0])
        start = face + n * vn * 1e-3 * (ph / phases) - v * 0.005
        d.qpos[ids.ball_qpos:ids.ball_qpos + 7] = np.r_[start, 1.0, 0.0, 0.0, 0.0]
        d.qvel[ids.ball_qvel:ids.ball_qvel + 6] = np.r_[v, w]
        for _ in range(30):
            mujoco.mj_step(m, d)
        w1 = np.zeros(3)
        mujoco.mju_rotVecQuat(w1, d.qvel[ids.ball_qvel + 3:ids.ball_qvel + 6],
                              d.qpos[ids.ball_qpos + 3:ids.ball_qpos + 7])
        rows.append((n, v, w, d.qvel[ids.ball_qvel:ids.ball_qvel + 3].copy(), w1))
    e = np.mean([np.dot(v1, n) / -np.dot(v, n) for n, v, w, v1, w1 in rows])
    # dv_t = -a v_t - b |v_n| v_t + c r (w x n): least squares over the tangential components
    feats, targ, gain_x, gain_y = [], [], [], []
    for n, v, w, v1, w1 in rows:
        vn_ = np.dot(v, n)
        vt_ = v - vn_ * n
        dvt = (v1 - np.dot(v1, n) * n) - vt_
        for k in range(3):
            feats.append([-vt_[k], -abs(vn_) * vt_[k], r * np.cross(w, n)[k]])
            targ.append(dvt[k])
        model_dw = -(1.5 / r) * np.cross(n, dvt)
        gain_x.extend(model_dw), gain_y.extend(w1 - w)
    a, b, c = np.linalg.lstsq(np.array(feats), np.array(targ), rcond=None)[0]
    gx, gy = np.array(gain_x), np.array(gain_y)
    k = float(np.dot(gx, gy) / max(np.dot(gx, gx), 1e-12))
    return Surface(restitution=float(e), grip=float(a), grip_per_speed=float(b), spin_grip=float(c),
                   spin_gain=k)


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
        vb, wb = bounce(mdl.table, v1, w1, up, jnp.zeros(3), b.radius)
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
    e = scfg.model.paddle.restitution
    s = (jnp.dot(v_out, n) + e * jnp.dot(v_in, n)) / (1.0 + e)
    return jnp.stack([jnp.arctan2(n[1], n[0]), jnp.arcsin(jnp.clip(n[2], -1.0, 1.0)), s])


def solve_stroke(cfg: World, scfg: StrikerConfig, theta, p_hit, v_in, w_in, target, duration):
    """Newton on theta [3] so that the ball struck at p_hit lands on target [2] after duration."""
    mdl = scfg.model
    goal = jnp.concatenate([target, jnp.array([cfg.table.top_z + cfg.ball.radius])])

    def resid(th):
        n = _direction(th[0], th[1])
        v_out, w_out = bounce(mdl.paddle, v_in, w_in, n, th[2] * n, cfg.ball.radius)
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
# The policy in four stages: predict the ball, choose the strike, solve the pose, time the swing.
# Each stage is a pure function of one throw's arrays; `striker_step` composes them.
# ----------------------------------------------------------------------------------------------

# 1. Predict the ball ------------------------------------------------------------------------

def track_ball(cfg: World, scfg: StrikerConfig, p, v, v_prev, spin, first):
    """The ball seen at one control step: position p [3] and velocity v [3], after the velocity
    v_prev [3] one step earlier; spin [3] is the estimate so far, first () the episode's first
    step. Returns (spin [3], bounce_now ()): the new spin estimate, and whether the ball bounced
    on the robot's half during this step."""
    # the bounce shows as the vertical velocity turning up near the table top
    bounce_now = (v_prev[2] < 0.0) & (v[2] > 0.0) & (p[0] < 0.0) & (p[2] < cfg.table.top_z + 0.2)
    # the observation has no spin: the velocity change in free flight reveals it (Magnus) ...
    spin_est, resid = estimate_spin(cfg, v_prev, v, cfg.control_dt)
    # ... but across a bounce the change is the contact's, so the bounce model carries the spin
    _, spin_bounce = bounce(scfg.model.table, v_prev, spin, jnp.array([0.0, 0.0, 1.0]), jnp.zeros(3),
                            cfg.ball.radius)
    # an air force no spin could make is some other contact (net, paddle): keep the old estimate
    free = ~first & ~bounce_now & (jnp.linalg.norm(resid) < 20.0)
    return jnp.where(bounce_now, spin_bounce, jnp.where(free, spin_est, spin)), bounce_now


def _crossing(values, level, past, k):
    """The fraction () of the step from k - 1 to k at which values [n] reach level; 1 where
    past[k] is False (that condition did not stop the search)."""
    a0, a1 = values[k - 1], values[k]
    return jnp.where(past[k], jnp.clip((a0 - level) / jnp.where(a0 == a1, 1.0, a0 - a1), 0.0, 1.0), 1.0)


def predict_hit(cfg: World, scfg: StrikerConfig, p, v, w, bounced, hit_x, t_now):
    """Where the ball will be struck, from its position p [3], velocity v [3], spin w [3] and
    bounced () (on the robot's half already) at t_now (s): the first moment of the predicted
    flight, after the own-half bounce, that the ball crosses the hitting plane x = hit_x (),
    falls to hit_min_height above the table top, or is so late that its return must leave now
    (`return_reserve_s`). Returns (t_hit (), p_hit [3], v_in [3], w_in [3], found ()), linear
    between predict_dt steps; found is False when no such moment lies ahead within predict_s."""
    ps, vs, ws, bs = (jnp.concatenate([now[None], later])
                      for now, later in zip((p, v, w, bounced), predict(cfg, scfg, p, v, w, bounced)))
    times = t_now + scfg.predict_dt * jnp.arange(ps.shape[0])
    t_latest, z_min = cfg.episode_s - scfg.return_reserve_s, cfg.table.top_z + scfg.hit_min_height
    past_x, past_t = ps[:, 0] < hit_x, times > t_latest
    past_z = (ps[:, 2] < z_min) & (vs[:, 2] < 0.0)
    cross = bs & (past_x | past_t | past_z)
    k = jnp.argmax(cross)
    found = jnp.any(cross) & (k > 0)      # k == 0: the ball is past already (no hit ahead)
    k = jnp.maximum(k, 1)
    f = jnp.minimum(jnp.minimum(_crossing(ps[:, 0], hit_x, past_x, k),
                                _crossing(times, t_latest, past_t, k)),
                    _crossing(ps[:, 2], z_min, past_z, k))
    lerp = lambda a: a[k - 1] + f * (a[k] - a[k - 1])  # noqa: E731
    return t_now + (k - 1 + f) * scfg.predict_dt, lerp(ps), lerp(vs), lerp(ws), found


# 2. Choose the strike -----------------------------------------------------------------------

def flight_time(cfg: World, scfg: StrikerConfig, p_hit, t_hit, target, clearance):
    """The return's flight time () from p_hit [3] at t_hit () to target [2]: the one clearing
    the net by clearance (), cut to land 0.1 s before the episode ends, but never so short that
    it clears the net by less than min_clearance."""
    t_left = cfg.episode_s - t_hit - 0.1
    t_min = return_time(cfg, p_hit, target, jnp.asarray(scfg.min_clearance))
    return jnp.maximum(jnp.minimum(return_time(cfg, p_hit, target, clearance), t_left), t_min)


def choose_stroke(cfg: World, scfg: StrikerConfig, p_hit, v_in, w_in, t_hit, target, clearance,
                  theta, first):
    """The stroke [3] (face normal yaw, pitch (rad), blade speed along it (m/s)) returning the
    ball that arrives at p_hit [3] at t_hit () with velocity v_in [3] and spin w_in [3] onto
    target [2], clearing the net by clearance (): newton_iters Newton steps warm-started from
    the last step's stroke theta [3] (from the drag-free guess where first ()). Newton runs
    a few steps per control step: the plan changes little from one step to the next."""
    duration = flight_time(cfg, scfg, p_hit, t_hit, target, clearance)
    guess = stroke_guess(cfg, scfg, p_hit, v_in, target, duration)
    theta = solve_stroke(cfg, scfg, jnp.where(first, guess, theta), p_hit, v_in, w_in, target, duration)
    return jnp.where(jnp.all(jnp.isfinite(theta)), theta, guess)   # a diverged solve restarts


# 3. Solve the pose --------------------------------------------------------------------------

def contact_offset(cfg: World) -> float:
    """How far (m) the blade centre is behind the ball centre, along the face normal, at the hit."""
    return cfg.ball.radius + cfg.robot.blade_thickness / 2


def roll_side(cfg: World, scfg: StrikerConfig, p_hit, found, roll_sign, side_set):
    """(roll_sign (), side_set ()): the blade roll's side, decided on the first found () hit at
    p_hit [3]: toward a ball wider than roll_side_y (the blade reaches out to it), else the
    episode's draw roll_sign; side_set () says it was decided already."""
    dy = p_hit[1] - cfg.robot.base_y
    side = jnp.where(jnp.abs(dy) > scfg.roll_side_y, jnp.sign(dy), roll_sign)
    return jnp.where(found & ~side_set, side, roll_sign), side_set | found


def roll_at(cfg: World, scfg: StrikerConfig, roll, sign, p_hit):
    """The signed blade roll () for a hit at p_hit [3]: the episode's roll size (), raised to
    what keeps the wrist below wrist_max_z (the extension hangs below the wrist by `hang`)."""
    r = cfg.robot
    hang = r.extension + r.blade_half_size[0] + _LINK_OFFSETS[4][0]
    floor = jnp.arccos(jnp.clip((scfg.wrist_max_z - p_hit[2]) / hang, 0.0, 1.0))
    return sign * jnp.maximum(roll, floor)


def posture(cfg: World, scfg: StrikerConfig, p_hit, roll, face):
    """The IK's posture preference [8] for a hit at p_hit [3]: gantry behind and partly under
    the ball, the forearm level and pointing forward, the wrist pitched so that the extension
    hangs down (j5 near 90 deg), then rolled sideways by j4 = roll () and the face () chosen by j6."""
    r = cfg.robot
    gx = jnp.clip(p_hit[0] - scfg.reach_x - r.base_x, r.lower[0], r.upper[0])
    gy = jnp.clip(scfg.gantry_follow_y * (p_hit[1] - r.base_y), r.lower[1], r.upper[1])
    j6 = jnp.where(face > 0, 0.0, math.pi)
    return jnp.stack([gx, gy, 0.0, 0.2, -0.4, roll, 0.5 * math.pi - 0.3, j6])


def solve_pose(cfg: World, scfg: StrikerConfig, q_start, p_hit, theta, roll, face, posture_offset,
               iters: int):
    """The joints [8] that strike the ball centre p_hit [3] with the stroke theta [3]: the blade
    centre `contact_offset` behind it along the face normal, the face () +1 / -1 toward it and
    the blade rolled by roll (); iters IK steps from q_start [8] (None: from the posture,
    shifted by posture_offset [8]). Returns (q_hit [8], blade [3] the blade centre aimed at,
    q_pref [8] the posture)."""
    normal = _direction(theta[0], theta[1])
    z_t, x_t = blade_frame(normal, roll, face)
    q_pref = posture(cfg, scfg, p_hit, roll, face) + posture_offset
    blade = p_hit - contact_offset(cfg) * normal
    q_start = q_pref if q_start is None else q_start
    return solve_ik(cfg, q_start, blade, z_t, x_t, q_pref, iters), blade, q_pref


def hit_joint_velocity(cfg: World, scfg: StrikerConfig, q_hit, theta):
    """Joint velocities [8] at q_hit [8] moving the blade at the stroke's speed along its face
    normal (theta [3]), within hit_speed_frac of the speed limits."""
    normal = _direction(theta[0], theta[1])
    return blade_joint_velocity(cfg, q_hit, theta[2] * normal, scfg.hit_speed_frac,
                                scfg.blade_turn_cost)


def next_ik_seed(cfg: World, scfg: StrikerConfig, q_hit, blade, q_pref, q_seed, ik_age, update, lead):
    """(q_seed [8], ik_age ()): the IK's next warm start, q_hit [8] where the plan updates ().
    A warm start stuck away from the blade target [3] restarts from the posture q_pref [8], at
    most every ik_restart_steps (what a restart needs to converge) and not within 0.2 s of the
    hit (lead (), s): so close, the jump would spoil the swing."""
    miss = jnp.linalg.norm(forward_kinematics(cfg, q_hit)[0] - blade)
    stuck = (miss > scfg.ik_restart_err) & (ik_age >= scfg.ik_restart_steps) & update & (lead > 0.2)
    return jnp.where(update, jnp.where(stuck, q_pref, q_hit), q_seed), jnp.where(stuck, 0, ik_age + 1)


# 4. Time the swing --------------------------------------------------------------------------

def swing_phase(cfg: World, scfg: StrikerConfig, t_now, t_hit, strike_s):
    """The swing's phase () at t_now () for a hit at t_hit (): 0 approach (to the back-swing,
    arriving at rest), 1 strike (constant acceleration over strike_s () up to the hit velocity,
    reached hold_s before the hit), 2 hold (the hit velocity through the hit), 3 follow-through."""
    t_hold = t_hit - scfg.hold_s
    t_strike = t_hold - strike_s
    return jnp.where(t_now >= t_hit + scfg.hold_s, 3, jnp.where(
        t_now >= t_hold, 2, jnp.where(t_now + cfg.control_dt >= t_strike, 1, 0)))


def swing_reference(cfg: World, scfg: StrikerConfig, q_ref, v_ref, t_now, t_hit, q_hit, qd_hit,
                    strike_s):
    """The joint reference one control step after t_now (): (position, velocity, acceleration),
    each [8], from q_ref, v_ref [8] in the `swing_phase` of the hit at t_hit (), joints q_hit
    [8] and velocities qd_hit [8]. Cubic segments (`hermite`) reach the back-swing at rest and
    the hold at the hit velocity; the follow-through's velocity decays over follow_s."""
    dt, hold = cfg.control_dt, scfg.hold_s
    t_next, t_hold = t_now + dt, t_hit - hold
    q_hold = q_hit - hold * qd_hit
    lo_m, hi_m = _limits(cfg, 0.01)
    q_back = jnp.clip(q_hold - 0.5 * strike_s * qd_hit, lo_m, hi_m)   # the strike's start, at rest
    approach = hermite(q_ref, v_ref, q_back, jnp.zeros(8), t_hold - strike_s - t_now, dt)
    st = hermite(q_ref, v_ref, q_hold, qd_hit, t_hold - t_now, jnp.minimum(dt, t_hold - t_now))
    extra = jnp.maximum(t_next - t_hold, 0.0)    # the hold starts within this step
    strike = (st[0] + st[1] * extra, st[1], jnp.where(extra > 0.0, 0.0, st[2]))
    held = (q_hit + qd_hit * (t_next - t_hit), qd_hit, jnp.zeros(8))
    fv = v_ref * jnp.exp(-dt / scfg.follow_s)
    follow = (q_ref + 0.5 * (v_ref + fv) * dt, fv, (fv - v_ref) / dt)
    phase = swing_phase(cfg, scfg, t_now, t_hit, strike_s)
    return tuple(jnp.select([phase == 0, phase == 1, phase == 2], list(x[:3]), x[3])
                 for x in zip(approach, strike, held, follow))


def limit_reference(cfg: World, scfg: StrikerConfig, q_ref, q, v):
    """The reference step from q_ref [8] to (q, v) [8], kept within approach_speed_frac of the
    speed limits and inside the joint ranges, with no velocity into a range's end."""
    lo, hi = _limits(cfg)
    vlim = scfg.approach_speed_frac * jnp.array(cfg.robot.max_speed)
    v = jnp.clip(v, -vlim, vlim)
    q = jnp.clip(q, q_ref - vlim * cfg.control_dt, q_ref + vlim * cfg.control_dt)
    v = jnp.where(((q <= lo) & (v < 0)) | ((q >= hi) & (v > 0)), 0.0, v)
    return jnp.clip(q, lo, hi), v


def servo_command(cfg: World, q, v, a, offset, u_prev):
    """The command [8] under which the position servos (scene.py: kv / kp = 2 zeta / omega)
    follow the reference q, v, a [8] (velocity and acceleration feed-forward), plus the
    episode's offset [8]; inside the joint ranges and the step from the last command u_prev [8]
    that `env.command` allows, so that the environment never has to clip it."""
    r = cfg.robot
    lo, hi = _limits(cfg)
    u = q + (2.0 * r.servo_damping / r.servo_omega) * v + a / r.servo_omega**2 + offset
    u = jnp.clip(u, lo, hi)
    step_max = jnp.array(r.max_speed) * r.speed_margin * cfg.control_dt
    return jnp.clip(u, u_prev - step_max, u_prev + step_max)


# The policy ---------------------------------------------------------------------------------

def _uniform(key, lo_hi, shape=()):
    return jax.random.uniform(key, shape, minval=lo_hi[0], maxval=lo_hi[1])


# A typical hit (ball centre, its velocity): the plan before the first prediction.
_NOMINAL_HIT = ((-1.52, 0.0, 1.0), (-4.0, 0.0, 0.0))


def draw_episode(cfg: World, scfg: StrikerConfig, key) -> StrikerState:
    """The carry at launch: the episode's draws (`StrikerConfig`), and a plan for a typical hit
    on the episode's hitting plane, so that the robot sets off toward a sensible pose."""
    keys = jax.random.split(key, 11)
    chosen = jnp.zeros(8).at[jax.random.permutation(keys[4], 8)[:scfg.perturb_joints]].set(1.0)
    signed = lambda k: chosen * jax.random.uniform(k, (8,), minval=-1.0, maxval=1.0)  # noqa: E731
    coin = lambda k, p: jnp.where(jax.random.bernoulli(k, p), 1.0, -1.0)  # noqa: E731
    z3, z8, no = jnp.zeros(3), jnp.zeros(8), jnp.array(False)
    s = StrikerState(
        target=jnp.stack([_uniform(keys[0], scfg.target_x), _uniform(keys[1], scfg.target_y)]),
        clearance=_uniform(keys[8], scfg.net_clearance), hit_x=_uniform(keys[7], scfg.hit_x),
        roll=_uniform(keys[2], scfg.roll_deg) * (math.pi / 180.0),
        roll_sign=coin(keys[3], scfg.roll_plus_prob), side_set=no,
        face=coin(keys[10], 1.0 - scfg.back_face_prob), strike_s=_uniform(keys[9], scfg.strike_s),
        offset=signed(keys[5]) * jnp.array(scfg.perturb),
        posture_offset=signed(keys[6]) * jnp.array(scfg.posture),
        # the plan, filled in below, and the tracking, filled in on the first step
        t_hit=jnp.asarray(0.65), p_hit=z3, theta=z3, q_hit=z8, q_seed=z8, ik_age=jnp.int32(0),
        qd_hit=z8, q_ref=z8, v_ref=z8, u_prev=z8, v_prev=z3, spin=z3, bounced=no, struck=no)
    p_nom, v_nom = jnp.array(_NOMINAL_HIT[0]).at[0].set(s.hit_x), jnp.array(_NOMINAL_HIT[1])
    duration = return_time(cfg, p_nom, s.target, s.clearance)
    theta = stroke_guess(cfg, scfg, p_nom, v_nom, s.target, duration)
    roll = roll_at(cfg, scfg, s.roll, s.roll_sign, p_nom)
    q_hit, _, _ = solve_pose(cfg, scfg, None, p_nom, theta, roll, s.face, s.posture_offset,
                             scfg.ik_init_iters)
    return s._replace(p_hit=p_nom, theta=theta, q_hit=q_hit, q_seed=q_hit)


def _start_from(s: StrikerState, joints, v, first) -> StrikerState:
    """The carry where first (): the reference and the last command at the robot's joints [8]
    (at rest), the last ball velocity v [3] (no velocity change to read the spin from yet)."""
    at_start = lambda new, old: jnp.where(first, new, old)  # noqa: E731
    return s._replace(q_ref=at_start(joints, s.q_ref), v_ref=at_start(0.0, s.v_ref),
                      u_prev=at_start(joints, s.u_prev), v_prev=at_start(v, s.v_prev))


def striker_step(cfg: World, scfg: StrikerConfig, s: StrikerState, obs: Obs):
    """One control step, the four stages in turn: (the carry after it, the command [8])."""
    first, t_now = obs.t == 0, obs.t.astype(jnp.float32) * cfg.control_dt
    p, v = observation.ball_pos(obs.frame), obs.ball_vel
    s = _start_from(s, observation.joints(obs.frame), v, first)
    # 1. predict the ball; the strike is over once its time has passed or the ball flies back
    spin, bounce_now = track_ball(cfg, scfg, p, v, s.v_prev, s.spin, first)
    t_hit, p_hit, v_in, w_in, found = predict_hit(cfg, scfg, p, v, spin, s.bounced, s.hit_x, t_now)
    struck = s.struck | ((s.bounced | bounce_now) & (v[0] > 0.0)) | (~first & (t_now >= s.t_hit))
    # 2. choose the strike
    theta = choose_stroke(cfg, scfg, p_hit, v_in, w_in, t_hit, s.target, s.clearance, s.theta, first)
    # 3. solve the pose, from the last step's
    roll_sign, side_set = roll_side(cfg, scfg, p_hit, found, s.roll_sign, s.side_set)
    roll = roll_at(cfg, scfg, s.roll, roll_sign, p_hit)
    q_hit, blade, q_pref = solve_pose(cfg, scfg, s.q_seed, p_hit, theta, roll, s.face,
                                      s.posture_offset, scfg.ik_iters)
    # the plan follows the prediction in free flight only (mid-bounce the velocity misleads)
    update = found & ~struck & ~bounce_now & (p[2] > cfg.table.top_z + cfg.ball.radius)
    q_seed, ik_age = next_ik_seed(cfg, scfg, q_hit, blade, q_pref, s.q_seed, s.ik_age, update,
                                  t_hit - t_now)
    plan = dict(t_hit=t_hit, p_hit=p_hit, theta=theta, q_hit=q_hit,
                qd_hit=hit_joint_velocity(cfg, scfg, q_hit, theta))
    s = s._replace(**{k: jnp.where(update, x, getattr(s, k)) for k, x in plan.items()})
    # 4. time the swing
    q, qd, qdd = swing_reference(cfg, scfg, s.q_ref, s.v_ref, t_now, s.t_hit, s.q_hit, s.qd_hit,
                                 s.strike_s)
    q, qd = limit_reference(cfg, scfg, s.q_ref, q, qd)
    u = servo_command(cfg, q, qd, qdd, s.offset, s.u_prev)
    return s._replace(q_ref=q, v_ref=qd, u_prev=u, v_prev=v, spin=spin, struck=struck,
                      bounced=s.bounced | bounce_now, roll_sign=roll_sign, side_set=side_set,
                      q_seed=q_seed, ik_age=ik_age), u


@functools.lru_cache(maxsize=None)
def striker_policy(cfg: World, scfg: StrikerConfig = StrikerConfig()) -> backends.Policy:
    """The scripted demonstrator as a Policy for ONE throw (params unused, pass None). One object
    per configuration: compiled rollouts are kept by the policy they play."""
    return backends.Policy(init=lambda params, key: draw_episode(cfg, scfg, key),
                           apply=lambda params, carry, obs, key: striker_step(cfg, scfg, carry, obs))


def imitable() -> StrikerConfig:
    """The striker for bootstrap datasets that a goal-conditioned policy must imitate.

    The default draws latent choices the observation cannot reveal before the swing (which blade
    face, which roll side, how long the strike): averaged by a mean-squared-error imitation,
    such modes give a stroke that is none of them. Here the face and roll side are fixed and the
    strike duration narrow; the landing target (the relabeled goal), the net clearance, the
    hitting plane and the 4 perturbed joints stay random, so landings still cover the half."""
    return StrikerConfig(roll_plus_prob=1.0, back_face_prob=0.0, roll_deg=(20.0, 60.0), strike_s=(0.15, 0.17))
