"""Ball physics calibration on both backends, MEASURED from simulated trajectories.

* air: MJX with ttmjx.world.ballphysics forces flies 100 random throws (with and without spin) within
  1 cm of MuJoCo C's ellipsoid fluid model after 1 s;
* restitution for normal impacts at 2-10 m/s, every arrival phase: table 0.86-0.92, paddle
  0.72-0.82 (PHYSICS.md); the table COR of real thrower throws too;
* no tunnelling through table, paddle or net at 20 m/s, and the net never lets a ball through.

Bands come from PHYSICS.md / the issue; never widen them to pass: tune ttmjx.world.config.Contacts.
Every MJX experiment runs as batches of calibration.MJX_BATCH through one jit-compiled program
(module fixtures), so the file compiles MJX once (persistent cache: tests/conftest.py).
"""
import dataclasses
import functools
from typing import NamedTuple

import numpy as np
import pytest

from ttmjx.world import backends, scene
from ttmjx.tools import calibration as cal
from ttmjx.world.config import World

CFG = World()
TABLE_BAND = (0.86, 0.92)     # ball dropped from 30.5 cm bounces ~23 cm (PHYSICS.md)
PADDLE_BAND = (0.72, 0.82)    # inverted rubber, measured racket data (PHYSICS.md)
SPEEDS = (2.0, 4.0, 6.0, 8.0, 10.0)   # normal impact speeds of the COR bands (m/s)
MAX_SPEED = 20.0              # relative speed nothing may tunnel at (m/s)
PHASES = 16                   # arrival phases per speed
PARITY_TOL = 0.01             # m, after 1 s of free flight
N_PARITY, N_TABLE_THROWS, N_NET = 100, 28, 48
FLIGHT_STEPS = 100            # control steps: 1 s


# --- the experiments, built once ---------------------------------------------------------------
class Impacts(NamedTuple):
    parts: dict          # {name: (surface, slice of the batch)}
    qpos: np.ndarray
    qvel: np.ndarray
    net_side: np.ndarray


class Flights(NamedTuple):
    qpos: np.ndarray     # [128, ...]
    qvel: np.ndarray


# The experiments are built on first use, not at import: every xdist worker imports every module
# to collect it, and the throws' solve would compile in each of them.
@functools.cache
def impact_experiments() -> Impacts:
    """All impact experiments in one batch: {name: (surface, slice)} and qpos, qvel, side."""
    parts, qs, vs = {}, [], []
    ph = cal.arrival_phases(PHASES)
    for name, surface, speeds in (("table", "table", SPEEDS), ("paddle", "paddle", SPEEDS),
                                  ("table_fast", "table", [MAX_SPEED]),
                                  ("paddle_fast", "paddle", [MAX_SPEED]),
                                  ("net_fast", "net", [MAX_SPEED])):
        q, v = cal.impact_states(CFG, surface, speeds, ph)
        start = sum(len(x) for x in qs)
        parts[name] = (surface, slice(start, start + len(q)))
        qs.append(q), vs.append(v)
    q, v, side = cal.net_throws(CFG, seed=3, n=N_NET, max_speed=MAX_SPEED)
    start = sum(len(x) for x in qs)
    parts["net_throws"] = ("net", slice(start, start + len(q)))
    qs.append(q), vs.append(v)
    return Impacts(parts, np.concatenate(qs), np.concatenate(vs), side)


@functools.cache
def flight_experiments() -> Flights:
    """100 free-flight throws (half with spin) and 28 thrower throws: qpos, qvel [128, ...]."""
    half = N_PARITY // 2
    throws = [cal.free_flight_throws(CFG, seed=1, n=half, spin=False),
              cal.free_flight_throws(CFG, seed=2, n=N_PARITY - half, spin=True),
              cal.table_throws(CFG, seed=4, n=N_TABLE_THROWS)]
    pos, vel, spin, quat = (np.concatenate(x) for x in zip(*throws))
    return Flights(*cal.ball_states(CFG, pos, vel, spin, quat))




@pytest.fixture(scope="module")
def physics():
    c = backends.CPhysics(CFG)
    yield {"c": c, "mjx": backends.MjxPhysics(CFG)}
    c.close()


