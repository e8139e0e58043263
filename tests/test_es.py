"""The ES demonstration source (ttmjx/tools/es.py): the optimiser, the weights file, the shipped policy."""
import os
import zipfile

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from ttmjx.world import backends, env
from ttmjx.tools import es
from ttmjx.world.config import World
from ttmjx.world.thrower import Throw

CFG = World().with_throws("narrow")


def _throws(n):
    """n copies of a fixed narrow throw (from sample_throws; avoids the launch solve here)."""
    rep = lambda *v: np.tile(np.array(v, np.float32), (n, 1))
    return Throw(launch_pos=rep(1.75, 0.35, 0.95), launch_vel=rep(-7.00208, -1.7936301, 1.6626624),
                 launch_spin=rep(0.0, 0.0, 0.0), aim=rep(-0.66546214, -0.26873672))


def test_es_improves_fitness_on_a_tiny_problem():
    target = jnp.linspace(-1.0, 1.0, 20)
    fit = lambda thetas, gen: -jnp.sum((thetas - target) ** 2, axis=1)
    x0 = jnp.zeros(20)
    start = float(fit(x0[None], 0)[0])                      # -7.37
    state, hist = es.openai_es(fit, x0, generations=15, population=16, seed=0,
                               es=es.ESConfig(sigma=0.1, lr=0.05, weight_decay=0.0))
    end = float(fit(state.mean[None], 0)[0])
    assert len(hist) == 15 and hist[-1]["fitness_mean"] > hist[0]["fitness_mean"]
    assert end > start + 0.5 * abs(start), (start, end)


def test_ask_is_antithetic_and_ranks_are_centred():
    state = es.es_init(jnp.arange(5.0))
    thetas, eps = es.es_ask(state, jax.random.PRNGKey(0), 8, 0.1)
    assert thetas.shape == (8, 5) and eps.shape == (4, 5)
    np.testing.assert_allclose(thetas[:4] + thetas[4:], np.broadcast_to(2 * state.mean, (4, 5)), rtol=1e-6)
    r = es.centered_ranks([3.0, -1.0, 10.0, 0.0])
    np.testing.assert_allclose(r, [1 / 6, -0.5, 0.5, -1 / 6])
    with pytest.raises(ValueError, match="even"):
        es.es_ask(state, jax.random.PRNGKey(0), 7, 0.1)


def test_population_policy_matches_the_single_policy():
    params = es.init_params(CFG, jax.random.PRNGKey(0), hidden=8)
    train, fixed = es.split_params(params)
    x0, unravel = ravel_pytree(train)
    thetas = x0[None] + 0.3 * jax.random.normal(jax.random.PRNGKey(1), (3, x0.shape[0]))
    pop = es.population_policy(fixed, unravel)
    single = es.mlp_policy()
    frame = jnp.concatenate([jnp.array(CFG.robot.home), jnp.array([-1.2, -0.3, 0.95]), jnp.array([2.0, 0.0])])
    obs = env.Obs(frame=frame, ball_vel=jnp.array([-4.0, -1.0, 1.0]), frames=frame[None], t=jnp.int32(3))
    _, a_pop = jax.jit(pop.apply)(thetas, jnp.zeros(()), obs, jax.random.PRNGKey(0))   # traceable
    _, a_one = single.apply({**fixed, **unravel(thetas[2])}, None, obs, None)
    np.testing.assert_allclose(a_pop, a_one, rtol=1e-6)


def test_weights_round_trip_is_exact_and_pickle_free(tmp_path):
    params = jax.tree.map(np.asarray, es.init_params(CFG, jax.random.PRNGKey(3), hidden=16))
    params["W2"] = np.asarray(jax.random.normal(jax.random.PRNGKey(4), (16, 8)), np.float32)
    path = es.save_params(str(tmp_path / "w"), params, {"note": "test"})
    assert path.endswith(".npz") and os.path.exists(str(tmp_path / "w.json"))
    with np.load(path, allow_pickle=False) as z:                       # plain numeric arrays
        assert all(z[k].dtype != object for k in z.files)
    back = es.load_params(path)
    for k in es.PARAM_NAMES:
        assert back[k].dtype == np.float32 and back[k].tobytes() == np.asarray(params[k]).tobytes(), k
    _, loaded = es.load_policy(CFG, str(tmp_path / "w.npz"))
    assert all(np.array_equal(np.asarray(loaded[k]), params[k]) for k in es.PARAM_NAMES)
    bad = tmp_path / "bad.npz"
    bad.write_bytes(open(path, "rb").read()[:100])
    with pytest.raises(ValueError, match="corrupt"):
        es.load_params(str(bad))
    with pytest.raises(ValueError, match="missing"):
        es.load_params(str(tmp_path / "absent.npz"))


