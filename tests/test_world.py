"""The task on both backends: observation layout, events on hand-built throws, command clipping
and speed limits, backend parity, determinism, bad input."""
from collections import namedtuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from ttmjx.world import backends, env, observation, record
from ttmjx.world.config import World

Throw = namedtuple("Throw", "launch_pos launch_vel launch_spin aim")
CFG = World()


def hand_throws(pos, vel, spin=None):
    pos, vel = np.atleast_2d(pos).astype(np.float32), np.atleast_2d(vel).astype(np.float32)
    spin = np.zeros_like(pos) if spin is None else np.atleast_2d(spin).astype(np.float32)
    return Throw(pos, vel, spin, np.zeros((len(pos), 2), np.float32))


def paddle_pose(cfg=CFG):
    """Blade centre and face normal at the exact home pose (no perturbation)."""
    from ttmjx.world import scene
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    lay = env.layout(m)
    d.qpos[list(lay.robot_qpos)] = cfg.robot.home
    mujoco.mj_forward(m, d)
    sid = m.site("paddle").id
    return d.site_xpos[sid].copy(), d.site_xmat[sid].reshape(3, 3)[:, 2].copy()


def open_loop_policy(cfg=CFG, amplitude=0.3):
    """Joint targets that are a fixed function of time: home + a sinusoid per joint."""
    home = jnp.array(cfg.robot.home)
    freq = jnp.linspace(1.0, 3.0, 8)

    def apply(params, carry, obs, key):
        t = obs.t.astype(jnp.float32) * cfg.control_dt
        return carry, home + amplitude * jnp.sin(2 * jnp.pi * freq * t) * jnp.array([0.3, 0.3, 1, 1, 1, 1, 1, 1])
    return backends.Policy(init=lambda p, k: jnp.zeros(()), apply=apply)


@pytest.fixture(scope="module")
def c_backend():
    return backends.Backend(CFG, "c")


@pytest.fixture(scope="module")
def mjx_backend():
    return backends.Backend(CFG, "mjx")


def test_reset_observation_and_frame_stack_layout(c_backend):
    th = hand_throws([1.7, 0.2, 0.95], [-6.5, -0.2, 1.0])
    goal = np.array([[0.6, -0.3]], np.float32)
    s = c_backend.reset(jax.random.PRNGKey(0), th, goal)
    obs = jax.vmap(lambda st: env.observe(CFG, c_backend.lay, st))(s)
    f = np.asarray(obs.frame[0])
    assert f.shape == (13,)
    np.testing.assert_allclose(f[8:11], [1.7, 0.2, 0.95], atol=1e-6)   # ball position
    np.testing.assert_allclose(f[11:13], [0.6, -0.3], atol=1e-6)        # goal
    home, noise = np.array(CFG.robot.home), np.array(CFG.robot.home_noise)
    assert np.all(np.abs(f[:8] - home) <= noise + 1e-6)                   # perturbed home pose
    assert obs.frames.shape == (1, CFG.frame_stack, 13)
    np.testing.assert_array_equal(np.asarray(obs.frames[0]), np.tile(f, (CFG.frame_stack, 1)))
    s2 = c_backend.step(s, np.asarray(s.target))
    fr = np.asarray(s2.frames[0])
    np.testing.assert_array_equal(fr[:-1], np.tile(f, (CFG.frame_stack - 1, 1)))
    assert fr[-1, 8] < f[8]  # the ball moved toward the robot


def test_record_frame_stack_matches_state_frames(c_backend):
    th = hand_throws([[1.7, 0.2, 0.95]] * 2, [[-6.5, -0.2, 1.0]] * 2)
    tr = c_backend.rollout_one(open_loop_policy(), None, jax.random.PRNGKey(1), th, np.zeros((2, 2)), horizon=12)
    stacks = observation.frame_stack(tr.obs, 4)
    assert stacks.shape == (2, 12, 4, 13)
    np.testing.assert_array_equal(stacks[:, 0], np.repeat(tr.obs[:, :1], 4, 1))  # padded with frame 0
    np.testing.assert_array_equal(stacks[:, 6], tr.obs[:, 3:7])
    assert observation.frame_stack(jnp.asarray(tr.obs), 4).shape == (2, 12, 4, 13)


def test_ball_velocity_observation_has_16_values():
    cfg = World(ball_velocity_obs=True)
    be = backends.Backend(cfg, "c")
    th = hand_throws([1.7, 0.2, 0.95], [-6.5, -0.2, 1.0])
    s = be.reset(jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    f = np.asarray(env.observe(cfg, be.lay, jax.tree.map(lambda x: x[0], s)).frame)
    assert f.shape == (16,)
    np.testing.assert_allclose(f[11:14], [-6.5, -0.2, 1.0], atol=1e-6)
    tr = be.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0), th, np.zeros((1, 2)), horizon=5)
    assert tr.obs.shape == (1, 5, 13)  # the record always keeps 13 + ball_vel separately