@pytest.fixture(scope="module")
def impacts(physics):
    """{backend: {experiment: (ball [B, T, 6], paddle [B, T, 3])}}, run on first use."""
    cache = {}

    def get(name):
        if name not in cache:
            ex = impact_experiments()
            ball, paddle = cal.ball_trajectories(physics[name], ex.qpos, ex.qvel, cal.IMPACT_CONTROL_STEPS)
            cache[name] = {k: (ball[s], paddle[s]) for k, (_, s) in impact_experiments().parts.items()}
        return cache[name]
    return get


@pytest.fixture(scope="module")
def flights(physics):
    """{backend: ball [128, 1000, 6]}: 1 s of the flight experiments, run on first use."""
    cache = {}

    def get(name):
        if name not in cache:
            ex = flight_experiments()
            cache[name] = cal.ball_trajectories(physics[name], ex.qpos, ex.qvel, FLIGHT_STEPS)[0]
        return cache[name]
    return get


def _outcome(impacts, backend, name):
    surface = impact_experiments().parts[name][0]
    return cal.impact_outcome(CFG, surface, *impacts(backend)[name])


def _table(cor, band):
    """Readable speed -> (min, mean, max) over arrival phases, for failure messages."""
    cor = cor.reshape(len(SPEEDS), PHASES)
    rows = [f"{v:4.1f} m/s: {c.min():.3f} / {c.mean():.3f} / {c.max():.3f}" for v, c in zip(SPEEDS, cor)]
    return f"band {band}, min / mean / max over {PHASES} arrival phases:\n" + "\n".join(rows)


# --- the measurement itself --------------------------------------------------------------------
def test_impact_outcome_measures_a_known_bounce():
    """A synthetic trajectory with a known bounce: 5 m/s in, 3 steps inside, 4 m/s out."""
    point, normal, half = cal.surface_face(CFG, "table")
    r, dt = CFG.ball.radius, CFG.physics_dt
    vz = np.array([-5.0] * 4 + [-2.0, 1.0, 4.0] + [4.0] * 5)
    z = np.empty_like(vz)
    z[0] = point[2] + r + 0.012
    for i in range(1, len(z)):
        z[i] = z[i - 1] + vz[i] * dt
    ball = np.zeros((1, len(z), 6))
    ball[0, :, :3] = point
    ball[0, :, 2], ball[0, :, 5] = z, vz
    out = cal.impact_outcome(CFG, "table", ball, np.zeros((1, len(z), 3)))
    assert out["cor"][0] == pytest.approx(0.8)
    assert out["depth"][0] == pytest.approx(r + point[2] - z.min())
    assert not out["through"][0]


