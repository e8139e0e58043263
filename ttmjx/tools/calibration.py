"""Measurements of the simulated ball, the same on both physics backends.

Everything here is measured from simulated trajectories (ball position and velocity after every
physics step), never derived from contact parameters:

* restitution (COR) of the table, the paddle and the net for normal impacts, from the ball's
  relative normal velocity just before and just after the contact;
* how deep a ball sinks into a surface and whether its centre ever passes the surface's
  mid-plane (tunnelling);
* free-flight positions, for the air-force parity of MJX (ttmjx.world.ballphysics) against MuJoCo C's
  ellipsoid fluid model.

Arrival phase. At dt = 1 ms a contact lasts only ~5 physics steps, and where the ball happens to
be at the first step boundary inside the surface (0 .. v*dt deep) changes the outcome by a few
per cent. A real ball arrives at a uniformly random phase, so every impact measurement here is
made over a set of arrival phases (sub-step offsets of the start position); `cor_by_phase`
gives each one, `measure_cor` their mean.

A `physics` argument is a `ttmjx.world.backends.CPhysics` (batched, numpy) or `MjxPhysics` (one throw,
jitted and vmapped here); `ball_trajectories` hides the difference. The robot is held at its
home pose (ctrl = qpos = home, at rest: gravity-compensated, a static equilibrium).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ttmjx.world import scene
from ttmjx.world.config import World

SURFACES = ("table", "paddle", "net")
# Free-flight physics steps before the ball first reaches a surface in an impact experiment.
LEAD_STEPS = 3


# --- set-up ------------------------------------------------------------------------------------
def home_state(cfg: World) -> tuple[np.ndarray, np.ndarray]:
    """qpos [nq], qvel [nv] with the robot at rest at its home pose (ball at its model default)."""
    m = scene.model(cfg)
    ids = scene.ids(m)
    qpos = m.qpos0.copy()
    qpos[ids.robot_qpos] = cfg.robot.home
    return qpos, np.zeros(m.nv)


def surface_face(cfg: World, surface: str) -> tuple[np.ndarray, np.ndarray, float]:
    """The flat face a normal-impact experiment hits: a point on it [3] (where the ball's centre
    line meets it), its outward unit normal [3] and the half-thickness of the slab behind it (m).

    table: the top, near the middle of the thrower's half; net: its +x face, between the table
    top and the tape; paddle: the blade face on the blade's +z side at the home pose.
    """
    if surface not in SURFACES:
        raise ValueError(f"unknown surface {surface!r}; expected one of {SURFACES}")
    t = cfg.table
    if surface == "table":
        return np.array([0.5, 0.0, t.top_z]), np.array([0.0, 0.0, 1.0]), t.thickness / 2
    if surface == "net":
        point = np.array([t.net_thickness / 2, 0.0, t.top_z + 0.08])
        return point, np.array([1.0, 0.0, 0.0]), t.net_thickness / 2
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    d.qpos[:] = home_state(cfg)[0]
    mujoco.mj_forward(m, d)
    g = scene.ids(m).paddle_geom
    normal = d.geom_xmat[g].reshape(3, 3)[:, 2].copy()
    half = cfg.robot.blade_thickness / 2
    return d.geom_xpos[g] + half * normal, normal, half


def ball_states(cfg: World, pos, vel, spin_world=None, quat=None) -> tuple[np.ndarray, np.ndarray]:
    """qpos [B, nq], qvel [B, nv]: the robot at rest at home, the ball at pos [B, 3] with
    velocity vel [B, 3], world angular velocity spin_world [B, 3] (default 0) and orientation
    quat [B, 4] (w, x, y, z; default identity)."""
    m = scene.model(cfg)
    ids = scene.ids(m)
    pos, vel = np.atleast_2d(pos), np.atleast_2d(vel)
    b = len(pos)
    q0, v0 = home_state(cfg)
    qpos, qvel = np.tile(q0, (b, 1)), np.tile(v0, (b, 1))
    quat = np.tile([1.0, 0, 0, 0], (b, 1)) if quat is None else np.asarray(quat, np.float64)
    spin_world = np.zeros((b, 3)) if spin_world is None else np.asarray(spin_world, np.float64)
    # The free joint's angular velocity is in the ball's local frame: w_local = R(q)^T w_world.
    spin_local = np.empty_like(spin_world)
    for i in range(b):
        rot = np.empty(9)
        mujoco.mju_quat2Mat(rot, quat[i])
        spin_local[i] = rot.reshape(3, 3).T @ spin_world[i]
    a, v = ids.ball_qpos, ids.ball_qvel
    qpos[:, a:a + 3], qpos[:, a + 3:a + 7] = pos, quat
    qvel[:, v:v + 3], qvel[:, v + 3:v + 6] = vel, spin_local
    return qpos, qvel


def arrival_phases(n: int) -> np.ndarray:
    """[n] evenly spread sub-step arrival phases in (0, 1)."""
    return (np.arange(n) + 0.5) / n


def impact_states(cfg: World, surface: str, normal_speeds, phases) -> tuple[np.ndarray, np.ndarray]:
    """Normal impacts on `surface`: qpos [N*P, nq], qvel [N*P, nv] (speed-major order) for
    normal_speeds [N] (m/s, toward the face) and arrival phases [P] in (0, 1).

    The ball starts (LEAD_STEPS + phase) steps of flight in front of the face's centre, so the
    first physics step that finds it inside the surface finds it (1 - phase) * v * dt deep.
    """
    point, normal, _ = surface_face(cfg, surface)
    speeds = np.repeat(np.asarray(normal_speeds, np.float64), len(phases))
    ph = np.tile(np.asarray(phases, np.float64), len(normal_speeds))
    gap = cfg.ball.radius + speeds * cfg.physics_dt * (LEAD_STEPS + ph)
    return ball_states(cfg, point + gap[:, None] * normal, -speeds[:, None] * normal)


# --- running -----------------------------------------------------------------------------------
# MJX runs are jit-compiled once for a fixed shape, [MJX_BATCH] throws x MJX_CHUNK control steps,
# and chained: every experiment here (1 s of flight, 40 ms impacts) reuses that one program
# (compiling a batched MJX step is slow on a CPU).
MJX_BATCH = 128
MJX_CHUNK = 4
IMPACT_CONTROL_STEPS = 4   # 40 ms: lead-in, the slowest (2 m/s) contact and the way out
# XLA:CPU's fusion emitters (the default in JAX 0.10) recompute MJX's batched body-tree chain per
# output element, far slower than its older loop emitters for the same physics (figures:
# docs/BENCHMARKS.md, "Third pass"). A compile option of this program only, on the CPU, where this
# XLA knows it (older and newer jaxlibs name no such option: they compile without it).
MJX_CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


@functools.lru_cache(maxsize=1)
def _cpu_compiler_options() -> dict | None:
    """MJX_CPU_COMPILER_OPTIONS if this process computes on a CPU whose XLA accepts them, else None."""
    if jax.default_backend() != "cpu":
        return None
    try:
        jax.jit(lambda x: x + 1, compiler_options=MJX_CPU_COMPILER_OPTIONS).lower(1.0).compile()
    except jax.errors.JaxRuntimeError as e:
        if "compile option" not in str(e):
            raise
        return None
    return MJX_CPU_COMPILER_OPTIONS


@functools.lru_cache(maxsize=4)
def _mjx_runner(physics):
    """jit(vmap) of MJX_CHUNK held-pose control steps of MjxPhysics:
    (qpos [B, nq], qvel [B, nv]) -> (qpos, qvel, ball [B, T, 6], paddle [B, T, 3])."""
    home = jnp.asarray(physics.cfg.robot.home, jnp.float32)

    def one(qpos, qvel):
        def body(c, _):
            qpos, qvel, ball, paddle, _ = physics.step(*c, home, home)
            return (qpos, qvel), (ball, paddle)
        (qpos, qvel), (ball, paddle) = jax.lax.scan(body, (qpos, qvel), None, length=MJX_CHUNK)
        return qpos, qvel, ball.reshape(-1, 6), paddle.reshape(-1, 3)

    return jax.jit(jax.vmap(one), compiler_options=_cpu_compiler_options())


def _mjx_trajectories(physics, qpos, qvel, n_control: int):
    run = _mjx_runner(physics)
    b = len(qpos)
    pad = -b % MJX_BATCH
    qpos = np.concatenate([qpos, np.repeat(qpos[-1:], pad, 0)]).astype(np.float32)
    qvel = np.concatenate([qvel, np.repeat(qvel[-1:], pad, 0)]).astype(np.float32)
    balls, paddles = [], []
    for lo in range(0, len(qpos), MJX_BATCH):
        q, v = jnp.asarray(qpos[lo:lo + MJX_BATCH]), jnp.asarray(qvel[lo:lo + MJX_BATCH])
        bs, ps = [], []
        for _ in range(-(-n_control // MJX_CHUNK)):
            q, v, ball, paddle = run(q, v)
            bs.append(np.asarray(ball)), ps.append(np.asarray(paddle))
        balls.append(np.concatenate(bs, 1)), paddles.append(np.concatenate(ps, 1))
    t = n_control * physics.cfg.substeps
    return (np.concatenate(balls)[:b, :t].astype(np.float64),
            np.concatenate(paddles)[:b, :t].astype(np.float64))


def ball_trajectories(physics, qpos, qvel, n_control: int) -> tuple[np.ndarray, np.ndarray]:
    """Run B throws for n_control control steps with the robot held at home.

    qpos [B, nq], qvel [B, nv] -> (ball [B, T, 6] world position and linear velocity after each
    physics step, paddle [B, T, 3] blade-centre position), T = n_control * cfg.substeps, numpy.
    """
    qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
    if not hasattr(physics, "pool"):
        return _mjx_trajectories(physics, qpos, qvel, n_control)
    home = np.tile(np.asarray(physics.cfg.robot.home, np.float64), (len(qpos), 1))
    balls, paddles = [], []
    for _ in range(n_control):  # MuJoCo C: batched steps through mujoco.rollout
        qpos, qvel, ball, paddle, _ = physics.step(qpos, qvel, home, home)
        balls.append(ball), paddles.append(paddle)
    return np.concatenate(balls, 1), np.concatenate(paddles, 1)


# --- impact measurements -----------------------------------------------------------------------
def impact_outcome(cfg: World, surface: str, ball, paddle) -> dict:
    """Measured outcome of normal impacts on `surface` from trajectories ball [B, T, 6] and
    paddle [B, T, 3] (ball_trajectories of impact_states). Returns numpy arrays [B]:

    cor:     -v_out / v_in of the ball's normal velocity relative to the face; v_in at the first
             state found inside the surface (the contact has not acted yet), v_out at the first
             state after it found outside again (the contact is over). NaN if it never leaves.
    depth:   deepest penetration of the ball into the face (m).
    through: the ball's centre passed the slab's mid-plane at some step (tunnelling).
    """
    point, normal, half = surface_face(cfg, surface)
    ball, paddle = np.asarray(ball), np.asarray(paddle)
    face = np.broadcast_to(point, ball[..., :3].shape).copy()
    face_vel = np.zeros_like(face)
    if surface == "paddle":  # the blade is held by servos; follow it (it barely moves)
        face = face + (paddle - paddle[:, :1])
        face_vel[:, 1:] = np.diff(paddle, axis=1) / cfg.physics_dt
    gap = np.einsum("btk,k->bt", ball[..., :3] - face, normal) - cfg.ball.radius
    vn = np.einsum("btk,k->bt", ball[..., 3:] - face_vel, normal)
    cor = np.full(len(ball), np.nan)
    for i in range(len(ball)):
        inside = np.flatnonzero(gap[i] < 0)
        if inside.size == 0:
            continue
        after = np.flatnonzero(gap[i, inside[0]:] >= 0)
        if after.size:
            cor[i] = -vn[i, inside[0] + after[0]] / vn[i, inside[0]]
    return {"cor": cor, "depth": np.maximum(-gap.min(1), 0.0),
            "through": (gap + cfg.ball.radius + half < 0).any(1)}


def cor_by_phase(physics, surface: str, normal_speeds, phases=16) -> np.ndarray:
    """[N, P] measured COR for each normal speed [N] (m/s) and arrival phase (P = phases)."""
    cfg = physics.cfg
    speeds = np.atleast_1d(np.asarray(normal_speeds, np.float64))
    qpos, qvel = impact_states(cfg, surface, speeds, arrival_phases(phases))
    ball, paddle = ball_trajectories(physics, qpos, qvel, IMPACT_CONTROL_STEPS)
    return impact_outcome(cfg, surface, ball, paddle)["cor"].reshape(len(speeds), phases)


def measure_cor(physics, surface: str, normal_speed: float, phases: int = 16) -> float:
    """Measured COR of `surface` at one normal impact speed (m/s): the mean over `phases`
    evenly spread arrival phases (the expected COR of a ball arriving at that speed)."""
    return float(np.mean(cor_by_phase(physics, surface, [normal_speed], phases)))


# --- free flight -------------------------------------------------------------------------------
def free_flight_throws(cfg: World, seed: int, n: int, spin: bool):
    """n random throws that stay in free flight: pos, vel, spin_world [n, 3] and quat [n, 4].

    They start 2.6-3.6 m beyond the thrower's end of the table, 1.5-3 m up, and fly away from
    the table (vx >= 0) at 2-15 m/s in any other direction, so nothing is within reach for
    1 s. With spin, each axis is uniform in +-cfg.throws.max_spin rad/s and the ball's
    orientation is random (exercising the local-frame angular velocity of the free joint).
    """
    rng = np.random.default_rng(seed)
    pos = np.stack([rng.uniform(4.0, 5.0, n), rng.uniform(-1.0, 1.0, n), rng.uniform(1.5, 3.0, n)], 1)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    direction[:, 0] = np.abs(direction[:, 0])
    vel = direction * rng.uniform(2.0, 15.0, (n, 1))
    if spin:
        w = rng.uniform(-cfg.throws.max_spin, cfg.throws.max_spin, (n, 3))
        quat = rng.normal(size=(n, 4))
        quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    else:
        w, quat = np.zeros((n, 3)), np.tile([1.0, 0, 0, 0], (n, 1))
    return pos, vel, w, quat


def flight_positions(physics, pos, vel, spin_world, quat, n_control: int) -> np.ndarray:
    """[B, T, 3] ball positions after each physics step (T = n_control * substeps) for balls
    launched from pos [B, 3] with velocity vel [B, 3], world angular velocity spin_world [B, 3]
    and orientation quat [B, 4], the robot held at home."""
    qpos, qvel = ball_states(physics.cfg, pos, vel, spin_world, quat)
    return ball_trajectories(physics, qpos, qvel, n_control)[0][..., :3]


def table_throws(cfg: World, seed: int, n: int):
    """n robot-free throws of the project's thrower (cfg.throws), which solves each launch so
    that the ball clears the net and first bounces on the robot's half: pos, vel, spin_world
    [n, 3] and quat [n, 4] for flight_positions."""
    from ttmjx.world import thrower
    th = thrower.sample_throws(jax.random.PRNGKey(seed), cfg, n)
    pos, vel, spin = (np.asarray(x, np.float64) for x in (th.launch_pos, th.launch_vel, th.launch_spin))
    return pos, vel, spin, np.tile([1.0, 0, 0, 0], (n, 1))


def first_bounce(cfg: World, ball) -> dict:
    """First table contact of free throws, from ball [B, T, 6]: numpy arrays [B] of the measured
    normal COR (as impact_outcome) and the contact point x, y (NaN where none)."""
    cor = impact_outcome(cfg, "table", ball, np.zeros(ball.shape[:-1] + (3,)))["cor"]
    gap = ball[..., 2] - cfg.table.top_z - cfg.ball.radius
    first = np.argmax(gap < 0, axis=1)
    xy = ball[np.arange(len(ball)), first, :2]
    xy[~(gap < 0).any(1)] = np.nan
    return {"cor": cor, "x": xy[:, 0], "y": xy[:, 1]}


def net_throws(cfg: World, seed: int, n: int, max_speed: float = 20.0):
    """n balls flying into the net from either side: qpos [n, nq], qvel [n, nv], side [n]
    (+1: from the thrower's side x > 0, -1: from the robot's side).

    Each aims at a point of the net face below the tape (centre 3 cm above the table to 4 cm
    under the tape, |y| <= 0.8 m) at 2..max_speed m/s, up to 60 deg off the net's normal, with
    random spin, and starts (LEAD_STEPS + a random phase) steps of flight before reaching it.
    """
    rng = np.random.default_rng(seed)
    t = cfg.table
    side = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    z = rng.uniform(t.top_z + 0.03, t.top_z + t.net_height - 0.04, n)
    hit = np.stack([side * (t.net_thickness / 2 + cfg.ball.radius), rng.uniform(-0.8, 0.8, n), z], 1)
    off = np.deg2rad(rng.uniform(0.0, 60.0, n))
    roll = rng.uniform(0.0, 2 * np.pi, n)
    direction = np.stack([-side * np.cos(off), np.sin(off) * np.cos(roll), np.sin(off) * np.sin(roll)], 1)
    vel = direction * rng.uniform(2.0, max_speed, (n, 1))
    pos = hit - vel * cfg.physics_dt * (LEAD_STEPS + rng.uniform(0.0, 1.0, (n, 1)))
    spin = rng.uniform(-cfg.throws.max_spin, cfg.throws.max_spin, (n, 3))
    qpos, qvel = ball_states(cfg, pos, vel, spin)
    return qpos, qvel, side


def net_passes(ball, side) -> np.ndarray:
    """[B] bool: the ball's centre reached the net's other side (x past 0) at some step, for
    ball [B, T, 6] of net_throws with their side [B]."""
    return (np.asarray(side)[:, None] * np.asarray(ball)[..., 0] < 0).any(1)