def test_events_unreturned_throw_bounces_on_robot_side_and_ends(c_backend):
    # Aimed wide of the robot: bounces on the robot's half, never touched, falls off the table.
    th = hand_throws([1.7, 0.6, 0.95], [-6.5, 0.0, 2.0])
    tr = c_backend.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    assert bool(tr.bounce_own[0]) and not bool(tr.hit[0]) and not bool(tr.net[0])
    assert tr.hit_step[0] == -1 and np.all(np.isnan(tr.landing[0])) and not tr.on_opponent[0]
    n = int(tr.valid[0].sum())
    assert n < CFG.horizon  # ended when the ball fell below the table, before the time limit
    assert tr.obs[0, n - 1, 10] < CFG.table.top_z + 0.3


def test_events_net_ball(c_backend):
    th = hand_throws([1.7, 0.0, 0.85], [-7.0, 0.0, 0.3])  # too low: hits the net
    tr = c_backend.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    assert bool(tr.net[0]) and not bool(tr.hit[0]) and not bool(tr.bounce_own[0])
    assert np.all(tr.obs[0, tr.valid[0], 8] > -0.05)  # never got through to the robot's side


def paddle_shot(velocity):
    """A ball thrown down onto the blade from 10 cm above it along its normal (2.5 m/s), with
    extra velocity `velocity` [3] along the table."""
    pos, normal = paddle_pose()
    return hand_throws(pos + 0.1 * normal, np.asarray(velocity) - 2.5 * normal)


def test_events_hit_and_landing_on_opponent_half(c_backend):
    tr = c_backend.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0),
                           paddle_shot([3.2, 0.0, 0.0]), np.zeros((1, 2)))
    assert bool(tr.hit[0]) and 0 <= tr.hit_step[0] <= 5
    assert bool(tr.on_opponent[0]) and not bool(tr.net[0])
    x, y = tr.landing[0]
    assert 0 < x < CFG.table.half_length and abs(y) < CFG.table.half_width
    # The episode ends at the landing: the last valid ball height is at the table top.
    n = int(tr.valid[0].sum())
    assert abs(tr.obs[0, n - 1, 10] - (CFG.table.top_z + CFG.ball.radius)) < 0.1


def test_events_hit_ball_that_misses_the_table_gets_a_fall_point(c_backend):
    tr = c_backend.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0),
                           paddle_shot([3.0, 2.5, 0.0]), np.zeros((1, 2)))
    assert bool(tr.hit[0]) and not bool(tr.on_opponent[0])
    x, y = tr.landing[0]
    assert np.isfinite(x) and abs(y) > CFG.table.half_width  # fell beside the table


def test_command_clips_to_ranges_speed_and_holds_on_nan(c_backend):
    th = hand_throws([1.7, 0.2, 0.95], [-6.5, -0.2, 1.0])
    s = c_backend.reset(jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    st = jax.tree.map(lambda x: x[0], s)
    r = CFG.robot
    far = np.array(r.upper) + 5.0
    tgt = np.asarray(env.command(CFG, st, jnp.asarray(far, jnp.float32)))
    step = np.array(r.max_speed) * r.speed_margin * CFG.control_dt
    np.testing.assert_allclose(tgt - np.asarray(st.target), step, rtol=1e-5)
    nan = np.full(8, np.nan, np.float32)
    np.testing.assert_array_equal(np.asarray(env.command(CFG, st, jnp.asarray(nan))), np.asarray(st.target))
    # Many steps toward far targets never leave the ranges.
    for _ in range(300):
        st = st._replace(target=env.command(CFG, st, jnp.asarray(far, jnp.float32)))
    assert np.all(np.asarray(st.target) <= np.array(r.upper) + 1e-6)


def test_simulated_joints_respect_speed_limits_and_ranges(c_backend):
    """Bang-bang random targets: every physics step's joint speed stays within the 120T limits."""
    rng = np.random.default_rng(0)
    r = CFG.robot
    phys = c_backend.physics
    th = hand_throws([[1.7, 0.2, 0.95]] * 8, [[-6.5, -0.2, 1.0]] * 8)
    s = c_backend.reset(jax.random.PRNGKey(0), th, np.zeros((8, 2)))
    qpos, qvel, target = np.asarray(s.qpos, np.float64), np.asarray(s.qvel, np.float64), np.asarray(s.target)
    lay = c_backend.lay
    peak = np.zeros(8)
    lo, hi = np.array(r.lower), np.array(r.upper)
    for t in range(100):
        action = np.where(rng.random((8, 8)) < 0.5, lo, hi) if t % 10 == 0 else action
        st = jax.tree.map(jnp.asarray, s._replace(target=jnp.asarray(target)))
        new = np.asarray(jax.vmap(lambda x, a: env.command(CFG, x, a))(st, jnp.asarray(action, jnp.float32)))
        ctrl = np.asarray(backends._ramp(target, new, CFG.substeps))
        states, _ = phys.pool.rollout(phys.m, phys.datas, phys.initial_state(qpos, qvel), ctrl)
        v = states[:, :, 1 + phys.nq:1 + phys.nq + phys.nv][:, :, list(lay.robot_qvel)]
        q = states[:, :, 1:1 + phys.nq][:, :, list(lay.robot_qpos)]
        peak = np.maximum(peak, np.abs(v).max((0, 1)))
        assert np.all(q >= lo - 1e-3) and np.all(q <= hi + 1e-3)
        qpos, qvel = states[:, -1, 1:1 + phys.nq], states[:, -1, 1 + phys.nq:1 + phys.nq + phys.nv]
        target = new
    assert np.all(peak <= np.array(r.max_speed)), peak / np.array(r.max_speed)
    assert np.all(peak >= 0.5 * np.array(r.max_speed))  # the test did drive them hard


def test_determinism_per_seed(c_backend):
    th = hand_throws([[1.7, 0.2, 0.95]] * 3, [[-6.5, -0.2, 1.0]] * 3)
    a = c_backend.rollout_one(open_loop_policy(), None, jax.random.PRNGKey(7), th, np.zeros((3, 2)), horizon=40)
    b = c_backend.rollout_one(open_loop_policy(), None, jax.random.PRNGKey(7), th, np.zeros((3, 2)), horizon=40)
    c = c_backend.rollout_one(open_loop_policy(), None, jax.random.PRNGKey(8), th, np.zeros((3, 2)), horizon=40)
    for f in record.Trajectories._fields:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)
    assert not np.array_equal(a.obs[:, 0, :8], c.obs[:, 0, :8])  # a different seed perturbs home


