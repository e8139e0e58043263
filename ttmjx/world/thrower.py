"""The ball thrower: three launch distributions, launch velocities solved WITH air drag.

Flight model. `ttmjx.world.ballphysics` (drag and, with spin, Magnus; identical to MuJoCo's ellipsoid
fluid model of the sphere) integrated exactly like MuJoCo's Euler integrator at cfg.physics_dt:

    v += a(v, w) dt;   w += (torque / I) dt;   x += v dt

(the spin stays parallel to itself, so the ball-frame angular velocity MuJoCo stores equals the
world spin throughout). MuJoCo C reproduces the predicted first bounce to float32 rounding
(micrometres). The first bounce is where the ball's centre first drops through table height +
radius, i.e. where MuJoCo's ball-table contact starts, interpolated linearly between physics steps.

Solve. A throw samples a launch position, a spin (zero unless `Throws.spin`), an aim (x, y) on
the robot's half and a speed fraction f in [0, 1). Three fixed-iteration Newton solves through the
flight (forward-mode Jacobians through a `lax.while_loop`) then give

1. the fastest low arc to the aim that still clears the net by net_margin + 1 cm,
2. the slowest: the arc launched at the highest elevation `max_pitch`,
3. the launch direction (yaw, pitch) at speed lo + f (hi - lo), where [lo, hi] is the
   distribution's speed range intersected with [slowest, fastest]; the two bounding arcs give
   the starting point.

A throw is valid if its predicted bounce is within `solve_tol` of the aim on the robot's half
and the ball's bottom clears the net tape by `net_margin`. An invalid candidate (an aim that no
speed in the range reaches on a low arc, e.g. a fast ball onto a short aim, or strong lifting
spin at a fixed speed) is redrawn from the throw's own key, up to `candidates` times (then the
least bad one is kept; `sample_throws_info` reports it). So each distribution is its box
conditioned on valid throws; for narrow and any the speed is uniform over the feasible part of
its range. Throw i depends only on (key, i): a longer batch extends a shorter one.

Distributions (`Throws.name`; numbers in config.Throws):

* narrow: one launch position, speed in a narrow range, aim uniform in a forehand region.
* any:    launch uniform in a box behind the opponent's end line, speed in 5-9 m/s, aim
  anywhere on the robot's half (a margin from the edges).
* varied: launch x = varied_launch_x[i % 3] (y, z fixed), fixed speed; the thrower's yaw is
  swept uniformly and the aim lies on the yawed line at a sampled horizontal distance.

All distribution numbers enter the compiled program as arrays, so one compilation (per n and
ball/table/solver settings) serves every distribution, spin on or off.
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

from ttmjx.world import ballphysics, scene
from ttmjx.world.config import THROW_DISTRIBUTIONS, Ball, Table, World

GRAVITY = 9.81


class Throw(NamedTuple):
    """A batch of throws (leading dims [...]); world frame, SI units."""
    launch_pos: jax.Array    # [..., 3] ball centre at launch (m)
    launch_vel: jax.Array    # [..., 3] (m/s)
    launch_spin: jax.Array   # [..., 3] world angular velocity at launch (rad/s)
    aim: jax.Array           # [..., 2] intended first bounce (x, y) on the robot's half


class _Spec(NamedTuple):
    """Static (hashable) settings that shape the compiled solver."""
    ball: Ball
    table: Table
    dt: float
    newton_iters: int
    max_pitch: float
    net_margin: float
    solve_tol: float
    max_steps: int
    candidates: int


class _Flight(NamedTuple):
    bounce: jax.Array     # [2] first-bounce (x, y)
    clearance: jax.Array  # the ball's bottom above the net tape while over the net (m)
    landed: jax.Array     # bool: the ball reached table height within the time limit
    time: jax.Array       # flight time to the bounce (s)


_FAR_BELOW = -10.0      # "no net crossing recorded"
_ANGLE_STEP = 0.15      # rad per Newton step
_SPEED_STEP = 1.5       # m/s per Newton step
_YAW = (-1.2, 1.2)      # rad: Newton's box
_PITCH_LOW = -0.4
_PITCH_SLACK = 0.2      # Newton's pitch box ends at max_pitch + this
_SPEED = (1.0, 30.0)
_NET_PAD = 0.01         # the fastest arc clears the net by net_margin + this


def _spec(cfg: World) -> _Spec:
    th = cfg.throws
    return _Spec(ball=cfg.ball, table=cfg.table, dt=float(cfg.physics_dt), newton_iters=int(th.newton_iters),
                 max_pitch=float(th.max_pitch), net_margin=float(th.net_margin), solve_tol=float(th.solve_tol),
                 max_steps=int(math.ceil(th.max_flight_s / cfg.physics_dt)), candidates=int(th.candidates))


def _check(cfg: World, n) -> None:
    name = cfg.throws.name
    if name not in THROW_DISTRIBUTIONS:
        raise ValueError(f"unknown throw distribution {name!r}; expected one of {THROW_DISTRIBUTIONS}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n (number of throws) must be an integer >= 1, got {n!r}")


# --------------------------------------------------------------------------------------------
# Flight model
# --------------------------------------------------------------------------------------------

def _fly(sp: _Spec, pos, vel, spin) -> _Flight:
    """Fly one ball from launch to its first bounce (or the time limit)."""
    b, tab, dt = sp.ball, sp.table, sp.dt
    h_bounce = tab.top_z + b.radius
    net_w = tab.net_thickness / 2 + b.radius           # |x| within which the ball can touch the net
    net_top = tab.top_z + tab.net_height + b.radius    # ball-centre height at the net tape
    inv_inertia = 1.0 / b.hollow_inertia
    gravity = jnp.array([0.0, 0.0, -GRAVITY], vel.dtype)

    def level_cross(x0, x1, c0, c1, level):
        """x interpolated where c passes `level` between steps."""
        return x0 + (c0 - level) / jnp.where(c0 == c1, 1.0, c0 - c1) * (x1 - x0)

    def cond(c):
        return (c[0] < sp.max_steps) & ~c[7]

    def body(c):
        k, x, v, w, bounce, z_in, z_out, done, t = c
        force, torque = ballphysics.air_force_torque(v, w, b)
        v1 = v + (force / b.mass + gravity) * dt
        w1 = w + torque * inv_inertia * dt
        x1 = x + v1 * dt
        # The ball-centre height where it enters / leaves the net's x band.
        z_in = jnp.where((x[0] > net_w) & (x1[0] <= net_w), level_cross(x[2], x1[2], x[0], x1[0], net_w), z_in)
        z_out = jnp.where((x[0] > -net_w) & (x1[0] <= -net_w), level_cross(x[2], x1[2], x[0], x1[0], -net_w), z_out)
        land = (x[2] >= h_bounce) & (x1[2] < h_bounce)
        frac = (x[2] - h_bounce) / jnp.where(land, x[2] - x1[2], 1.0)
        bounce = jnp.where(land, x[:2] + frac * (x1[:2] - x[:2]), bounce)
        t = jnp.where(land, (k + frac) * dt, t)
        return k + 1, x1, v1, w1, bounce, z_in, z_out, done | land, t

    dtype = vel.dtype
    far = jnp.asarray(_FAR_BELOW, dtype)
    init = (jnp.int32(0), pos, vel, spin, pos[:2], far, far, jnp.array(False), jnp.asarray(0.0, dtype))
    _, _, _, _, bounce, z_in, z_out, done, t = jax.lax.while_loop(cond, body, init)
    # Between the two crossings the arc is (nearly) a parabola: its lowest point is an end.
    return _Flight(bounce=bounce, clearance=jnp.minimum(z_in, z_out) - net_top, landed=done, time=t)


def _direction(yaw, pitch):
    """Unit launch direction: yaw 0 points along -x (toward the robot), positive yaw turns
    toward -y; pitch is the elevation."""
    return jnp.stack([-jnp.cos(pitch) * jnp.cos(yaw), -jnp.cos(pitch) * jnp.sin(yaw), jnp.sin(pitch)])


# --------------------------------------------------------------------------------------------
# Launch solve
# --------------------------------------------------------------------------------------------

def _newton(fn, u0, iters: int, max_step, lo, hi):
    """Fixed-iteration Newton on fn(u) -> residual [m] with m unknowns; forward-mode Jacobian,
    steps clipped to max_step and iterates to [lo, hi]. A tiny Levenberg term keeps a singular
    Jacobian finite."""
    m = u0.shape[0]

    def body(_, u):
        jac, r = jax.jacfwd(lambda v: (lambda res: (res, res))(fn(v)), has_aux=True)(u)
        du = -jnp.linalg.solve(jac.T @ jac + 1e-6 * jnp.eye(m, dtype=u.dtype), jac.T @ r)
        return jnp.clip(u + jnp.clip(du, -max_step, max_step), lo, hi)

    return jax.lax.fori_loop(0, iters, body, u0)


def _fastest(sp: _Spec, pos, spin, aim):
    """(yaw, pitch, speed) of the fastest low arc to the aim that still clears the net by
    net_margin + _NET_PAD. Starts from the drag-free parabola through the net point."""
    t = sp.table
    target = sp.net_margin + _NET_PAD
    dx, dy = aim[0] - pos[0], aim[1] - pos[1]
    d = jnp.hypot(dx, dy)
    s_net = d * pos[0] / (pos[0] - aim[0])                 # horizontal distance to the net
    z_net = t.top_z + t.net_height + sp.ball.radius + target - pos[2]
    z_aim = t.top_z + sp.ball.radius - pos[2]
    curv = jnp.maximum((z_net / s_net - z_aim / d) / (d - s_net), 0.05)   # z = a s - curv s^2
    slope = z_net / s_net + curv * s_net
    vh = 1.1 * jnp.sqrt(GRAVITY / (2.0 * curv))            # 1.1: drag
    u0 = jnp.stack([jnp.arctan2(-dy, -dx), jnp.arctan(slope), vh * jnp.sqrt(1.0 + slope * slope)])

    def fn(u):
        fl = _fly(sp, pos, u[2] * _direction(u[0], u[1]), spin)
        return jnp.concatenate([fl.bounce - aim, (fl.clearance - target)[None]])

    return _newton(fn, u0, sp.newton_iters, jnp.array([_ANGLE_STEP, _ANGLE_STEP, _SPEED_STEP]),
                   jnp.array([_YAW[0], _PITCH_LOW, _SPEED[0]]),
                   jnp.array([_YAW[1], sp.max_pitch + _PITCH_SLACK, _SPEED[1]]))


def _slowest(sp: _Spec, pos, spin, aim):
    """(yaw, speed) of the arc to the aim launched at the highest elevation, max_pitch."""
    dx, dy = aim[0] - pos[0], aim[1] - pos[1]
    d = jnp.hypot(dx, dy)
    z_aim = sp.table.top_z + sp.ball.radius - pos[2]
    c = math.cos(sp.max_pitch)
    v2 = GRAVITY * d * d / (2.0 * c * c * jnp.maximum(d * math.tan(sp.max_pitch) - z_aim, 0.1))
    u0 = jnp.stack([jnp.arctan2(-dy, -dx), 1.1 * jnp.sqrt(v2)])
    fn = lambda u: _fly(sp, pos, u[1] * _direction(u[0], sp.max_pitch), spin).bounce - aim
    return _newton(fn, u0, sp.newton_iters, jnp.array([_ANGLE_STEP, _SPEED_STEP]),
                   jnp.array([_YAW[0], _SPEED[0]]), jnp.array([_YAW[1], _SPEED[1]]))


def _solve(sp: _Spec, pos, speed_range, frac, spin, aim):
    """Launch velocity [3] for one throw (see the module docstring)."""
    fast = _fastest(sp, pos, spin, aim)
    slow = _slowest(sp, pos, spin, aim)
    lo = jnp.maximum(speed_range[0], slow[1])
    hi = jnp.minimum(speed_range[1], fast[2])
    speed = jnp.clip(lo + frac * jnp.maximum(hi - lo, 0.0), speed_range[0], speed_range[1])
    # Start between the two bounding arcs, by speed.
    w = jnp.clip((fast[2] - speed) / jnp.maximum(fast[2] - slow[1], 1e-3), 0.0, 1.0)
    p0 = jnp.stack([fast[0] + w * (slow[0] - fast[0]), fast[1] + w * (sp.max_pitch - fast[1])])
    fn = lambda p: _fly(sp, pos, speed * _direction(p[0], p[1]), spin).bounce - aim
    p = _newton(fn, p0, sp.newton_iters, _ANGLE_STEP, jnp.array([_YAW[0], _PITCH_LOW]),
                jnp.array([_YAW[1], sp.max_pitch + _PITCH_SLACK]))
    return speed * _direction(p[0], p[1])


# --------------------------------------------------------------------------------------------
# Distributions
# --------------------------------------------------------------------------------------------

def _params(cfg: World) -> dict:
    """The distribution's numbers as arrays (traced, so every distribution shares one program)."""
    th = cfg.throws
    f = lambda *x: jnp.asarray(np.array(x, np.float32))
    varied = th.name == "varied"
    if th.name == "narrow":
        launch_lo = launch_hi = th.narrow_launch
        speed, aim_x, aim_y = th.narrow_speed, th.narrow_aim_x, th.narrow_aim_y
    elif th.name == "any":
        launch_lo = (th.any_launch_x[0], th.any_launch_y[0], th.any_launch_z[0])
        launch_hi = (th.any_launch_x[1], th.any_launch_y[1], th.any_launch_z[1])
        speed, aim_x, aim_y = th.any_speed, th.any_aim_x, th.any_aim_y
    else:
        launch_lo = launch_hi = (0.0,) + tuple(th.varied_launch_yz)
        speed, aim_x, aim_y = (th.varied_speed, th.varied_speed), (0.0, 0.0), (0.0, 0.0)
    return {"varied": jnp.asarray(varied), "launch_lo": f(*launch_lo), "launch_hi": f(*launch_hi),
            "speed": f(*speed), "aim_lo": f(aim_x[0], aim_y[0]), "aim_hi": f(aim_x[1], aim_y[1]),
            "varied_x": f(*th.varied_launch_x), "yaw": f(*th.varied_yaw_deg) * (math.pi / 180.0),
            "distance": f(*th.varied_distance), "max_spin": f(th.max_spin if th.spin else 0.0)}


