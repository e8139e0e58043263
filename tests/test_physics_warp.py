"""MuJoCo Warp as MJX's implementation (`--world.mjx-impl warp`) plays the same physics as MJX in
JAX: every impact experiment of tests/test_physics.py (table, paddle and net at 2-20 m/s, every
arrival phase) keeps the measured restitution bands of PHYSICS.md, nothing tunnels, and each
throw's track stays within 1 cm of MJX-JAX's over the whole experiment (the two agree to ~1e-5 m
in the median: float32 and a different solver's arithmetic, not different physics).

Slow (Warp compiles its kernels for the CPU on first use, ~40 s; cached in ~/.cache/warp).
Needs warp-lang (`pip install 'ttmjx[warp]'`); skipped without it.
"""
import dataclasses

import numpy as np
import pytest

pytest.importorskip("warp")
pytestmark = pytest.mark.slow

from ttmjx.tools import calibration as cal  # noqa: E402
from ttmjx.world import backends  # noqa: E402
from ttmjx.world.config import World  # noqa: E402

import test_physics as tp  # noqa: E402

TRACK_TOL = 0.01   # m, the same tolerance as MJX against MuJoCo C after 1 s of flight


@pytest.fixture(scope="module")
def tracks():
    """{impl: (ball [B, T, 6], paddle [B, T, 3])} of the impact experiments on both implementations."""
    ex = tp.impact_experiments()
    out = {}
    for impl in ("jax", "warp"):
        physics = backends.MjxPhysics(dataclasses.replace(World(), mjx_impl=impl))
        out[impl] = cal.ball_trajectories(physics, ex.qpos, ex.qvel, cal.IMPACT_CONTROL_STEPS)
    return out


@pytest.mark.parametrize("name,band", [("table", tp.TABLE_BAND), ("paddle", tp.PADDLE_BAND),
                                       ("table_fast", tp.TABLE_BAND), ("paddle_fast", tp.PADDLE_BAND)])
def test_warp_restitution_in_band_and_no_tunnelling(tracks, name, band):
    surface, s = tp.impact_experiments().parts[name]
    ball, paddle = tracks["warp"]
    out = cal.impact_outcome(World(), surface, ball[s], paddle[s])
    assert np.all((out["cor"] >= band[0]) & (out["cor"] <= band[1])), (name, out["cor"])
    assert not out["through"].any(), name


def test_warp_net_stops_what_jax_stops(tracks):
    surface, s = tp.impact_experiments().parts["net_fast"]
    out = cal.impact_outcome(World(), surface, tracks["warp"][0][s], tracks["warp"][1][s])
    assert not out["through"].any()


def test_warp_tracks_follow_mjx_jax(tracks):
    gap = np.abs(tracks["warp"][0][..., :3] - tracks["jax"][0][..., :3]).max(axis=(1, 2))   # [B] m
    assert gap.max() < TRACK_TOL, f"worst throw {gap.max():.4f} m (median {np.median(gap):.2e} m)"


def test_warp_refused_naming_the_fix_without_warp(monkeypatch):
    import importlib.util
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: None if n == "warp" else real(n, *a))
    with pytest.raises(RuntimeError, match=r"ttmjx\[warp\]"):
        backends.MjxPhysics(dataclasses.replace(World(), mjx_impl="warp"))


def test_unknown_impl_refused():
    with pytest.raises(ValueError, match="mjx_impl"):
        World(mjx_impl="cuda")
