"""The scripted demonstrator (ttmjx/tools/striker.py) on the MuJoCo C backend: its models against the
scene (kinematics, contacts, ball flight), the policy contract (pure JAX, goal ignored, commands
within the limits), and its quality on real throws (hit and return rates, landing coverage)."""
import functools
import itertools
from collections import namedtuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from ttmjx.world import backends, env, observation, scene, thrower
from ttmjx.tools import striker
from ttmjx.world.config import World, opponent_half

CFG = World()
N = 64                      # throws per distribution in the quality tests
SCFG = striker.StrikerConfig()
Throw = namedtuple("Throw", "launch_pos launch_vel launch_spin aim")


@pytest.fixture(scope="module")
def c_backend():
    return backends.Backend(CFG, "c")


@pytest.fixture(scope="module")
def policy():
    return striker.striker_policy(CFG)


@pytest.fixture(scope="module")
def demos(c_backend, policy):
    """One rollout of N throws per distribution (fixed seeds)."""
    out = {}
    for i, name in enumerate(("narrow", "any", "varied")):
        throws = thrower.sample_throws(jax.random.PRNGKey(10 + i), CFG.with_throws(name), N)
        goals = np.zeros((N, 2), np.float32)
        out[name] = c_backend.rollout_one(policy, None, jax.random.PRNGKey(20 + i), throws, goals)
    return out


def plane_crossing(ps, after, x_plane):
    """(k, f): the positions ps [T, 3] first cross x = x_plane where after [T], f of the way
    from step k - 1 to step k."""
    k = int(np.argmax(after & (ps[:, 0] < x_plane)))
    return k, (ps[k - 1, 0] - x_plane) / (ps[k - 1, 0] - ps[k, 0])


def lerp(a, k, f):
    return a[k - 1] + f * (a[k] - a[k - 1])


# --- models against the scene ------------------------------------------------------------------
def test_forward_kinematics_matches_the_scene():
    m = scene.model(CFG)
    ids = scene.ids(m)
    d = mujoco.MjData(m)
    rng = np.random.default_rng(0)
    fk = jax.jit(lambda q: striker.forward_kinematics(CFG, q))
    for _ in range(10):
        q = rng.uniform(CFG.robot.lower, CFG.robot.upper)
        d.qpos[ids.robot_qpos] = q
        mujoco.mj_forward(m, d)
        pos, rot = fk(jnp.asarray(q, jnp.float32))
        np.testing.assert_allclose(pos, d.site_xpos[ids.paddle_site], atol=2e-5)
        np.testing.assert_allclose(rot, d.site_xmat[ids.paddle_site].reshape(3, 3), atol=2e-5)


@pytest.mark.parametrize("surface,model", [("table", striker.TABLE), ("paddle", striker.PADDLE)])
def test_contact_model_matches_the_scene(surface, model):
    """The striker's bounce constants are what the scene does now (re-fit them with
    striker.measure_surface if the contacts change)."""
    got = striker.measure_surface(CFG, surface, phases=4)
    assert got.restitution == pytest.approx(model.restitution, abs=0.02)
    assert got.grip == pytest.approx(model.grip, abs=0.02)
    assert got.grip_per_speed == pytest.approx(model.grip_per_speed, abs=0.003)
    assert got.spin_grip == pytest.approx(model.spin_grip, abs=0.02)
    assert got.spin_gain == pytest.approx(model.spin_gain, abs=0.1)


