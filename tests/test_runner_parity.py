"""With ideal timing the robot runner feeds the policy what evaluation feeds it: the same policy
member, goals, throws and start poses, played by `ttmjx eval`'s rollout (MuJoCo C) and by the
runner on the simulated station (zero sensor delays, every physics step sampled, compute time
not charged, tick 0 at the launch), give the same frames and commands, step for step."""
from __future__ import annotations

import os
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "scripts"))
import runner_vs_eval  # noqa: E402

RUN = os.path.join(ROOT, "tests", "data", "tiny_run_v0")     # a real two-member run (read only)
N, STEPS = 3, 40


@pytest.fixture(scope="module")
def played(tmp_path_factory):
    """(evaluation Trajectories, runner episodes) of member 0 on N uniform goals."""
    from deploy.sim.export import export
    cfg, params, goals, throws, tr = runner_vs_eval.evaluation(RUN, 0, N, seed=7)
    out = export(params, cfg.policy, cfg.world, str(tmp_path_factory.mktemp("parity") / "policy"),
                 source="tiny_run_v0@member0")
    poses = np.asarray(tr.obs[:, 0, :8], np.float64)
    episodes, runner, _ = runner_vs_eval.runner_play(out, goals, runner_vs_eval.station_throws(throws), poses)
    return tr, episodes, runner


def test_ideal_runner_sees_and_sends_what_evaluation_does(played):
    tr, episodes, runner = played
    assert len(episodes) == N and all(ep.meta["end"] == "done" for ep in episodes)
    assert runner.skipped == runner.overruns == 0
    for i, ep in enumerate(episodes):
        steps = int(min(STEPS, tr.valid[i].sum()))
        assert steps >= 20
        div = runner_vs_eval.first_divergence(tr.obs[i], tr.actions[i], ep.traj.obs[0],
                                              ep.extras["commands"], steps)
        assert div is None, f"episode {i}: {div}"
        np.testing.assert_allclose(ep.extras["t_grid"] - ep.meta["events"]["t_launch"],
                                   np.arange(len(ep.extras["t_grid"])) * runner.contract.dt, atol=1e-9)


def test_ideal_runner_has_the_evaluations_outcomes(played):
    tr, episodes, _ = played
    rows = runner_vs_eval.episode_rows(tr, episodes, STEPS)
    assert [r["hit"][0] for r in rows] == [r["hit"][1] for r in rows]
    for r in rows:
        np.testing.assert_allclose(r["landing"][1], r["landing"][0], atol=1e-3)