def _candidate(prm: dict, key, i):
    """One candidate for throw i: launch pos [3], speed fraction, spin [3], aim [2]."""
    k_pos, k_aim, k_frac, k_spin = jax.random.split(key, 4)
    u = jax.random.uniform(k_pos, (3,))
    pos = prm["launch_lo"] + u * (prm["launch_hi"] - prm["launch_lo"])
    ua = jax.random.uniform(k_aim, (2,))
    aim_box = prm["aim_lo"] + ua * (prm["aim_hi"] - prm["aim_lo"])
    # varied: the site by index; the aim on the yawed line (the yaw convention of _direction).
    pos = jnp.where(prm["varied"], pos.at[0].set(prm["varied_x"][i % 3]), pos)
    yaw = prm["yaw"][0] + ua[0] * (prm["yaw"][1] - prm["yaw"][0])
    dist = prm["distance"][0] + ua[1] * (prm["distance"][1] - prm["distance"][0])
    aim_line = pos[:2] - dist * jnp.stack([jnp.cos(yaw), jnp.sin(yaw)])
    aim = jnp.where(prm["varied"], aim_line, aim_box)
    frac = jax.random.uniform(k_frac, ())
    spin = prm["max_spin"] * jax.random.uniform(k_spin, (3,), minval=-1.0, maxval=1.0)
    return pos, frac, spin, aim