def test_prediction_matches_the_c_backend(c_backend):
    """The predicted flight against MuJoCo C: where the ball crosses the hitting plane after its
    bounce, predicted from the launch (through the modelled bounce, whose restitution varies
    +-2.5% with the arrival phase) and from the observations just after the bounce (spin
    estimated from two of them)."""
    n = 8
    throws = thrower.sample_throws(jax.random.PRNGKey(3), CFG, n)
    tr = c_backend.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0), throws,
                           np.zeros((n, 2), np.float32))
    scfg = striker.StrikerConfig()
    dt, x_plane = CFG.control_dt, -1.5

    def crossing(ps, t0, step, after):
        k, f = plane_crossing(ps, after, x_plane)
        return lerp(ps, k, f), t0 + (k - 1 + f) * step

    for i in range(n):
        ball, vel = observation.ball_pos(tr.obs[i]), tr.ball_vel[i]
        kb = int(np.argmax((vel[:-1, 2] < 0) & (vel[1:, 2] > 0))) + 1     # first obs after the bounce
        actual, t_actual = crossing(ball, 0.0, dt, np.arange(len(ball)) > kb)
        for k0, tol in ((0, 0.05), (kb + 2, 0.01)):
            spin = (striker.estimate_spin(CFG, jnp.asarray(vel[k0 - 1]), jnp.asarray(vel[k0]), dt)[0]
                    if k0 else jnp.zeros(3))
            ps, _, _, bs = striker.predict(CFG, scfg, jnp.asarray(ball[k0]), jnp.asarray(vel[k0]), spin,
                                           jnp.array(k0 > kb))
            ps = np.concatenate([ball[k0][None], np.asarray(ps)])
            bs = np.concatenate([[k0 > kb], np.asarray(bs)])
            pred, t_pred = crossing(ps, k0 * dt, scfg.predict_dt, bs)
            assert np.abs(pred - actual).max() < tol, (i, k0, pred, actual)
            assert abs(t_pred - t_actual) < 0.01, (i, k0, t_pred, t_actual)


def test_inverse_kinematics_reaches_typical_hits():
    scfg = striker.StrikerConfig()
    policy = striker.striker_policy(CFG, scfg)
    carry = jax.vmap(policy.init, in_axes=(None, 0))(None, jax.random.split(jax.random.PRNGKey(0), 16))
    for i in range(16):
        pos, rot = striker.forward_kinematics(CFG, carry.q_hit[i])
        normal = striker._direction(carry.theta[i, 0], carry.theta[i, 1])
        blade = carry.p_hit[i] - (CFG.ball.radius + CFG.robot.blade_thickness / 2) * normal
        assert float(jnp.linalg.norm(pos - blade)) < 0.005
        assert float(jnp.dot(rot[:, 2], carry.face[i] * normal)) > np.cos(np.radians(2.0))


# --- the policy's stages, each against the scene -----------------------------------------------
Held = namedtuple("Held", "pos vel spin bounce")
X_PLANE = -1.5             # the hitting plane of the stage tests


def world_spin(lay, qpos, qvel):
    """[3] the ball's angular velocity in the world frame (the free joint's is in the ball's)."""
    w = np.zeros(3)
    i, j = lay.ball_qvel + 3, lay.ball_qpos + 3
    mujoco.mju_rotVecQuat(w, qvel[i:i + 3], qpos[j:j + 4])
    return w


@pytest.fixture(scope="module")
def held(c_backend):
    """Spinning throws flying past the robot at rest, at each control step [n, T, ...]: ball
    position, velocity and (world) spin, and the environment's own-half bounce event [n, T]."""
    n, lay = 6, c_backend.lay
    throws = thrower.sample_throws(jax.random.PRNGKey(3), CFG.with_throws("any", spin=True), n)
    states = c_backend.reset(jax.random.PRNGKey(0), throws, np.zeros((n, 2), np.float32))
    observe = jax.jit(jax.vmap(lambda s: env.observe(CFG, lay, s)))
    rows = []
    for _ in range(CFG.horizon):
        obs = observe(states)
        qpos, qvel = np.asarray(states.qpos, np.float64), np.asarray(states.qvel, np.float64)
        rows.append((observation.ball_pos(obs.frame), obs.ball_vel,
                     [world_spin(lay, qpos[i], qvel[i]) for i in range(n)], states.events.bounce_own))
        states = c_backend.step(states, np.asarray(observation.joints(obs.frame)))
    return Held(*(np.stack([np.asarray(r[j]) for r in rows], axis=1) for j in range(4)))


@pytest.fixture(scope="module")
def tracked(held):
    """track_ball along the held flights: spin estimates [n, T, 3] and bounce_now [n, T]."""
    def flight(pos, vel):
        def step(spin, obs):
            p, v, v_prev, first = obs
            spin, bounce_now = striker.track_ball(CFG, SCFG, p, v, v_prev, spin, first)
            return spin, (spin, bounce_now)

        v_prev = jnp.concatenate([vel[:1], vel[:-1]])
        return jax.lax.scan(step, jnp.zeros(3), (pos, vel, v_prev, jnp.arange(pos.shape[0]) == 0))[1]

    return tuple(np.asarray(x) for x in jax.jit(jax.vmap(flight))(held.pos, held.vel))


