"""The ball thrower: three launch distributions, launch velocities solved WITH air drag.

Each throw samples a launch position, a launch speed, a spin (zero unless `Throws.spin`) and an
aim point (x, y) on the robot's half (x < 0), then solves the launch direction (yaw, pitch) so
that the ball's first bounce lands on the aim point. The flight model is
`ttmjx.ballphysics.ball_acceleration` (drag and, with spin, Magnus; identical to MuJoCo's
ellipsoid fluid model of the sphere) integrated exactly like MuJoCo's Euler integrator at
`cfg.physics_dt`:

    v += a(v, w) dt;   w += (torque / I) dt;   x += v dt

so MuJoCo C reproduces the predicted bounce up to float32 rounding. The first bounce is where the
ball's centre first drops through the table-top height plus the radius (the ball's bottom touches
the table: MuJoCo's contact starts there), interpolated linearly between physics steps.

The solve is a fixed number of Newton steps on (yaw, pitch) at the sampled speed, the Jacobian by
forward-mode differentiation through the flight (`lax.while_loop`), so `sample_throws` is
jittable (cfg and n static) and vmappable over keys. A sampled speed cannot reach every aim point
while clearing the net (a fast ball cannot drop onto a short aim on a low arc), so every throw
draws `Throws.candidates` independent candidates and keeps the first valid one: converged to
within `Throws.solve_tol` of its aim, the ball's bottom at least `Throws.net_margin` above the net
tape. The result is the box distribution conditioned on valid throws; the distributions'
defaults are chosen so that most candidates are valid (`acceptance` measures it).

Distributions (`Throws.name`; numbers in config.Throws):

* narrow: one launch position, speed uniform in a narrow range, aim uniform in a forehand
  region of the robot's half.
* any:    launch position uniform in a box behind the opponent's end line, speed 5-9 m/s, aim
  anywhere on the robot's half (a margin from the edges).
* varied: launch x cycled through three positions by throw index (y, z fixed), fixed speed; the
  thrower's yaw is swept uniformly and the aim lies on the yawed line at a sampled depth.

Frame: docs/DESIGN.md (robot at x < 0, thrower at x > 1.37, table top z = 0.76, net at x = 0).
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ttmjx import ballphysics, scene
from ttmjx.config import THROW_DISTRIBUTIONS, World


class Throw(NamedTuple):
    """A batch of throws (leading dims [...]); world frame, SI units."""
    launch_pos: jax.Array    # [..., 3] ball centre at launch (m)
    launch_vel: jax.Array    # [..., 3] (m/s)
    launch_spin: jax.Array   # [..., 3] world angular velocity at launch (rad/s)
    aim: jax.Array           # [..., 2] intended first bounce (x, y) on the robot's half


class _Flight(NamedTuple):
    bounce: jax.Array     # [2] first-bounce (x, y)
    clearance: jax.Array  # ball bottom above the net tape while over the net (m); -inf-ish if never
    landed: jax.Array     # bool: the ball reached the table height within the time limit
    time: jax.Array       # flight time to the bounce (s)


_FAR_BELOW = -10.0


def _check(cfg: World, n) -> None:
    name = cfg.throws.name
    if name not in THROW_DISTRIBUTIONS:
        raise ValueError(f"unknown throw distribution {name!r}; expected one of {THROW_DISTRIBUTIONS}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n (number of throws) must be an integer >= 1, got {n!r}")


# --------------------------------------------------------------------------------------------
# Flight model
# --------------------------------------------------------------------------------------------

def _fly(cfg: World, pos, vel, spin) -> _Flight:
    """Fly one ball from launch to its first bounce (or the time limit)."""
    b, tab, th = cfg.ball, cfg.table, cfg.throws
    dt = cfg.physics_dt
    h_bounce = tab.top_z + b.radius
    net_w = tab.net_thickness / 2 + b.radius           # |x| where the ball can touch the net
    net_top = tab.top_z + tab.net_height + b.radius    # ball centre height at the net tape
    inv_inertia = 1.0 / b.hollow_inertia
    max_steps = int(math.ceil(th.max_flight_s / dt))

    def cross(p0, p1, c0, c1, level):
        frac = (c0 - level) / jnp.where(c0 - c1 == 0.0, 1.0, c0 - c1)
        return p0 + frac * (p1 - p0)

    def cond(c):
        k, _, _, _, _, _, _, done, _ = c
        return (k < max_steps) & ~done

    def body(c):
        k, x, v, w, bounce, z_in, z_out, done, t = c
        force, torque = ballphysics.air_force_torque(v, w, b)
        v1 = v + (force / b.mass + jnp.array([0.0, 0.0, -9.81], v.dtype)) * dt
        w1 = w + torque * inv_inertia * dt
        x1 = x + v1 * dt
        # Net crossings: the ball's centre height where it enters/leaves the net's x band.
        hit_in = (x[0] > net_w) & (x1[0] <= net_w)
        hit_out = (x[0] > -net_w) & (x1[0] <= -net_w)
        z_in = jnp.where(hit_in, cross(x[2], x1[2], x[0], x1[0], net_w), z_in)
        z_out = jnp.where(hit_out, cross(x[2], x1[2], x[0], x1[0], -net_w), z_out)
        land = (x[2] >= h_bounce) & (x1[2] < h_bounce)
        frac = (x[2] - h_bounce) / jnp.where(land, x[2] - x1[2], 1.0)
        bounce = jnp.where(land, x[:2] + frac * (x1[:2] - x[:2]), bounce)
        t = jnp.where(land, (k + frac) * dt, t)
        return k + 1, x1, v1, w1, bounce, z_in, z_out, done | land, t

    dtype = vel.dtype
    init = (jnp.int32(0), pos, vel, spin, pos[:2], jnp.asarray(_FAR_BELOW, dtype),
            jnp.asarray(_FAR_BELOW, dtype), jnp.array(False), jnp.asarray(0.0, dtype))
    _, _, _, _, bounce, z_in, z_out, done, t = jax.lax.while_loop(cond, body, init)
    clearance = jnp.minimum(z_in, z_out) - net_top
    return _Flight(bounce=bounce, clearance=clearance, landed=done, time=t)


def _direction(yaw, pitch):
    """Unit launch direction: yaw 0 points along -x (toward the robot), positive yaw turns
    toward -y; pitch is the elevation."""
    return jnp.stack([-jnp.cos(pitch) * jnp.cos(yaw), -jnp.cos(pitch) * jnp.sin(yaw), jnp.sin(pitch)])


def _newton(fn, u0, iters: int, max_step, lo, hi):
    """Fixed-iteration Newton on fn(u) -> residual [m] (m unknowns), Jacobian by forward mode;
    steps clipped to max_step, iterates to [lo, hi]. A tiny Levenberg term keeps a singular
    Jacobian finite."""
    m = u0.shape[0]

    def body(_, u):
        jac, r = jax.jacfwd(lambda v: (lambda res: (res, res))(fn(v)), has_aux=True)(u)
        du = -jnp.linalg.solve(jac.T @ jac + 1e-6 * jnp.eye(m, dtype=u.dtype), jac.T @ r)
        return jnp.clip(u + jnp.clip(du, -max_step, max_step), lo, hi)

    return jax.lax.fori_loop(0, iters, body, u0)


_ANGLE_STEP = 0.15      # rad per Newton step
_SPEED_STEP = 1.5       # m/s per Newton step
_YAW_RANGE = (-1.2, 1.2)
_PITCH_RANGE = (-0.4, None)   # upper: max_pitch + _PITCH_SLACK
_PITCH_SLACK = 0.2
_SPEED_RANGE = (1.0, 30.0)
_NET_PAD = 0.01         # the fastest `any` speed clears the net by net_margin + this


def _landing_z(cfg: World):
    return cfg.table.top_z + cfg.ball.radius


def _guess_direction(cfg: World, pos, speed, aim):
    """Drag-free low-arc (yaw, pitch) at a drag-reduced speed (a start for Newton)."""
    g = 9.81
    dx, dy = aim[0] - pos[0], aim[1] - pos[1]
    yaw = jnp.arctan2(-dy, -dx)
    d = jnp.hypot(dx, dy)
    rise = _landing_z(cfg) - pos[2]
    s2 = (0.85 * speed) ** 2
    disc = s2 * s2 - g * (g * d * d + 2.0 * rise * s2)
    pitch = jnp.where(disc > 0.0, jnp.arctan((s2 - jnp.sqrt(jnp.maximum(disc, 0.0))) / (g * d)),
                      cfg.throws.max_pitch)
    return jnp.stack([yaw, jnp.clip(pitch, _PITCH_RANGE[0], cfg.throws.max_pitch)])


def _solve_direction(cfg: World, pos, speed, spin, aim, p0):
    """(yaw, pitch) at a given speed so that the first bounce is the aim."""
    hi_pitch = cfg.throws.max_pitch + _PITCH_SLACK
    fn = lambda p: _fly(cfg, pos, speed * _direction(p[0], p[1]), spin).bounce - aim
    return _newton(fn, p0, cfg.throws.newton_iters, _ANGLE_STEP,
                   jnp.array([_YAW_RANGE[0], _PITCH_RANGE[0]]), jnp.array([_YAW_RANGE[1], hi_pitch]))


def _fastest(cfg: World, pos, spin, aim):
    """(yaw, pitch, speed) of the fastest low arc to the aim that still clears the net by
    net_margin + _NET_PAD."""
    t, th = cfg.table, cfg.throws
    g = 9.81
    target = th.net_margin + _NET_PAD
    # Drag-free parabola through the launch point, the net point and the aim.
    dx, dy = aim[0] - pos[0], aim[1] - pos[1]
    d = jnp.hypot(dx, dy)
    s_net = d * pos[0] / (pos[0] - aim[0])
    z_net = t.top_z + t.net_height + cfg.ball.radius + target - pos[2]
    z_aim = _landing_z(cfg) - pos[2]
    b = jnp.maximum((z_net / s_net - z_aim / d) / (d - s_net), 0.05)
    a = z_net / s_net + b * s_net
    vh = jnp.sqrt(g / (2.0 * b)) * 1.1
    u0 = jnp.stack([jnp.arctan2(-dy, -dx), jnp.arctan(a), vh * jnp.sqrt(1.0 + a * a)])

    def fn(u):
        fl = _fly(cfg, pos, u[2] * _direction(u[0], u[1]), spin)
        return jnp.concatenate([fl.bounce - aim, (fl.clearance - target)[None]])

    return _newton(fn, u0, th.newton_iters, jnp.array([_ANGLE_STEP, _ANGLE_STEP, _SPEED_STEP]),
                   jnp.array([_YAW_RANGE[0], _PITCH_RANGE[0], _SPEED_RANGE[0]]),
                   jnp.array([_YAW_RANGE[1], th.max_pitch + _PITCH_SLACK, _SPEED_RANGE[1]]))


def _slowest(cfg: World, pos, spin, aim):
    """(yaw, speed) of the low arc to the aim launched at the highest elevation, max_pitch."""
    th = cfg.throws
    g = 9.81
    dx, dy = aim[0] - pos[0], aim[1] - pos[1]
    d = jnp.hypot(dx, dy)
    z_aim = _landing_z(cfg) - pos[2]
    c = jnp.cos(th.max_pitch)
    v2 = g * d * d / (2.0 * c * c * jnp.maximum(d * jnp.tan(th.max_pitch) - z_aim, 0.1))
    u0 = jnp.stack([jnp.arctan2(-dy, -dx), 1.1 * jnp.sqrt(v2)])
    fn = lambda u: _fly(cfg, pos, u[1] * _direction(u[0], th.max_pitch), spin).bounce - aim
    return _newton(fn, u0, th.newton_iters, jnp.array([_ANGLE_STEP, _SPEED_STEP]),
                   jnp.array([_YAW_RANGE[0], _SPEED_RANGE[0]]), jnp.array([_YAW_RANGE[1], _SPEED_RANGE[1]]))


def _solve_fixed_speed(cfg: World, pos, speed, spin, aim, frac):
    del frac
    p = _solve_direction(cfg, pos, speed, spin, aim, _guess_direction(cfg, pos, speed, aim))
    return speed, p


def _solve_speed_range(cfg: World, pos, lo_hi, spin, aim, frac):
    """Speed at fraction `frac` of the feasible low-arc speed range [slowest, fastest]
    intersected with lo_hi, then the direction at that speed."""
    th = cfg.throws
    fast = _fastest(cfg, pos, spin, aim)
    slow = _slowest(cfg, pos, spin, aim)
    lo = jnp.maximum(lo_hi[0], slow[1])
    hi = jnp.minimum(lo_hi[1], fast[2])
    speed = jnp.clip(lo + frac * jnp.maximum(hi - lo, 0.0), lo_hi[0], lo_hi[1])
    # Start between the two bounding arcs, by speed.
    w = jnp.clip((fast[2] - speed) / jnp.maximum(fast[2] - slow[1], 1e-3), 0.0, 1.0)
    p0 = jnp.stack([fast[0] + w * (slow[0] - fast[0]), fast[1] + w * (th.max_pitch - fast[1])])
    return speed, _solve_direction(cfg, pos, speed, spin, aim, p0)


# --------------------------------------------------------------------------------------------
# Distributions
# --------------------------------------------------------------------------------------------

def _uniform(key, lo_hi, shape):
    lo, hi = lo_hi
    return jax.random.uniform(key, shape, minval=lo, maxval=hi)


def _candidates(key, cfg: World, n: int):
    """Launch position [n, K, 3], speed [n, K] (for `any`, a fraction of the feasible range),
    spin [n, K, 3], aim [n, K, 2]."""
    th = cfg.throws
    shape = (n, th.candidates)
    ks = jax.random.split(key, 8)
    if th.name == "narrow":
        pos = jnp.broadcast_to(jnp.array(th.narrow_launch, jnp.float32), shape + (3,))
        speed = _uniform(ks[0], th.narrow_speed, shape)
        aim = jnp.stack([_uniform(ks[1], th.narrow_aim_x, shape), _uniform(ks[2], th.narrow_aim_y, shape)], -1)
    elif th.name == "any":
        pos = jnp.stack([_uniform(ks[0], th.any_launch_x, shape), _uniform(ks[1], th.any_launch_y, shape),
                         _uniform(ks[2], th.any_launch_z, shape)], -1)
        speed = _uniform(ks[3], (0.0, 1.0), shape)
        aim = jnp.stack([_uniform(ks[4], th.any_aim_x, shape), _uniform(ks[5], th.any_aim_y, shape)], -1)
    else:  # varied
        xs = jnp.array(th.varied_launch_x, jnp.float32)
        lx = jnp.broadcast_to(xs[jnp.arange(n) % xs.shape[0]][:, None], shape)
        ly = jnp.full(shape, th.varied_launch_yz[0], jnp.float32)
        lz = jnp.full(shape, th.varied_launch_yz[1], jnp.float32)
        pos = jnp.stack([lx, ly, lz], -1)
        speed = jnp.full(shape, th.varied_speed, jnp.float32)
        yaw = _uniform(ks[0], th.varied_yaw_deg, shape) * (math.pi / 180.0)
        dist = _uniform(ks[1], th.varied_distance, shape)
        # The aim on the thrower's yawed line (the yaw convention of _direction).
        aim = jnp.stack([lx - dist * jnp.cos(yaw), ly - dist * jnp.sin(yaw)], -1)
    if th.spin:
        spin = _uniform(ks[6], (-th.max_spin, th.max_spin), shape + (3,))
    else:
        spin = jnp.zeros(shape + (3,), jnp.float32)
    return pos, speed, spin, aim


def _valid(cfg: World, fl: _Flight, aim):
    th, tab = cfg.throws, cfg.table
    err = jnp.linalg.norm(fl.bounce - aim, axis=-1)
    on_half = ((fl.bounce[..., 0] < 0.0) & (fl.bounce[..., 0] > -tab.half_length)
               & (jnp.abs(fl.bounce[..., 1]) < tab.half_width))
    return fl.landed & (err < th.solve_tol) & (fl.clearance >= th.net_margin) & on_half, err


@functools.partial(jax.jit, static_argnums=(1, 2))
def _sample(key, cfg: World, n: int):
    th = cfg.throws
    pos, speed, spin, aim = _candidates(key, cfg, n)
    if th.name == "any":
        solve = functools.partial(_solve_speed_range, cfg, lo_hi=th.any_speed)
        speed, p = jax.vmap(jax.vmap(lambda *a: solve(a[0], spin=a[2], aim=a[3], frac=a[1])))(pos, speed, spin, aim)
    else:
        speed, p = jax.vmap(jax.vmap(functools.partial(_solve_fixed_speed, cfg)))(pos, speed, spin, aim, speed)
    vel = speed[..., None] * jax.vmap(jax.vmap(_direction))(p[..., 0], p[..., 1])
    fl = jax.vmap(jax.vmap(functools.partial(_fly, cfg)))(pos, vel, spin)
    valid, err = _valid(cfg, fl, aim)
    k = th.candidates
    # The first valid candidate; if none is valid, the least bad one.
    badness = err + jnp.maximum(th.net_margin - fl.clearance, 0.0) + jnp.where(fl.landed, 0.0, 10.0)
    cost = jnp.where(valid, jnp.arange(k, dtype=jnp.float32)[None, :], k + badness)
    idx = jnp.argmin(cost, axis=1)
    pick = lambda a: jnp.take_along_axis(a, idx.reshape((n, 1) + (1,) * (a.ndim - 2)), axis=1)[:, 0]
    throw = Throw(launch_pos=pick(pos), launch_vel=pick(vel), launch_spin=pick(spin), aim=pick(aim))
    info = {"valid": pick(valid), "error": pick(err), "clearance": pick(fl.clearance),
            "flight_time": pick(fl.time), "acceptance": jnp.mean(valid.astype(jnp.float32))}
    return throw, info


def sample_throws(key, cfg: World, n: int) -> Throw:
    """n throws [n, ...] from the distribution cfg.throws.name; deterministic per key.

    Jittable with cfg and n static (`jax.jit(sample_throws, static_argnums=(1, 2))`) and
    vmappable over keys. For `varied`, throw i launches from varied_launch_x[i % 3].
    Raises ValueError for an unknown distribution name or n < 1.
    """
    _check(cfg, n)
    return _sample(key, cfg, int(n))[0]


def sample_throws_info(key, cfg: World, n: int) -> tuple[Throw, dict]:
    """sample_throws plus diagnostics: per-throw `valid`, predicted `error` (m), net
    `clearance` (m), `flight_time` (s), and the candidates' `acceptance` rate."""
    _check(cfg, n)
    return _sample(key, cfg, int(n))


