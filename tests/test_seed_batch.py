"""`ttmjx eval BATCH` (eval/seed_batch.py): every seed of a batch scored as its own run, then the
mean and the sample spread over the seeds; a single run is no batch; --out is refused for a
batch, naming it. (tests/test_seeds.py scores a real batch through the command.)"""
import json
import os

import pytest

from eval import evaluate as evaluation
from eval.seed_batch import evaluate_seeds
from training.rundir import SEEDS_FILE


def test_every_seed_then_the_spread(tmp_path, monkeypatch):
    (tmp_path / SEEDS_FILE).write_text(json.dumps({"run_dirs": ["seed0", "seed1", "seed2"]}))
    scores = {"seed0": 0.1, "seed1": 0.2, "seed2": 0.6}
    asked = []

    def score(d, goals, per_goal, distribution, backend, seed, member, step, out=None):
        asked.append((os.path.basename(d), goals, seed, member, step, out))
        return {"within_30cm": scores[os.path.basename(d)], "per_goal": {}, "note": "text"}
    monkeypatch.setattr(evaluation, "evaluate_checkpoint", score)
    out = evaluate_seeds(str(tmp_path), "8", 40, None, None, 7, 1, 3)
    assert asked == [(f"seed{s}", "8", 7, 1, 3, None) for s in range(3)]
    assert out["seeds"] == 3 and [r["eval_within_30cm"] for r in out["runs"]] == [0.1, 0.2, 0.6]
    assert out["eval_within_30cm_mean"] == pytest.approx(0.3)
    assert out["eval_within_30cm_std"] == pytest.approx(0.264575, rel=1e-5)     # n - 1 in the denominator
    assert evaluate_seeds(str(tmp_path / "single"), "8", 40, None, None, 7, None, None) is None
    with pytest.raises(ValueError, match=r"^--out with .* \(a batch of 3 seeds\): choose one with --seed-index$"):
        evaluate_seeds(str(tmp_path), "8", 40, None, None, 7, None, None, out="o")