def test_track_ball_finds_the_bounce_and_the_spin(held, tracked):
    """The bounce is flagged once, on the step of the scene's table contact or the next (a
    contact at a step's end shows in the next velocity); in free flight, before the bounce and
    from two steps after it, the spin estimate is the true spin's part across the velocity
    (the part along it exerts no force), within 3% of the spin."""
    spin, bounce_now = tracked
    for i in range(spin.shape[0]):
        k_env = int(np.argmax(held.bounce[i]))
        k = np.flatnonzero(bounce_now[i])[0]
        assert k_env <= k <= k_env + 1, (i, k, k_env)
        assert not bounce_now[i, :k_env].any() and not bounce_now[i, k + 1:k + 30].any()
        v_dir = held.vel[i] / np.linalg.norm(held.vel[i], axis=-1, keepdims=True)
        across = held.spin[i] - np.sum(held.spin[i] * v_dir, -1, keepdims=True) * v_dir
        free = np.r_[1:k_env, k + 2:k + 30]
        err = np.linalg.norm(spin[i, free] - across[free], axis=-1)
        assert np.all(err < 0.5 + 0.03 * np.linalg.norm(held.spin[i, free], axis=-1)), (i, err.max())


@pytest.fixture(scope="module")
def predicted(held, tracked):
    """predict_hit from the observation two steps after each bounce (hitting plane X_PLANE),
    with the tracked spin: (t_hit [n], p_hit, v_in, w_in [n, 3], found [n]), and that step [n]."""
    k0 = np.argmax(tracked[1], axis=1) + 2
    rows = np.arange(len(k0))
    hit = jax.jit(jax.vmap(functools.partial(striker.predict_hit, CFG, SCFG)))(
        held.pos[rows, k0], held.vel[rows, k0], tracked[0][rows, k0], np.ones(len(k0), bool),
        np.full(len(k0), X_PLANE, np.float32), (k0 * CFG.control_dt).astype(np.float32))
    return tuple(np.asarray(x) for x in hit), k0


def test_predict_hit_meets_the_flight(held, tracked, predicted):
    """The predicted hit is where and when the scene's ball crosses the hitting plane; late in
    the episode, it is where the ball is at return_reserve_s before the episode's end."""
    (t_hit, p_hit, v_in, _, found), k0 = predicted
    dt = CFG.control_dt
    for i in range(len(k0)):
        k, f = plane_crossing(held.pos[i], np.arange(held.pos.shape[1]) > k0[i], X_PLANE)
        assert found[i]
        assert abs(t_hit[i] - (k - 1 + f) * dt) < 0.002, i
        assert np.abs(p_hit[i] - lerp(held.pos[i], k, f)).max() < 0.025, i
        assert np.abs(v_in[i] - lerp(held.vel[i], k, f)).max() < 0.2, i
    # the clock set so that the latest hit is 10 steps ahead, the plane out of reach
    t_latest, rows = CFG.episode_s - SCFG.return_reserve_s, np.arange(len(k0))
    predict = jax.vmap(functools.partial(striker.predict_hit, CFG, SCFG), (0, 0, 0, None, None, None))
    late = predict(held.pos[rows, k0], held.vel[rows, k0], tracked[0][rows, k0], jnp.array(True),
                   jnp.float32(-5.0), jnp.float32(t_latest - 10 * dt))
    np.testing.assert_allclose(late[0], t_latest, atol=1e-5)
    np.testing.assert_allclose(late[1], held.pos[rows, k0 + 10], atol=0.003)
    assert np.all(late[4])


def fly_to_table(m, d, lay, p, v, w):
    """The ball launched from p with velocity v and spin w [3] in the scene (MuJoCo C, its air
    model): (landing [3] at the first bounce, flight time (s), height over the net plane x = 0)."""
    mujoco.mj_resetData(m, d)
    d.qpos[lay.ball_qpos:lay.ball_qpos + 7] = np.r_[p, 1.0, 0.0, 0.0, 0.0]
    d.qvel[lay.ball_qvel:lay.ball_qvel + 6] = np.r_[v, w]
    net_z, x = np.nan, p[0]
    for k in range(1, 2000):
        vz = d.qvel[lay.ball_qvel + 2]
        mujoco.mj_step(m, d)
        ball = d.qpos[lay.ball_qpos:lay.ball_qpos + 3].copy()
        net_z = ball[2] if x < 0.0 <= ball[0] else net_z
        if vz < 0.0 < d.qvel[lay.ball_qvel + 2]:
            return ball, k * m.opt.timestep, net_z
        x = ball[0]
    raise AssertionError("the ball never bounced")


