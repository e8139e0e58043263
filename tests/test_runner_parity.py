"""The robot runner plays as the training world predicts (deploy/sim/parity.py, `ttmjx robot
parity`): one export, the same goals, throws, start poses and timing draws, played by the world
(MuJoCo C) and by the runner on the simulated station, gives the same frames and sent commands
step for step (float32 against float64 arithmetic: 1e-4) and the same hits and landings (1 mm),

* under ideal timing (every physics step sensed at once, commands acting at once), and
* under the cell's training timing (CELL_TRAINING: the tracker at 125 Hz and the joints at 250 Hz,
  their latencies and the command delay drawn per episode, per-sample jitter), the world's draws
  set on the station.
"""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from ttmjx.world.config import CELL_TRAINING, TIMING_PROFILES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUN = os.path.join(ROOT, "tests", "data", "tiny_run_v0")     # a real two-member run (read only)
N, STEPS, SEED = 3, 40, 9          # seed 9: both timings hit at least one ball
TIMINGS = {"ideal": TIMING_PROFILES["zero"], "cell": CELL_TRAINING}


@pytest.fixture(scope="module")
def loaded(tmp_path_factory):
    """Member 0 of the tiny run, exported and loaded for the station."""
    from deploy.sim.export import export
    from deploy.sim.station import load_for_station
    from models.policy import member
    from training.checkpoint import load_checkpoint
    ck = load_checkpoint(RUN)
    out = export(member(ck.params, 0), ck.cfg.policy, ck.cfg.world, str(tmp_path_factory.mktemp("parity") / "policy"),
                 source="tiny_run_v0@member0")
    return load_for_station(out)


@pytest.fixture(scope="module", params=sorted(TIMINGS))
def played(request, loaded):
    """(timing name, WorldPlay, runner episodes, runner) on N uniform goals."""
    from deploy.sim import parity
    tm = TIMINGS[request.param]
    world = parity.world_play(loaded, tm, "c", N, seed=SEED)
    episodes, runner, _ = parity.runner_play(loaded, tm, world, seed=SEED)
    return request.param, world, episodes, runner


def test_the_runner_sees_and_sends_what_the_world_does(played):
    from deploy.sim import parity
    name, world, episodes, runner = played
    assert len(episodes) == N and all(ep.meta["end"] == "done" for ep in episodes)
    assert runner.skipped == runner.overruns == 0
    for i, ep in enumerate(episodes):
        steps = int(min(STEPS, world.tr.valid[i].sum()))
        assert steps >= 20
        diffs = parity.step_differences(world.tr, ep, i)
        for q, d in diffs.items():
            assert parity.first_part(d[:steps], parity.TOLERANCES[q]) is None, (name, i, q, d[:steps])
    if name == "cell":       # the draws are the cell's: delays randomized per episode, tick 0 after the launch
        assert len({round(float(x), 4) for x in world.draws.action_delay}) == N
        assert np.all(world.draws.n_exec > 0)


def test_the_runner_has_the_worlds_outcomes(played):
    from deploy.sim import parity
    name, world, episodes, _ = played
    rows = [parity.episode_row(world.tr, ep, i) for i, ep in enumerate(episodes)]
    assert any(r["hit"][0] for r in rows), "no episode hit: the comparison of landings would be empty"
    for r in rows:
        assert r["hit"][0] == r["hit"][1], (name, r)
        if r["hit"][0]:
            assert r["landing_diff_m"] <= parity.LANDING_TOL, (name, r)
    out = parity.summary(world, episodes, rows)
    assert out["gap_30cm_points"] == 0.0 and out["same_hit"] == N


def test_robot_parity_command_writes_its_table(loaded, tmp_path, capsys):
    from ttmjx.cli import main
    out_dir = tmp_path / "parity"
    main(["robot", "parity", "--policy", loaded.policy_dir, "--n", "2", "--seed", "7", "--out", str(out_dir), "--json"])
    line = capsys.readouterr().out.strip().splitlines()[-1]
    out = json.loads(line)
    assert out == json.load(open(out_dir / "parity.json"))
    assert (out_dir / "parity.png").stat().st_size > 0
    assert out["episodes"] == 2 and len(out["rows"]) == 2 and out["backend"] == "c" and out["timing"] == "trained"
    # the trained timing of this ideal-timing run is ideal: both sides agree to the end
    assert all(r["landing_diff_m"] is None or r["landing_diff_m"] <= 1e-3 for r in out["rows"])
    assert set(out["world"]) >= {"within_30cm", "within_20cm", "hit_rate", "on_opponent"}


def test_a_velocity_policy_sees_the_runners_tick_0_line(tmp_path):
    """16-value frames (the paper's original observation, the GPU presets' frame stacks): the
    runner reads tick 0 after its trigger, through the trigger's sample taken after the tick, so
    the ball's sensed velocity there is the line's slope, and that frame pads the whole stack;
    the world's tick-0 frame holds the same slope, not a lone sample's zero."""
    import dataclasses

    import jax

    from deploy.sim import parity
    from deploy.sim.export import export
    from deploy.sim.station import load_for_station
    from models import PolicyConfig, identity_normalizer, init_params
    from ttmjx.world.config import World
    pcfg = PolicyConfig(kind="framestack", hidden=16, layers=1, obs_size=16, frame_stack=8)
    params = init_params(jax.random.key(1), pcfg, identity_normalizer(16))
    world = dataclasses.replace(World(), ball_velocity_obs=True, timing=CELL_TRAINING)
    loaded = load_for_station(export(params, pcfg, world, str(tmp_path / "policy"), source="random-init"))
    played = parity.world_play(loaded, CELL_TRAINING, "c", 2, seed=3)
    episodes, _, _ = parity.runner_play(loaded, CELL_TRAINING, played, seed=3)
    for i, ep in enumerate(episodes):
        assert np.linalg.norm(played.tr.ball_vel[i, 0]) > 3.0          # a thrown ball's speed, m/s
        diffs = parity.step_differences(played.tr, ep, i, velocity=True)
        for q, d in diffs.items():
            assert parity.first_part(d[:STEPS], parity.TOLERANCES[q]) is None, (i, q, d[:STEPS])
