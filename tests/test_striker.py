"""The scripted demonstrator (ttmjx/tools/striker.py) on the MuJoCo C backend: its models against the
scene (kinematics, contacts, ball flight), the policy contract (pure JAX, goal ignored, commands
within the limits), and its quality on real throws (hit and return rates, landing coverage)."""
from collections import namedtuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from ttmjx.world import backends, env, scene, thrower
from ttmjx.tools import striker
from ttmjx.world.config import World, opponent_half

CFG = World()
N = 64                      # throws per distribution in the quality tests
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
        out[name] = c_backend.rollout(policy, None, jax.random.PRNGKey(20 + i), throws, goals)
    return out


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
    tr = c_backend.rollout(backends.hold_policy(), None, jax.random.PRNGKey(0), throws,
                           np.zeros((n, 2), np.float32))
    scfg = striker.StrikerConfig()
    dt, x_plane = CFG.control_dt, -1.5

    def crossing(ps, t0, step, after):
        k = np.argmax(after & (ps[:, 0] < x_plane))
        f = (ps[k - 1, 0] - x_plane) / (ps[k - 1, 0] - ps[k, 0])
        return ps[k - 1] + f * (ps[k] - ps[k - 1]), t0 + (k - 1 + f) * step

    for i in range(n):
        ball, vel = tr.obs[i, :, 8:11], tr.ball_vel[i]
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
    states = states._replace(qpos=jnp.concatenate([states.qpos[:n]] * 2),   # same start pose
                             target=jnp.concatenate([states.target[:n]] * 2),
                             frames=states.frames.at[n:, :, :11].set(states.frames[:n, :, :11]))
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