@pytest.fixture(scope="module")
def strokes(predicted):
    """choose_stroke for the predicted hits, toward random targets and net clearances:
    (theta [n, 3], target [n, 2], clearance [n])."""
    (t_hit, p_hit, v_in, w_in, _), _ = predicted
    rng = np.random.default_rng(0)
    n = len(t_hit)
    target = np.float32(np.stack([rng.uniform(*SCFG.target_x, n), rng.uniform(*SCFG.target_y, n)], -1))
    clearance = rng.uniform(*SCFG.net_clearance, n).astype(np.float32)
    choose = functools.partial(striker.choose_stroke, CFG, SCFG)
    theta = jax.jit(jax.vmap(choose))(p_hit, v_in, w_in, t_hit, target, clearance,
                                      np.zeros((n, 3), np.float32), np.ones(n, bool))
    return np.asarray(theta), target, clearance


def test_choose_stroke_lands_the_return_on_the_target(predicted, strokes):
    """The ball after the modelled paddle bounce, flown in the scene: it lands on the target
    after the planned flight time, and clears the net (the clearance itself is a drag-free plan)."""
    (t_hit, p_hit, v_in, w_in, _), _ = predicted
    theta, target, clearance = strokes
    m = scene.model(CFG, fluid=True)
    d, lay = mujoco.MjData(m), env.layout(m)
    tab = CFG.table
    for i in range(len(theta)):
        normal = striker._direction(theta[i, 0], theta[i, 1])
        v_out, w_out = striker.bounce(striker.PADDLE, v_in[i], w_in[i], normal, theta[i, 2] * normal,
                                      CFG.ball.radius)
        land, t_flight, net_z = fly_to_table(m, d, lay, p_hit[i], np.asarray(v_out), np.asarray(w_out))
        planned = striker.flight_time(CFG, SCFG, p_hit[i], t_hit[i], target[i], clearance[i])
        assert np.abs(land[:2] - target[i]).max() < 0.03, (i, land, target[i])
        assert abs(t_flight - float(planned)) < 0.01, (i, t_flight, planned)
        assert net_z - (tab.top_z + tab.net_height + CFG.ball.radius) > 0.5 * SCFG.min_clearance, i


def test_solve_pose_puts_the_blade_on_the_ball(predicted, strokes):
    """The pose and joint velocities in the scene: the blade centre one contact offset behind
    the ball along the stroke's normal, the chosen face toward it, the blade rolled as asked,
    and the blade moving at the stroke's velocity (well within the speed limits here)."""
    (_, p_hit, _, _, _), _ = predicted
    theta = strokes[0]
    m = scene.model(CFG)
    d, ids = mujoco.MjData(m), scene.ids(m)

    @jax.jit
    def pose(p, th, roll, face):
        q = striker.solve_pose(CFG, SCFG, None, p, th, roll, face, jnp.zeros(8), SCFG.ik_init_iters)[0]
        return q, striker.hit_joint_velocity(CFG, SCFG, q, th)

    for i, face in itertools.product(range(len(theta)), (1.0, -1.0)):
        sign, _ = striker.roll_side(CFG, SCFG, p_hit[i], jnp.array(True), 1.0, jnp.array(False))
        roll = striker.roll_at(CFG, SCFG, 0.5, sign, p_hit[i])
        q, qd = pose(p_hit[i], theta[i], roll, face)
        d.qpos[ids.robot_qpos], d.qvel[ids.robot_qvel] = q, qd
        mujoco.mj_forward(m, d)
        vel = np.zeros(6)
        mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_SITE, ids.paddle_site, vel, 0)
        rot = d.site_xmat[ids.paddle_site].reshape(3, 3)
        normal = np.asarray(striker._direction(theta[i, 0], theta[i, 1]))
        _, x_t = striker.blade_frame(normal, roll, face)
        blade = p_hit[i] - striker.contact_offset(CFG) * normal
        assert np.linalg.norm(d.site_xpos[ids.paddle_site] - blade) < 0.003, i
        assert np.dot(rot[:, 2], face * normal) > np.cos(np.radians(2.0)), i
        assert np.dot(rot[:, 0], np.asarray(x_t)) > np.cos(np.radians(10.0)), i
        assert np.max(np.abs(qd) / np.array(CFG.robot.max_speed)) < SCFG.hit_speed_frac
        np.testing.assert_allclose(vel[3:], theta[i, 2] * normal, atol=0.02)


