"""Outputs against docs/DATA.md under the settings the docs describe: a run's metrics.jsonl (the
session's recorded tiny run), a dataset's truth arrays. (eval --out under the cell's timing:
tests/test_true_tracks.py; at ideal timing: tests/test_eval_goals.py.)"""
import json

import numpy as np
import pytest

from documented import check_metrics_rows
from ttmjx.world import record


def test_metrics_jsonl_holds_the_documented_keys_and_they_mean_it(recorded_tiny_run):
    from training.runconfig import from_json
    run_dir, _ = recorded_tiny_run
    cfg = from_json(json.loads((run_dir / "config.json").read_text()))
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    check_metrics_rows(rows, cfg)


def test_a_dataset_keeps_its_truth_beside_the_record_and_refuses_a_clash(tmp_path):
    b, t = 2, 3
    traj = record.Trajectories(
        obs=np.zeros((b, t, 13)), ball_vel=np.zeros((b, t, 3)), actions=np.zeros((b, t, 8)), valid=np.ones((b, t), bool),
        goal=np.zeros((b, 2)), hit=np.zeros(b, bool), hit_step=np.full(b, -1), landing=np.full((b, 2), np.nan),
        on_opponent=np.zeros(b, bool), bounce_own=np.zeros(b, bool), net=np.zeros(b, bool),
        launch_pos=np.zeros((b, 3)), launch_vel=np.zeros((b, 3)), launch_spin=np.zeros((b, 3)), aim=np.zeros((b, 2)))
    truth = {"true_ball_pos": np.arange(b * t * 3, dtype=np.float32).reshape(b, t, 3)}
    record.save(str(tmp_path / "d"), traj, {"source": "test"}, extra=truth)
    back, _ = record.load(str(tmp_path / "d"))
    assert back.size == b
    extra = record.extra_arrays(str(tmp_path / "d"))
    assert list(extra) == ["true_ball_pos"]
    np.testing.assert_array_equal(extra["true_ball_pos"], truth["true_ball_pos"])
    for bad in ({"obs": np.zeros((b, t, 3))}, {"true_ball_pos": np.zeros((b + 1, t, 3))}):
        with pytest.raises(record.RecordError, match="extra array"):
            record.save(str(tmp_path / "e"), traj, {"source": "test"}, extra=bad)
