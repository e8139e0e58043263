"""The ball thrower: launches solved with drag land on their aim in MuJoCo C physics."""
import dataclasses
import math

import jax
import mujoco
import numpy as np
import pytest

from ttmjx.world import scene, thrower
from ttmjx.world.config import THROW_DISTRIBUTIONS, World

N = 60                 # throws per distribution (one compiled sampler serves all of them)
SEED = 7
CASES = [("narrow", False), ("any", False), ("varied", False), ("any", True)]


def _cfg(name, spin=False):
    return World().with_throws(name, spin=spin)


@pytest.fixture(scope="module")
def runs():
    """{(name, spin): (cfg, Throw as numpy, info, MuJoCo C simulation)}."""
    out = {}
    for name, spin in CASES:
        cfg = _cfg(name, spin)
        throw, info = thrower.sample_throws_info(jax.random.PRNGKey(SEED), cfg, N)
        throw = jax.tree.map(np.asarray, throw)
        out[(name, spin)] = (cfg, throw, jax.tree.map(np.asarray, info), thrower.simulate(cfg, throw))
    return out


@pytest.mark.parametrize("case", CASES, ids=[f"{n}{'-spin' if s else ''}" for n, s in CASES])
def test_simulated_bounce_within_2cm_of_aim(runs, case):
    cfg, throw, info, sim = runs[case]
    assert throw.launch_pos.shape == (N, 3) and throw.launch_vel.shape == (N, 3)
    assert throw.launch_spin.shape == (N, 3) and throw.aim.shape == (N, 2)
    assert info["valid"].all()
    err = np.linalg.norm(sim["bounce"] - throw.aim, axis=-1)
    assert np.all(np.isfinite(err)) and err.max() < 0.02, f"max bounce error {err.max():.4f} m"
    assert sim["bounced"].all()
    # The flight model predicts MuJoCo C's bounce (same forces, same integrator).
    pred = np.asarray(thrower.first_bounce(throw, cfg))
    assert np.abs(pred - sim["bounce"]).max() < 1e-3
    assert np.abs(pred - throw.aim).max() < cfg.throws.solve_tol


@pytest.mark.parametrize("case", CASES, ids=[f"{n}{'-spin' if s else ''}" for n, s in CASES])
def test_throws_clear_net_and_land_on_robot_half(runs, case):
    cfg, throw, _, sim = runs[case]
    t = cfg.table
    assert np.all(throw.launch_pos[:, 0] > t.half_length)          # behind the opponent's end line
    assert np.all(throw.launch_vel[:, 0] < 0)
    assert sim["clearance"].min() > 0.01                             # ball bottom over the net tape
    b = sim["bounce"]
    assert np.all((b[:, 0] < 0) & (b[:, 0] > -t.half_length) & (np.abs(b[:, 1]) < t.half_width))
    aim = throw.aim
    assert np.all((aim[:, 0] < 0) & (aim[:, 0] > -t.half_length) & (np.abs(aim[:, 1]) < t.half_width))


def test_first_contact_is_the_table_on_the_robots_half(runs):
    """mj_step a few throws and read MuJoCo's contact list: the first contact is ball-table."""
    cfg, throw, _, sim = runs[("any", False)]
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    ids = scene.ids(m)
    ball, table = m.geom("ball").id, m.geom("table").id
    for i in range(4):
        mujoco.mj_resetData(m, d)
        d.qpos[ids.ball_qpos:ids.ball_qpos + 7] = [*throw.launch_pos[i], 1, 0, 0, 0]
        d.qvel[ids.ball_qvel:ids.ball_qvel + 6] = [*throw.launch_vel[i], *throw.launch_spin[i]]
        for _ in range(2000):
            prev = d.qpos[ids.ball_qpos:ids.ball_qpos + 3].copy()
            mujoco.mj_step(m, d)
            if d.ncon:
                break
        assert d.ncon == 1 and {d.contact[0].geom1, d.contact[0].geom2} == {ball, table}
        # The contact was found at `prev` (collision runs before the integration).
        assert prev[0] < 0 and np.linalg.norm(prev[:2] - sim["bounce"][i]) < 0.01


def test_speeds_within_distribution_ranges(runs):
    th = World().throws
    for (name, _), (cfg, throw, _, _) in runs.items():
        speed = np.linalg.norm(throw.launch_vel, axis=-1)
        lo, hi = {"narrow": th.narrow_speed, "any": th.any_speed,
                  "varied": (th.varied_speed, th.varied_speed)}[name]
        assert np.all(speed > lo - 1e-4) and np.all(speed < hi + 1e-4), (name, speed.min(), speed.max())
    speed = np.linalg.norm(runs[("any", False)][1].launch_vel, axis=-1)
    assert speed.max() - speed.min() > 2.5                           # "any" really spans 5-9 m/s


def test_narrow_launches_from_one_position(runs):
    cfg, throw, _, _ = runs[("narrow", False)]
    np.testing.assert_allclose(throw.launch_pos, np.broadcast_to(cfg.throws.narrow_launch, (N, 3)), atol=1e-6)
    th = cfg.throws
    assert np.all((throw.aim[:, 0] >= th.narrow_aim_x[0]) & (throw.aim[:, 0] <= th.narrow_aim_x[1]))
    assert np.all((throw.aim[:, 1] >= th.narrow_aim_y[0]) & (throw.aim[:, 1] <= th.narrow_aim_y[1]))


