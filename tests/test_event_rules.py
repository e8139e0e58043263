"""The event rules (hit, bounce on the robot's half, net, landing, on the opponent's half, done)
have one definition, ttmjx.world.env.update_events. The simulation folds it over each control
step's physics steps (env.advance); the simulated station (deploy/sim/station.py) folds it over one
physics step at a time as it steps MuJoCo C. On the same recorded ball/paddle tracks both must
give identical events."""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from deploy.robot import Contract
from deploy.sim.station import SimStation, fold_physics_steps
from ttmjx.world import env
from ttmjx.world.config import World

CFG = World()
HOME = np.asarray(CFG.robot.home)
NO_SPIN, AIM = (0.0, 0.0, 0.0), (-1.2, 0.0)
# Launch position and velocity of each track, the robot held at home; the blade centre is at
# (-1.24, 0, 1.23), nearly level.
LAUNCHES = {
    "hit-to-opponent": ((-1.40, 0.0, 1.31), (4.5, 0.0, -1.0)),     # onto the blade, toward the opponent
    "bounce-own-then-hit": ((-0.7, 0.0, 1.0), (-1.0, 0.0, -3.5)),  # table first, then the blade
    "net": ((0.5, 0.0, 0.85), (-5.0, 0.0, 0.0)),                   # low into the net
    "hit-off-table": ((-0.6, 0.0, 1.38), (-4.0, 0.0, 0.0)),        # off the blade, behind the robot
    "unhit": ((1.5, 0.6, 1.1), (-6.0, 0.3, 1.2)),                  # bounces wide of the robot
}
# What each track must show: (hit, bounce_own, net, landed, on_opponent).
EXPECTED = {
    "hit-to-opponent": (True, False, False, True, True),
    "bounce-own-then-hit": (True, True, False, True, False),
    "net": (False, False, True, False, False),
    "hit-off-table": (True, False, False, True, False),
    "unhit": (False, True, False, False, False),
}
UPDATE = jax.jit(functools.partial(env.update_events, CFG))  # (events, t, ball_prev, ball, paddle)


def record_track(launch):
    """One throw on the station: its events and the recorded track, ball [S, 6] (position and
    velocity after each physics step) and blade centre paddle [S, 3], from the launch."""
    st = SimStation(CFG, Contract(), q0=HOME)
    st.trace = []
    st.throw_in(0.0, (*launch, NO_SPIN, AIM))
    ev = st.finish_throw()
    ball, paddle = (np.stack(x) for x in zip(*st.trace))
    return ev, ball, paddle


@pytest.fixture(scope="module")
def tracks():
    return {name: record_track(launch) for name, launch in LAUNCHES.items()}


def simulation_events(launch, ball, paddle) -> env.Events:
    """env.update_events once per control step, each over its cfg.substeps physics steps, as
    env.advance applies it in the simulation (the steps of a last, partial control step unused)."""
    s = CFG.substeps
    ev, prev = env.no_events(), np.r_[launch[0], launch[1]]
    for c in range(len(ball) // s):
        steps = slice(c * s, (c + 1) * s)
        ev = UPDATE(ev, jnp.int32(c), jnp.asarray(prev, jnp.float32),
                    jnp.asarray(ball[steps], jnp.float32), jnp.asarray(paddle[steps], jnp.float32))
        prev = ball[steps][-1]
    return ev


def assert_same_events(station, ev: env.Events) -> None:
    """The station's ThrowEvents hold the flags and the landing of env.Events ev."""
    flags = ("hit", "bounce_own", "net", "landed", "on_opponent", "done")
    assert {f: getattr(station, f) for f in flags} == {f: bool(getattr(ev, f)) for f in flags}
    np.testing.assert_array_equal(station.landing.astype(np.float32), np.asarray(ev.landing))


def control_step(t: float) -> int:
    """The control step of a station event at time t (launch at 0, physics step n ends at n dt)."""
    return -1 if not np.isfinite(t) else (int(round(t / CFG.physics_dt)) - 1) // CFG.substeps


@pytest.mark.parametrize("name", LAUNCHES)
def test_station_and_simulation_give_identical_events_on_one_track(tracks, name):
    station, ball, paddle = tracks[name]
    sim = simulation_events(LAUNCHES[name], ball, paddle)
    assert bool(sim.done) and station.done
    assert_same_events(station, sim)
    assert control_step(station.t_hit) == int(sim.hit_step)
    assert control_step(station.t_done) == int(sim.done_step)


@pytest.mark.parametrize("name", ["hit-to-opponent", "unhit"])
def test_folding_a_whole_track_at_once_gives_the_station_events(tracks, name):
    """fold_physics_steps over all of a track in one call (many compiled chunks, the last one
    padded) equals the station's events, folded as it stepped."""
    station, ball, paddle = tracks[name]
    prev = np.concatenate([np.r_[LAUNCHES[name][0], LAUNCHES[name][1]][None], ball[:-1]])
    ev = fold_physics_steps(CFG, env.no_events(), np.arange(1, len(ball) + 1), prev, ball, paddle)
    assert_same_events(station, ev)
    assert int(ev.done_step) * CFG.physics_dt == pytest.approx(station.t_done)


@pytest.mark.parametrize("name", LAUNCHES)
def test_each_track_shows_its_case(tracks, name):
    ev, _, _ = tracks[name]
    assert (ev.hit, ev.bounce_own, ev.net, ev.landed, ev.on_opponent) == EXPECTED[name]
    assert ev.done and ev.fell == (not ev.landed)
    half_length, half_width = CFG.table.half_length, CFG.table.half_width
    if name == "hit-to-opponent":
        assert 0 < ev.landing[0] <= half_length and abs(ev.landing[1]) <= half_width
    if name == "hit-off-table":
        assert ev.landing[0] < -half_length                      # fell past the robot's end line
    if ev.hit:
        assert 0 < ev.t_hit < ev.t_done
    else:
        assert np.isnan(ev.t_hit) and np.all(np.isnan(ev.landing))