def test_shipped_weights_load_without_pickle_and_run_on_c():
    path = os.path.join(es.ASSETS, es.WEIGHTS_NAME)
    assert zipfile.is_zipfile(path)
    with np.load(path, allow_pickle=False) as z:
        assert set(es.PARAM_NAMES) <= set(z.files)
    policy, params = es.load_policy(CFG)
    assert isinstance(policy, backends.Policy)
    n = 4
    be = backends.Backend(CFG, "c")
    traj = be.rollout_one(policy, params, jax.random.PRNGKey(0), _throws(n), np.zeros((n, 2), np.float32))
    assert traj.obs.shape == (n, CFG.horizon, 13)
    assert np.all(np.isfinite(traj.actions[traj.valid]))
    lo, hi = np.array(CFG.robot.lower), np.array(CFG.robot.upper)
    assert np.all(traj.actions[traj.valid] >= lo - 1e-6) and np.all(traj.actions[traj.valid] <= hi + 1e-6)
    # The policy moves the arm (it is not the hold policy) and the shaped reward is computable.
    assert np.abs(traj.actions[:, 60] - traj.actions[:, 0]).max() > 0.01
    r = es.shaped_reward(traj, es.Paddle(CFG))
    assert r["reward"].shape == (n,) and np.all(np.isfinite(r["reward"]))


def test_train_es_runs_end_to_end(tmp_path):
    ckpt = str(tmp_path / "best.npz")
    params, hist = es.train_es(CFG, generations=2, population=4, seed=0, progress=False,
                               throws_per_candidate=2, pool=8, val_throws=8, eval_every=1,
                               checkpoint=ckpt)
    assert len(hist) == 2 and all(np.isfinite(h["fitness_mean"]) for h in hist)
    assert {"hit_rate", "return_rate", "val_hit_rate", "best_generation"} <= set(hist[-1])
    saved = es.load_params(ckpt)
    assert all(np.array_equal(saved[k], np.asarray(params[k])) for k in es.PARAM_NAMES)


def _hit_record(landing, on_opponent, last_x):
    """Two-step records of hit balls (hit at step 0) that came down at `landing` (NaN: still
    flying at the end, last seen at x = last_x)."""
    from ttmjx.world.record import Trajectories
    b = len(landing)
    obs = np.zeros((b, 2, 13), np.float32)
    obs[:, :, :8] = CFG.robot.home
    obs[:, 0, 8:11] = (-1.5, 0.0, 0.9)
    obs[:, 1, 8:11] = np.stack([np.asarray(last_x, np.float32), np.zeros(b), np.full(b, 1.0)], 1)
    z = lambda *s, d=np.float32: np.zeros((b, *s), d)  # noqa: E731
    return Trajectories(obs=obs, ball_vel=z(2, 3), actions=z(2, 8), valid=np.ones((b, 2), bool), goal=z(2),
                        hit=np.ones(b, bool), hit_step=np.zeros(b, np.int32), landing=np.asarray(landing, np.float32),
                        on_opponent=np.asarray(on_opponent, bool), bounce_own=z(d=bool), net=z(d=bool),
                        launch_pos=z(3), launch_vel=z(3), launch_spin=z(3), aim=z(2))


def test_the_return_reward_climbs_from_a_block_to_a_return():
    """The return phase's landing term rises steadily as the ball comes down closer to the aim
    (a block falling back on the robot's half < a ball short of the net < a return), so a
    search near a block sees a slope toward returns; a ball still flying when the episode ends
    counts where it was last seen. The contact reward has no such term."""
    aim_x = es.RETURN.aim[0]
    landing = [(-1.2, 0.0), (-0.3, 0.0), (0.4, 0.0), (aim_x, 0.0), (np.nan, np.nan)]
    traj = _hit_record(landing, [False, False, True, True, False], last_x=[0, 0, 0, 0, -0.3])
    r = es.shaped_reward(traj, es.Paddle(CFG), es.RETURN)
    assert np.all(np.diff(r["land"][:4]) > 0) and r["land"][3] == pytest.approx(1.0)
    assert r["land"][4] == pytest.approx(r["land"][1])
    assert np.all(np.diff(r["reward"][:4]) > 0)
    np.testing.assert_allclose(r["land"][:2], 1 - (aim_x - np.array([-1.2, -0.3])) / es.LAND_SCALE, rtol=1e-6)
    c = es.shaped_reward(traj, es.Paddle(CFG), es.CONTACT)
    assert c["reward"][0] == pytest.approx(c["reward"][1])       # contact: a block is as good as a near miss


def test_the_shipped_es_policy_returns_balls():
    """The shipped weights are the return phase's: on 48 fresh narrow throws they hit most balls
    and return most of them to the opponent's half (the contact phase alone returned none)."""
    from ttmjx.tools import demos
    from ttmjx.world import thrower
    traj = demos.collect(CFG, "es", 48, seed=7)
    throws = thrower.sample_throws(jax.random.PRNGKey(8), CFG, 48)
    unperturbed = es.evaluate(CFG, *es.load_policy(CFG), throws, reward=es.RETURN)
    assert unperturbed["hit_rate"] >= 0.9 and unperturbed["return_rate"] >= 0.6, unperturbed
    assert np.mean(traj.hit) >= 0.8 and np.mean(traj.on_opponent) >= 0.4, (np.mean(traj.hit), np.mean(traj.on_opponent))