def drive(c_backend, states, swing, steps):
    """Step the scene's robot by swing (q_ref, v_ref, u_prev, t_now) -> (q, v, command), each
    [n, 8], from rest: the reference's and the robot's joint positions and velocities,
    [n, steps + 1, 8] each."""
    lay, dt = c_backend.lay, CFG.control_dt
    q = np.asarray(states.qpos)[:, list(lay.robot_qpos)]
    ref, robot, u = [(q, np.zeros_like(q))], [(q, np.zeros_like(q))], np.float32(q)
    for t in range(steps):
        q, v, u = swing(*(np.float32(x) for x in (*ref[-1], u, t * dt)))
        states = c_backend.step(states, np.asarray(u))
        ref.append((np.asarray(q), np.asarray(v)))
        robot.append((np.asarray(states.qpos)[:, list(lay.robot_qpos)],
                      np.asarray(states.qvel)[:, list(lay.robot_qvel)]))
    return tuple(np.stack([x[j] for x in seq], 1) for seq in (ref, robot) for j in (0, 1))


def test_swing_brings_the_robot_to_the_hit(c_backend):
    """The swing's commands, sent through the environment to the scene's servos: the
    reference passes through the hit joints at the hit velocity at the hit time (between
    control steps), and the robot follows it there (the servo feed-forward): blade within 5 mm,
    joint speeds within 1% + 0.01 rad/s."""
    n, dt = 3, CFG.control_dt
    throws = thrower.sample_throws(jax.random.PRNGKey(7), CFG, n)
    states = c_backend.reset(jax.random.PRNGKey(8), throws, np.zeros((n, 2), np.float32))
    keys = jax.random.split(jax.random.PRNGKey(9), n)
    plan = jax.vmap(functools.partial(striker.draw_episode, CFG, SCFG))(keys)
    qd_hit = jax.vmap(functools.partial(striker.hit_joint_velocity, CFG, SCFG))(plan.q_hit, plan.theta)
    t_hit = np.float32(0.6) + np.arange(n, dtype=np.float32) * np.float32(0.0037)    # off the grid

    @jax.jit
    def swing(q_ref, v_ref, u_prev, t_now):
        def one(q_ref, v_ref, u_prev, t_hit, q_hit, qd_hit, strike_s):
            q, v, a = striker.swing_reference(CFG, SCFG, q_ref, v_ref, t_now, t_hit, q_hit, qd_hit,
                                              strike_s)
            q, v = striker.limit_reference(CFG, SCFG, q_ref, q, v)
            return q, v, striker.servo_command(CFG, q, v, a, jnp.zeros(8), u_prev)
        return jax.vmap(one)(q_ref, v_ref, u_prev, t_hit, plan.q_hit, qd_hit, plan.strike_s)

    rq, rv, aq, av = drive(c_backend, states, swing, 70)
    blade = jax.jit(lambda q: striker.forward_kinematics(CFG, q)[0])
    for i in range(n):
        k, f = int(t_hit[i] / dt) + 1, (t_hit[i] / dt) % 1.0
        np.testing.assert_allclose(lerp(rq[i], k, f), plan.q_hit[i], atol=1e-5)
        np.testing.assert_allclose(lerp(rv[i], k, f), qd_hit[i], atol=1e-5)
        assert np.linalg.norm(blade(np.float32(lerp(aq[i], k, f))) - blade(plan.q_hit[i])) < 0.005, i
        assert np.all(np.abs(lerp(av[i], k, f) - qd_hit[i]) < 0.01 + 0.01 * np.abs(qd_hit[i])), i