# --- air ---------------------------------------------------------------------------------------
def test_air_forces_mjx_matches_mujoco_ellipsoid_model_within_1cm_after_1s(flights, physics):
    c, m = flights("c")[:N_PARITY, :, :3], flights("mjx")[:N_PARITY, :, :3]
    err = np.linalg.norm(m - c, axis=-1)             # [100, 1000]
    assert err[:, -1].max() < PARITY_TOL, (
        f"after 1 s: max {err[:, -1].max() * 100:.2f} cm, no spin max "
        f"{err[:N_PARITY // 2, -1].max() * 100:.2f} cm, spin max {err[N_PARITY // 2:, -1].max() * 100:.2f} cm")
    assert err.max() < PARITY_TOL
    # The test can see what it claims to check: without air the same throws end far away, and
    # the spin throws without their spin (no Magnus) end far away too.
    t = np.arange(1, c.shape[1] + 1) * CFG.physics_dt
    p0, v0 = flight_experiments().qpos[:N_PARITY, :3], flight_experiments().qvel[:N_PARITY, :3]
    vacuum = p0 + v0 * t[-1] + np.array([0, 0, -9.81 / 2]) * t[-1] ** 2
    assert np.linalg.norm(vacuum - c[:, -1], axis=-1).min() > 0.1
    spin = slice(N_PARITY // 2, N_PARITY)
    qvel = flight_experiments().qvel[spin].copy()
    qvel[:, 3:6] = 0.0
    no_magnus = cal.ball_trajectories(physics["c"], flight_experiments().qpos[spin], qvel, FLIGHT_STEPS)[0][:, -1, :3]
    assert np.median(np.linalg.norm(no_magnus - c[spin, -1], axis=-1)) > 0.1


# --- restitution -------------------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["c", "mjx"])
def test_table_cor_in_band_at_every_speed_and_arrival_phase(impacts, backend):
    cor = _outcome(impacts, backend, "table")["cor"]
    assert np.all((cor >= TABLE_BAND[0]) & (cor <= TABLE_BAND[1])), _table(cor, TABLE_BAND)


@pytest.mark.parametrize("backend", ["c", "mjx"])
def test_paddle_cor_in_band_at_every_speed_and_arrival_phase(impacts, backend):
    cor = _outcome(impacts, backend, "paddle")["cor"]
    assert np.all((cor >= PADDLE_BAND[0]) & (cor <= PADDLE_BAND[1])), _table(cor, PADDLE_BAND)


@pytest.mark.parametrize("backend", ["c", "mjx"])
def test_robot_free_throws_bounce_off_the_table_with_cor_in_band(flights, backend):
    bounce = cal.first_bounce(CFG, flights(backend)[N_PARITY:])
    assert np.all(bounce["x"] < 0) and np.all(bounce["x"] > -CFG.table.half_length), bounce["x"]
    cor = bounce["cor"]
    assert np.all((cor >= TABLE_BAND[0]) & (cor <= TABLE_BAND[1])), np.round(cor, 3)


# --- tunnelling and the net --------------------------------------------------------------------
@pytest.mark.parametrize("backend", ["c", "mjx"])
@pytest.mark.parametrize("name", ["table_fast", "paddle_fast", "net_fast"])
def test_no_tunnelling_at_20_mps(impacts, backend, name):
    out = _outcome(impacts, backend, name)
    assert not out["through"].any(), f"deepest {out['depth'].max() * 100:.2f} cm"
    assert np.all(out["cor"] > 0), out["cor"]    # every ball came back out on its own side


@pytest.mark.parametrize("backend", ["c", "mjx"])
def test_slower_impacts_never_reach_the_mid_plane(impacts, backend):
    for name in ("table", "paddle"):
        assert not _outcome(impacts, backend, name)["through"].any(), name


@pytest.mark.parametrize("backend", ["c", "mjx"])
def test_net_never_lets_a_ball_through(impacts, backend):
    ball, _ = impacts(backend)["net_throws"]
    passed = cal.net_passes(ball, impact_experiments().net_side)
    assert not passed.any(), f"{passed.sum()} of {len(passed)} net throws passed through"


# --- the constraint solver's caps --------------------------------------------------------------
CAPS_TOL = PARITY_TOL / 10    # m: the caps may move a ball by a tenth of what the backends may differ


def test_the_solver_caps_reach_both_backends_models():
    """world.contacts' caps are the MJCF's, so MuJoCo C and MJX solve with the same ones; a bad
    cap is refused naming the field."""
    caps = CFG.with_solver_caps(7, 3)
    for m in (scene.model(caps, fluid=True), scene.model(caps, fluid=False)):
        assert (m.opt.iterations, m.opt.ls_iterations) == (7, 3)
    with pytest.raises(ValueError, match=r"^world.contacts.line_search_iterations must be an integer in "
                                         r"\[1, 1000\], got 0$"):
        dataclasses.replace(CFG.contacts, line_search_iterations=0)


@pytest.mark.slow
def test_the_solver_caps_move_no_ball_on_mjx(impacts):
    """MJX at world.contacts' caps against MuJoCo's defaults (100 iterations of a 50-step line
    search) on every impact experiment (table, paddle, net, 20 m/s): the caps make MJX's batched
    solver cheaper (docs/BENCHMARKS.md, "The constraint solver's caps") and must not change a
    bounce: every ball within CAPS_TOL after each physics step."""
    defaults = CFG.with_solver_caps(100, 50)
    assert (CFG.contacts.solver_iterations, CFG.contacts.line_search_iterations) != (100, 50)
    ex = impact_experiments()
    ball, _ = cal.ball_trajectories(backends.MjxPhysics(defaults), ex.qpos, ex.qvel, cal.IMPACT_CONTROL_STEPS)
    for name, (_, s) in ex.parts.items():
        err = np.linalg.norm(impacts("mjx")[name][0][..., :3] - ball[s][..., :3], axis=-1).max()
        assert err < CAPS_TOL, f"{name}: {err * 1e3:.3f} mm"