@functools.partial(jax.jit, static_argnums=(1,))
def _first_bounce(throw: Throw, cfg: World):
    lead = throw.launch_pos.shape[:-1]
    flat = lambda a: jnp.reshape(jnp.asarray(a, jnp.float32), (-1, a.shape[-1]))
    fl = jax.vmap(functools.partial(_fly, cfg))(flat(throw.launch_pos), flat(throw.launch_vel),
                                                 flat(throw.launch_spin))
    return fl.bounce.reshape(lead + (2,))


def first_bounce(throw: Throw, cfg: World):
    """[..., 2] first-bounce (x, y) of the throws predicted by the flight model."""
    return _first_bounce(throw, cfg)


# --------------------------------------------------------------------------------------------
# MuJoCo C check
# --------------------------------------------------------------------------------------------

def simulate(cfg: World, throw: Throw, chunk: int = 256) -> dict:
    """Fly the throws in MuJoCo C (scene.model(cfg), its ellipsoid fluid model; the robot held at
    its reference pose) up to the first table contact.

    Returns numpy arrays: `bounce` [n, 2] (the ball's centre crossing table height + radius,
    interpolated between physics steps: where MuJoCo's ball-table contact starts), `bounced`
    [n] (that contact happened and sent the ball back up), `clearance` [n] (lowest height of the
    ball's bottom above the net tape while over the net, m).
    """
    from mujoco import rollout

    m = scene.model(cfg, fluid=True)
    ids = scene.ids(m)
    tab, r = cfg.table, cfg.ball.radius
    h = tab.top_z + r
    net_w = tab.net_thickness / 2 + r
    net_top = tab.top_z + tab.net_height + r
    pos = np.asarray(throw.launch_pos, np.float64).reshape(-1, 3)
    vel = np.asarray(throw.launch_vel, np.float64).reshape(-1, 3)
    spin = np.asarray(throw.launch_spin, np.float64).reshape(-1, 3)
    n = pos.shape[0]
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(m, spec)
    q0 = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_TIME)
    v0 = q0 + m.nq
    bq, bv = ids.ball_qpos, ids.ball_qvel
    d = mujoco.MjData(m)
    nstep = int(math.ceil(cfg.throws.max_flight_s / cfg.physics_dt)) + 40
    out = {"bounce": np.full((n, 2), np.nan), "bounced": np.zeros(n, bool), "clearance": np.full(n, np.nan)}
    with rollout.Rollout(nthread=1) as pool:
        for s in range(0, n, chunk):
            e = min(n, s + chunk)
            init = np.zeros((e - s, nstate))
            for i in range(s, e):
                mujoco.mj_resetData(m, d)
                d.qpos[bq:bq + 7] = np.concatenate([pos[i], [1.0, 0.0, 0.0, 0.0]])
                d.qvel[bv:bv + 6] = np.concatenate([vel[i], spin[i]])
                mujoco.mj_getState(m, d, init[i - s], spec)
            states, _ = pool.rollout(m, [d], init, nstep=nstep)
            for j, i in enumerate(range(s, e)):
                xyz = np.concatenate([init[j:j + 1, q0 + bq:q0 + bq + 3], states[j, :, q0 + bq:q0 + bq + 3]])
                vz = states[j, :, v0 + bv + 2]
                below = np.nonzero(xyz[:, 2] < h)[0]
                over_net = np.abs(xyz[:, 0]) <= net_w
                if below.size:
                    k = below[0]
                    frac = (xyz[k - 1, 2] - h) / (xyz[k - 1, 2] - xyz[k, 2])
                    out["bounce"][i] = xyz[k - 1, :2] + frac * (xyz[k, :2] - xyz[k - 1, :2])
                    # states[k - 1] is xyz[k]: the ball is sent back up within a few steps.
                    out["bounced"][i] = bool(np.any(vz[k - 1:k + 30] > 0.0))
                    over_net[k:] = False
                zs = xyz[over_net, 2]
                out["clearance"][i] = zs.min() - net_top if zs.size else -np.inf
    return out


def throw_report(cfg: World, n: int, seed: int) -> dict:
    """JSON-ready report of n throws: launch state, aim, and the first bounce simulated in
    MuJoCo C (scene.model(cfg))."""
    _check(cfg, n)
    throw = jax.tree.map(np.asarray, sample_throws(jax.random.PRNGKey(seed), cfg, n))
    sim = simulate(cfg, throw)
    fl = lambda a: [float(x) for x in a]
    return {"frame": cfg.frame(),
            "throws": [{"launch_pos": fl(throw.launch_pos[i]), "launch_vel": fl(throw.launch_vel[i]),
                        "launch_spin": fl(throw.launch_spin[i]), "aim": fl(throw.aim[i]),
                        "bounce": fl(sim["bounce"][i])} for i in range(n)]}