# --- the policy contract -----------------------------------------------------------------------
def test_init_draws_the_episode_randomization(policy):
    scfg = striker.StrikerConfig()
    carry = jax.vmap(policy.init, in_axes=(None, 0))(None, jax.random.split(jax.random.PRNGKey(1), 200))
    perturbed = np.count_nonzero(np.asarray(carry.offset), axis=1)
    assert np.all(perturbed == scfg.perturb_joints)      # "perturb 4 of the 8 joints"
    assert np.all(np.abs(carry.offset) <= np.array(scfg.perturb))
    t = np.asarray(carry.target)
    assert t[:, 0].min() >= scfg.target_x[0] and t[:, 0].max() <= scfg.target_x[1]
    assert t[:, 1].min() < -0.4 and t[:, 1].max() > 0.4  # targets spread across the half
    assert set(np.unique(carry.face)) == {-1.0, 1.0}


def test_closed_loop_commands_are_pure_jax_within_limits_and_ignore_the_goal(c_backend, policy):
    """A manual rollout through the public Backend.reset/step with the policy jit-compiled and
    vmapped: the raw commands never need the environment's clipping, and the goal in the
    observation changes nothing."""
    n = 6
    throws = thrower.sample_throws(jax.random.PRNGKey(4), CFG.with_throws("any"), n)
    throws = Throw(*(np.concatenate([np.asarray(x)] * 2) for x in throws))
    goals = np.concatenate([np.zeros((n, 2)), np.tile([[1.2, 0.6]], (n, 1))]).astype(np.float32)
    keys = jax.random.split(jax.random.PRNGKey(5), n)
    keys = jnp.concatenate([keys, keys])
    init, apply = backends.batched_policy(policy)
    observe = jax.vmap(lambda s: env.observe(CFG, c_backend.lay, s))
    clip = jax.vmap(lambda s, a: env.command(CFG, s, a))

    @jax.jit
    def act(carry, states, key):
        carry, action = apply(None, carry, observe(states), jax.random.split(key, 2 * n))
        return carry, action, clip(states, action)

    states = c_backend.reset(jax.random.PRNGKey(6), throws, goals)
    same = observation.with_goal(states.frames[:n], observation.goal(states.frames[n:]), xp=jnp)
    states = states._replace(qpos=jnp.concatenate([states.qpos[:n]] * 2),   # same start pose
                             target=jnp.concatenate([states.target[:n]] * 2),
                             frames=states.frames.at[n:].set(same))
    carry = jax.jit(init)(None, keys)
    worst = 0.0
    for t in range(CFG.horizon):
        carry, action, sent = act(carry, states, jax.random.PRNGKey(t))
        live = ~np.asarray(states.events.done)
        worst = max(worst, float(np.abs(np.asarray(action) - np.asarray(sent))[live].max(initial=0.0)))
        np.testing.assert_array_equal(np.asarray(action[:n]), np.asarray(action[n:]))
        states = c_backend.step(states, np.asarray(action))
        if not live.any():
            break
    assert worst < 1e-5, f"the environment had to clip a striker command by {worst}"
    assert np.asarray(states.events.hit).all()


# --- quality on real throws --------------------------------------------------------------------
@pytest.mark.parametrize("name,min_hit,min_return", [("narrow", 0.9, 0.7), ("any", 0.8, 0.5),
                                                     ("varied", 0.8, 0.5)])
def test_hits_and_returns(demos, name, min_hit, min_return):
    tr = demos[name]
    assert tr.hit.mean() >= min_hit, f"{name}: hit rate {tr.hit.mean():.2f}"
    assert tr.on_opponent.mean() >= min_return, f"{name}: return rate {tr.on_opponent.mean():.2f}"
    assert tr.bounce_own[tr.hit].all(), "struck before the own-half bounce"


def test_landings_cover_the_opponents_half(demos):
    """Landings of all demonstrations reach >= 70% of a 6 x 4 grid over the opponent's half."""
    box = opponent_half(CFG.table)
    land = np.concatenate([tr.landing[tr.on_opponent] for tr in demos.values()])
    ix = np.clip(((land[:, 0] - box[0, 0]) / np.ptp(box[0]) * 6).astype(int), 0, 5)
    iy = np.clip(((land[:, 1] - box[1, 0]) / np.ptp(box[1]) * 4).astype(int), 0, 3)
    covered = len(set(zip(ix.tolist(), iy.tolist())))
    assert covered >= 0.7 * 24, f"{covered} of 24 cells"