def test_a_new_backend_of_the_same_world_runs_what_the_first_compiled(c_backend, caplog):
    """Backends of one world share their jitted steps and compiled rollouts: an evaluation makes a
    Backend per call, and each one traced and compiled reset, act and advance again. A second
    Backend's rollout of the same policy compiles nothing and plays the same numbers."""
    import logging
    policy, goals = open_loop_policy(), np.zeros((2, 2))
    th = hand_throws([[1.7, 0.2, 0.95]] * 2, [[-6.5, -0.2, 1.0]] * 2)
    a = c_backend.rollout_one(policy, None, jax.random.PRNGKey(3), th, goals, horizon=20)
    with caplog.at_level(logging.DEBUG, logger="jax._src.interpreters.pxla"):
        b = backends.Backend(CFG, "c").rollout_one(policy, None, jax.random.PRNGKey(3), th, goals, horizon=20)
    compiled = [r.getMessage()[:80] for r in caplog.records if r.getMessage().startswith("Compiling ")]
    assert compiled == []
    for f in record.Trajectories._fields:
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f), err_msg=f)


def test_compiled_rollouts_kept_are_the_most_recently_used():
    kept = backends._Recent(2)
    kept["a"], kept["b"] = 1, 2
    assert kept["a"] == 1          # "a" used last: "b" is the oldest now
    kept["c"] = 3
    assert sorted(kept) == ["a", "c"]


def paddle_pose_at_reset(backend, key, n):
    """Blade centre and normal [n, 3] of the perturbed home poses `backend.rollout_one(key)` resets to."""
    k_reset = jax.random.split(key, 3)[0]
    dummy = hand_throws([[1.7, 0.0, 0.95]] * n, [[-6.5, 0.0, 2.0]] * n)
    s = backend.reset(k_reset, dummy, np.zeros((n, 2)))
    from ttmjx.world import scene
    m = scene.model(CFG)
    d = mujoco.MjData(m)
    sid = m.site("paddle").id
    pos, nrm = [], []
    for q in np.asarray(s.qpos, np.float64):
        d.qpos[:] = q
        mujoco.mj_forward(m, d)
        pos.append(d.site_xpos[sid].copy()), nrm.append(d.site_xmat[sid].reshape(3, 3)[:, 2].copy())
    return np.array(pos), np.array(nrm)


