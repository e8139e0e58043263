"""`ttmjx eval BATCH` (eval/seed_batch.py): every seed of a batch scored as its own run, all of
them the lanes of one rollout (eval/evaluate.py evaluate_checkpoints), then the mean and the
sample spread over the seeds; a single run is no batch; --out is refused for a batch, naming it.
(tests/test_seeds.py scores a trained batch through the command.)"""
import dataclasses
import json
import math
import os

import numpy as np
import pytest

from eval import evaluate as evaluation
from eval.evaluate import evaluate_checkpoint, evaluate_checkpoints, lane_metrics, shared_config
from eval.seed_batch import evaluate_seeds
from training import runconfig
from training.rundir import SEEDS_FILE
from training.seeds import seed_configs, seed_run_dirs
from training.trainer import Run
from ttmjx.world.record import Trajectories


def test_every_seed_in_one_call_then_the_spread(tmp_path, monkeypatch):
    (tmp_path / SEEDS_FILE).write_text(json.dumps({"run_dirs": ["seed0", "seed1", "seed2"]}))
    scores = {"seed0": 0.1, "seed1": 0.2, "seed2": 0.6}
    asked = []

    def score(dirs, goals, per_goal, distribution, backend, seed, member, step, out=None):
        asked.append(([os.path.basename(d) for d in dirs], goals, seed, member, step, out))
        return [{"within_30cm": scores[os.path.basename(d)], "per_goal": {}, "note": "text"} for d in dirs]
    monkeypatch.setattr(evaluation, "evaluate_checkpoints", score)
    out = evaluate_seeds(str(tmp_path), "8", 40, None, None, 7, 1, 3)
    assert asked == [(["seed0", "seed1", "seed2"], "8", 7, 1, 3, None)]      # one evaluation, every seed a lane
    assert out["seeds"] == 3 and [r["eval_within_30cm"] for r in out["runs"]] == [0.1, 0.2, 0.6]
    assert out["eval_within_30cm_mean"] == pytest.approx(0.3)
    assert out["eval_within_30cm_std"] == pytest.approx(0.264575, rel=1e-5)     # n - 1 in the denominator
    assert evaluate_seeds(str(tmp_path / "single"), "8", 40, None, None, 7, None, None) is None
    with pytest.raises(ValueError, match=r"^--out with .* \(a batch of 3 seeds\): choose one with --seed-index$"):
        evaluate_seeds(str(tmp_path), "8", 40, None, None, 7, None, None, out="o")


@pytest.fixture(scope="module")
def seed_batch(tmp_path_factory):
    """A real batch of 2 tiny seeds (no demonstrations) at their initial checkpoints: nothing
    trained, two different policies (each seed's own initialisation)."""
    base = dataclasses.replace(runconfig.tiny(), demos=0, pretrain_steps=0,
                               run_dir=str(tmp_path_factory.mktemp("seeds") / "batch"))
    Run(seed_configs(base, 2), None, progress=False, parent=base.run_dir).start()
    return base.run_dir


def numbers(metrics: dict) -> dict:
    return {f"eval_{k}": v for k, v in metrics.items() if isinstance(v, (int, float))}


def comparable(x):
    """x with every float NaN as None (NaN != NaN: an untrained policy lands nothing, so its mean
    distances are NaN), nested dicts and lists included."""
    if isinstance(x, dict):
        return {k: comparable(v) for k, v in x.items()}
    if isinstance(x, list):
        return [comparable(v) for v in x]
    return None if isinstance(x, float) and math.isnan(x) else x


def test_each_lane_of_a_real_batch_scores_what_its_seed_scores_alone(seed_batch, monkeypatch):
    """The same goals, throws and keys in every lane: a seed's figures are those of
    `ttmjx eval BATCH --seed-index K`, exactly, and so is every lane's record (an untrained
    policy hits nothing, so the figures alone would not tell the lanes apart)."""
    records = []

    def recorded(tr, goals, *rest):
        records.append((tr, goals))
        return lane_metrics(tr, goals, *rest)
    monkeypatch.setattr(evaluation, "lane_metrics", recorded)
    dirs = seed_run_dirs(seed_batch)
    # the five goals twice each throughout: one count of throws, so one thrower program per lane count
    out = evaluate_seeds(seed_batch, "five", 2, None, "c", 7, None, None)
    alone = [evaluate_checkpoint(d, "five", 2, backend="c", seed=7) for d in dirs]
    assert comparable(out["runs"]) == comparable([{"run_dir": d, **numbers(m)} for d, m in zip(dirs, alone)])
    assert alone[0]["goals"] == 10 and alone[0]["step"] == 0
    batched, one = records[:2], records[2:]
    for s in range(2):
        for name, x, y in zip(Trajectories._fields, batched[s][0], one[s][0]):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=f"seed {s}: {name}")
        np.testing.assert_array_equal(batched[s][1], one[s][1])
    # two policies, not one copied: the lanes' actions differ
    assert not np.array_equal(np.asarray(batched[0][0].actions), np.asarray(batched[1][0].actions))
    # one member alone in every lane, on the five goals (per-goal figures included)
    lanes = evaluate_checkpoints(dirs, "five", 2, None, "c", 7, member_index=1)
    assert comparable(lanes) == comparable([evaluate_checkpoint(d, "five", 2, backend="c", seed=7, member_index=1)
                                            for d in dirs])
    assert set(lanes[0]["per_goal"]) == set("ABCDE")
    with pytest.raises(ValueError, match=r"^--member 2 is out of range: the run has 2 members$"):
        evaluate_checkpoints(dirs, "five", 2, backend="c", member_index=2)
    with pytest.raises(ValueError, match=r"out='o' with 2 runs: the records are one run's; expected one run"):
        evaluate_checkpoints(dirs, "five", 2, backend="c", out="o")


def test_runs_played_together_must_share_the_rollout(tmp_path):
    """The first run and field that differ are named, with both values."""
    a = runconfig.tiny()
    b = dataclasses.replace(a, seed=3, policy=dataclasses.replace(a.policy, hidden=32))
    assert shared_config(["a", "b"], [a, dataclasses.replace(a, seed=3)], None) is a     # the seed is a lane's own
    with pytest.raises(ValueError, match=r"^b: policy.hidden is 32, a's is 64; runs evaluated together must share"):
        shared_config(["a", "b"], [a, b], None)
    c = dataclasses.replace(a, world=a.world.with_throws("any"))
    with pytest.raises(ValueError, match=r"^c: world.throws.name is 'any', a's is 'narrow'"):
        shared_config(["a", "b", "c"], [a, a, c], None)
    with pytest.raises(ValueError, match=r"^b: train.members is 4, a's is 2"):
        shared_config(["a", "b"], [a, dataclasses.replace(a, train=dataclasses.replace(a.train, members=4))], None)
