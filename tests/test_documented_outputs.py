"""Outputs against docs/DATA.md under the settings the docs describe: a run's metrics.jsonl (the
session's recorded tiny run), a dataset's truth arrays, a dry run's robot episode logs. (eval --out
under the cell's timing: tests/test_true_tracks.py; at ideal timing: tests/test_eval_goals.py; the
simulated station's logs: tests/test_station.py, tests/test_true_tracks.py; experiment tables:
tests/test_table_outputs.py.)"""
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


def test_a_dry_run_episode_log_holds_the_documented_metadata(tmp_path):
    """`ttmjx robot run --station fake --goals five --out DIR --json` (no export: the dry run's
    ball follower) under the default runner settings: session.json is the printed summary and
    every episode's meta.json holds DATA.md's keys, recomputed from its arrays, the contract
    the dry run plays and RunnerConfig's defaults; no events, so no outcomes in the record."""
    import contextlib
    import dataclasses
    import io

    from deploy.robot import Contract, RunnerConfig
    from deploy.robot.cli import DRY_RUN_FRAMES, DRY_RUN_HZ
    from documented import SESSION_KEYS, check_episode_meta
    from ttmjx.entry import main
    from ttmjx.world.goals import five_goals
    out = str(tmp_path / "logs")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        main(["robot", "run", "--station", "fake", "--goals", "five", "--out", out, "--json"])
    session = json.loads(printed.getvalue().strip().splitlines()[-1])
    assert json.loads((tmp_path / "logs" / "session.json").read_text()) == session
    assert set(session) == SESSION_KEYS and session["episodes"] == session["goals"] == 5
    contract = dataclasses.replace(Contract(), control_hz=DRY_RUN_HZ, frame_stack=DRY_RUN_FRAMES)
    for i in range(5):
        meta = check_episode_meta(out, i, session, five_goals(1)[0], contract, RunnerConfig(), station="fake")
        assert meta["end"] == "done"