def _attempt(sp: _Spec, prm: dict, key, i, attempt):
    """Draw and solve candidate `attempt` of throw i: (Throw fields, valid, badness, flight)."""
    pos, frac, spin, aim = _candidate(prm, jax.random.fold_in(jax.random.fold_in(key, i), attempt), i)
    vel = _solve(sp, pos, prm["speed"], frac, spin, aim)
    fl = _fly(sp, pos, vel, spin)
    tab = sp.table
    err = jnp.linalg.norm(fl.bounce - aim)
    on_half = (fl.bounce[0] < 0.0) & (fl.bounce[0] > -tab.half_length) & (jnp.abs(fl.bounce[1]) < tab.half_width)
    valid = fl.landed & (err < sp.solve_tol) & (fl.clearance >= sp.net_margin) & on_half
    badness = err + jnp.maximum(sp.net_margin - fl.clearance, 0.0) + jnp.where(fl.landed & on_half, 0.0, 10.0)
    return Throw(pos, vel, spin, aim), valid, badness, fl


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample(key, prm: dict, sp: _Spec, n: int):
    """Every throw tries candidates until one is valid (at most sp.candidates). After the first
    round only pending throws are solved, up to `m` of them per round."""
    attempt = jax.vmap(functools.partial(_attempt, sp, prm, key))
    idx = jnp.arange(n)
    throw, valid, bad, fl = attempt(idx, jnp.zeros(n, jnp.int32))
    tries = jnp.ones(n, jnp.int32)
    m = min(n, max(8, -(-n // 8)))

    def pending(c):
        _, valid, _, _, tries = c
        return ~valid & (tries < sp.candidates)

    def body(c):
        throw, valid, bad, fl, tries = c
        sel = jnp.nonzero(pending(c), size=m, fill_value=n)[0]          # n: padding, dropped
        safe = jnp.minimum(sel, n - 1)
        t_new, v_new, b_new, f_new = attempt(safe, tries[safe])
        better = v_new | (b_new < bad[safe])
        put = lambda old, new: old.at[sel].set(jnp.where(better.reshape((-1,) + (1,) * (new.ndim - 1)),
                                                         new, old[safe]), mode="drop")
        throw, fl = (jax.tree.map(put, throw, t_new), jax.tree.map(put, fl, f_new))
        return (throw, valid.at[sel].set(v_new, mode="drop"), put(bad, b_new), fl,
                tries.at[sel].add(1, mode="drop"))

    throw, valid, bad, fl, tries = jax.lax.while_loop(lambda c: jnp.any(pending(c)), body,
                                                      (throw, valid, bad, fl, tries))
    info = {"valid": valid, "error": jnp.linalg.norm(fl.bounce - throw.aim, axis=-1),
            "clearance": fl.clearance, "flight_time": fl.time, "tries": tries,
            "acceptance": jnp.sum(valid) / jnp.sum(tries)}
    return throw, info


def sample_throws(key, cfg: World, n: int) -> Throw:
    """n throws [n, ...] from the distribution cfg.throws.name; deterministic per key.

    Jittable with cfg and n static (`jax.jit(sample_throws, static_argnums=(1, 2))`) and
    vmappable over keys. For `varied`, throw i launches from varied_launch_x[i % 3].
    Raises ValueError for an unknown distribution name or n < 1.
    """
    return sample_throws_info(key, cfg, n)[0]


def sample_throws_info(key, cfg: World, n: int) -> tuple[Throw, dict]:
    """sample_throws plus diagnostics, arrays [n]: `valid`, predicted bounce `error` (m), net
    `clearance` (m), `flight_time` (s), `tries` (candidates drawn); and `acceptance`, the
    fraction of drawn candidates that were valid."""
    _check(cfg, n)
    return _sample(key, _params(cfg), _spec(cfg), int(n))


@functools.partial(jax.jit, static_argnums=(1,))
def _first_bounce(throw: Throw, sp: _Spec):
    lead = jnp.shape(throw.launch_pos)[:-1]
    flat = lambda a: jnp.reshape(jnp.asarray(a, jnp.float32), (-1, 3))
    fl = jax.vmap(functools.partial(_fly, sp))(flat(throw.launch_pos), flat(throw.launch_vel),
                                                flat(throw.launch_spin))
    return fl.bounce.reshape(lead + (2,))


def first_bounce(throw: Throw, cfg: World):
    """[..., 2] first-bounce (x, y) of the throws predicted by the flight model."""
    return _first_bounce(throw, _spec(cfg))


# --------------------------------------------------------------------------------------------
# MuJoCo C check
# --------------------------------------------------------------------------------------------

def simulate(cfg: World, throw: Throw, chunk: int = 256) -> dict:
    """Fly the throws in MuJoCo C (scene.model(cfg) with its ellipsoid fluid model; the ball
    alone moves, the robot rests at its reference pose) to the first table contact.

    Returns numpy arrays: `bounce` [n, 2], where the ball's centre crosses table height +
    radius (MuJoCo's ball-table contact starts there), interpolated between physics steps, NaN
    if it never does; `bounced` [n], the ball then went back up; `clearance` [n], the lowest
    height of the ball's bottom above the net tape while over the net (m).
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
    q0 = mujoco.mj_stateSize(m, mujoco.mjtState.mjSTATE_TIME)   # qpos follows time
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
                d.qvel[bv:bv + 6] = np.concatenate([vel[i], spin[i]])   # identity orientation
                mujoco.mj_getState(m, d, init[i - s], spec)
            states, _ = pool.rollout(m, [d], init, nstep=nstep)
            for j, i in enumerate(range(s, e)):
                xyz = np.concatenate([init[j:j + 1, q0 + bq:q0 + bq + 3], states[j, :, q0 + bq:q0 + bq + 3]])
                vz = states[j, :, v0 + bv + 2]            # vz[k - 1] belongs to xyz[k]
                below = np.nonzero(xyz[:, 2] < h)[0]
                in_flight = np.ones(len(xyz), bool)
                if below.size:
                    k = below[0]
                    frac = (xyz[k - 1, 2] - h) / (xyz[k - 1, 2] - xyz[k, 2])
                    out["bounce"][i] = xyz[k - 1, :2] + frac * (xyz[k, :2] - xyz[k - 1, :2])
                    out["bounced"][i] = bool(np.any(vz[k - 1:k + 30] > 0.0))
                    in_flight[k:] = False
                zs = xyz[in_flight & (np.abs(xyz[:, 0]) <= net_w), 2]
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