def test_backend_parity_positions_and_events(c_backend, mjx_backend):
    """Same throws and action sequences: ball within 1 cm, joints within 1e-3 rad over 1 s,
    and the same events, on throws that bounce, fly with spin, get hit, land and miss."""
    key = jax.random.PRNGKey(3)
    pos, normal = paddle_pose_at_reset(c_backend, key, 7)
    launch = np.array([[1.7, 0.3, 0.95], [1.9, -0.4, 1.0], pos[2] + 0.1 * normal[2], pos[3] + 0.1 * normal[3],
                       [1.7, 0.6, 0.95], [1.8, -0.2, 1.0], [1.7, 0.0, 0.85]])
    vel = np.array([[-6.5, -0.3, 2.0], [-7.5, 0.3, 0.9], [3.2, 0.0, 0.0] - 2.5 * normal[2],
                    [3.0, 2.5, 0.0] - 2.5 * normal[3], [-6.5, 0.0, 2.0], [-8.0, 0.2, 1.2], [-7.0, 0.0, 0.3]])
    spin = np.array([[0, 0, 0], [0, 80, 30], [0, 0, 0], [0, 0, 0], [20, -50, 0], [0, -120, 0], [0, 0, 0]])
    throws = hand_throws(launch, vel, spin)
    goals = np.zeros((7, 2), np.float32)
    horizon = int(1.0 * CFG.control_hz)
    policy = open_loop_policy(amplitude=0.01)
    tc = c_backend.rollout_one(policy, None, key, throws, goals, horizon=horizon)
    tm = mjx_backend.rollout_one(policy, None, key, throws, goals, horizon=horizon)
    # An episode ends when the ball crosses a height; positions 1 cm apart can put that instant
    # on either side of a 10 ms tick, so the ends may differ by one control step.
    assert np.abs(tc.valid.sum(1) - np.asarray(tm.valid).sum(1)).max() <= 1
    v = tc.valid & np.asarray(tm.valid)
    # The last throw hits the net and then rolls and skips along the table at low speed: there
    # float32 MJX and float64 MuJoCo C contact solutions drift apart (~1 cm after 0.5 s of
    # rolling), so it is held to the same events, not to the 1 cm bound.
    v[-1] = False
    ball_err = np.linalg.norm(tc.obs[..., 8:11] - np.asarray(tm.obs[..., 8:11]), axis=-1)[v]
    joint_err = np.abs(tc.obs[..., :8] - np.asarray(tm.obs[..., :8])).max(-1)[v]
    assert ball_err.max() < 0.01, ball_err.max()
    assert joint_err.max() < 1e-3, joint_err.max()
    for f in ("hit", "hit_step", "on_opponent", "bounce_own", "net"):
        np.testing.assert_array_equal(getattr(tc, f), np.asarray(getattr(tm, f)), err_msg=f)
    np.testing.assert_allclose(tc.landing, np.asarray(tm.landing), atol=0.01)
    # The events were exercised: hits with landing points, own-half bounces, the net.
    assert tc.hit.sum() >= 2 and np.isfinite(tc.landing[:, 0]).sum() >= 2
    assert tc.net.sum() >= 1 and tc.bounce_own.sum() >= 3


def test_bad_input_errors_name_the_field(c_backend):
    with pytest.raises(ValueError, match="control_hz=60 is not a whole number of physics steps of 0.001 s"):
        World(control_hz=60, physics_dt=0.001)
    with pytest.raises(ValueError, match="control_hz must be a positive integer"):
        World(control_hz=0)
    with pytest.raises(ValueError, match="unknown throw distribution 'wide'"):
        CFG.with_throws("wide")
    th = hand_throws([1.7, 0.2, 0.95], [-6.5, -0.2, 1.0])
    with pytest.raises(ValueError, match=r"goals of shape \(1, 3\); expected \[N, 2\]"):
        c_backend.reset(jax.random.PRNGKey(0), th, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="not finite"):
        c_backend.reset(jax.random.PRNGKey(0), th, np.array([[np.nan, 0.0]]))
    s = c_backend.reset(jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"actions must have shape \[1, 8\]"):
        c_backend.step(s, np.zeros((1, 7)))
    with pytest.raises(ValueError, match=r"actions\[0, 3\] = inf"):
        c_backend.step(s, np.array([[0, 0, 0, np.inf, 0, 0, 0, 0]]))
    with pytest.raises(ValueError, match="unknown backend 'gpu'"):
        backends.Backend(CFG, "gpu")


@pytest.mark.parametrize("hz", [20, 60])
def test_other_control_rates_run_the_same_task(hz):
    """20 Hz (the real robot) and 60 Hz (varied balls) with physics substeps beneath."""
    cfg = World(control_hz=hz)
    assert cfg.substeps * cfg.physics_dt == pytest.approx(1.0 / hz) and cfg.physics_dt <= 0.001
    be = backends.Backend(cfg, "c")
    pos, normal = paddle_pose(cfg)
    th = hand_throws(pos + 0.1 * normal, np.array([3.2, 0.0, 0.0]) - 2.5 * normal)
    tr = be.rollout_one(backends.hold_policy(), None, jax.random.PRNGKey(0), th, np.zeros((1, 2)))
    assert tr.obs.shape == (1, cfg.horizon, 13) and cfg.horizon == round(cfg.episode_s * hz)
    assert bool(tr.hit[0]) and np.isfinite(tr.landing[0]).all()