def test_any_spreads_launches_and_aims(runs):
    cfg, throw, _, _ = runs[("any", False)]
    th = cfg.throws
    for axis, rng in enumerate((th.any_launch_x, th.any_launch_y, th.any_launch_z)):
        v = throw.launch_pos[:, axis]
        assert v.min() >= rng[0] - 1e-6 and v.max() <= rng[1] + 1e-6
        assert v.max() - v.min() > 0.5 * (rng[1] - rng[0])
    assert np.ptp(throw.aim[:, 0]) > 0.6 and np.ptp(throw.aim[:, 1]) > 0.9


def test_varied_cycles_three_launch_positions_and_sweeps_yaw(runs):
    cfg, throw, _, _ = runs[("varied", False)]
    th = cfg.throws
    expect_x = np.array(th.varied_launch_x)[np.arange(N) % 3]
    np.testing.assert_allclose(throw.launch_pos[:, 0], expect_x, atol=1e-6)
    np.testing.assert_allclose(throw.launch_pos[:, 1:], np.broadcast_to(th.varied_launch_yz, (N, 2)), atol=1e-6)
    # Without spin the flight stays in the vertical plane of the launch: yaw = aim direction.
    yaw = np.degrees(np.arctan2(-throw.launch_vel[:, 1], -throw.launch_vel[:, 0]))
    d = throw.aim - throw.launch_pos[:, :2]
    np.testing.assert_allclose(yaw, np.degrees(np.arctan2(-d[:, 1], -d[:, 0])), atol=0.05)
    lo, hi = th.varied_yaw_deg
    assert yaw.min() >= lo - 0.05 and yaw.max() <= hi + 0.05 and yaw.max() - yaw.min() > 0.6 * (hi - lo)


def test_spin_is_off_by_default_and_nonzero_when_on(runs):
    assert not World().throws.spin
    for (name, spin), (cfg, throw, _, _) in runs.items():
        if not spin:
            assert np.all(throw.launch_spin == 0)
        else:
            s = throw.launch_spin
            assert np.all(np.linalg.norm(s, axis=-1) > 0) and np.abs(s).max() <= cfg.throws.max_spin
            assert np.abs(s).max() > 0.5 * cfg.throws.max_spin


def test_deterministic_per_key(runs):
    cfg, throw, _, _ = runs[("narrow", False)]
    again = jax.tree.map(np.asarray, thrower.sample_throws(jax.random.PRNGKey(SEED), cfg, N))
    for a, b in zip(throw, again):
        np.testing.assert_array_equal(a, b)
    other = thrower.sample_throws(jax.random.PRNGKey(SEED + 1), cfg, N)
    assert not np.allclose(np.asarray(other.aim), throw.aim)


def test_jittable_and_vmappable():
    cfg = _cfg("varied")
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    out = jax.eval_shape(jax.vmap(lambda k: thrower.sample_throws(k, cfg, 5)), keys)
    assert out.launch_vel.shape == (3, 5, 3) and out.aim.shape == (3, 5, 2)
    lowered = jax.jit(thrower.sample_throws, static_argnums=(1, 2)).lower(keys[0], cfg, 5)
    assert lowered is not None


def test_throw_report_structure(runs):
    cfg, throw, _, sim = runs[("narrow", False)]
    rep = thrower.throw_report(cfg, N, SEED)
    assert set(rep) == {"frame", "throws"} and rep["frame"] == cfg.frame()
    assert len(rep["throws"]) == N
    for i, t in enumerate(rep["throws"]):
        assert set(t) == {"launch_pos", "launch_vel", "launch_spin", "aim", "bounce"}
        assert all(isinstance(x, float) for v in t.values() for x in v)
        assert len(t["aim"]) == 2 and len(t["bounce"]) == 2 and len(t["launch_pos"]) == 3
        assert math.dist(t["bounce"], t["aim"]) < 0.02
    np.testing.assert_allclose([t["aim"] for t in rep["throws"]], throw.aim, atol=1e-6)


def test_bad_input_raises():
    with pytest.raises(ValueError, match=r"'bogus'.*narrow.*any.*varied"):
        World().with_throws("bogus")
    cfg = World()
    broken = dataclasses.replace(cfg.throws)
    object.__setattr__(broken, "name", "lobs")
    bad_cfg = dataclasses.replace(cfg)
    object.__setattr__(bad_cfg, "throws", broken)
    for call in (lambda: thrower.sample_throws(jax.random.PRNGKey(0), bad_cfg, 4),
                 lambda: thrower.throw_report(bad_cfg, 4, 0)):
        with pytest.raises(ValueError, match=r"'lobs'.*" + ".*".join(THROW_DISTRIBUTIONS)):
            call()
    for n in (0, -3):
        with pytest.raises(ValueError, match=rf"n .*>= 1, got {n}"):
            thrower.sample_throws(jax.random.PRNGKey(0), cfg, n)
        with pytest.raises(ValueError, match=rf">= 1, got {n}"):
            thrower.throw_report(cfg, n, 0)
