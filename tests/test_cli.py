"""The `ttmjx` commands as a user runs them: JSON last lines, datasets, plots, video, errors."""
import ctypes.util
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from ttmjx.world import record


def ttmjx(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "ttmjx.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def last_json(out):
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_throw_json_reports_frame_and_simulated_bounces():
    res = last_json(ttmjx("throw", "--distribution", "any", "--n", "5", "--seed", "3", "--json"))
    assert res["frame"] == {"table_top_z": 0.76, "table_x": [-1.37, 1.37], "table_y": [-0.7625, 0.7625]}
    assert len(res["throws"]) == 5
    for t in res["throws"]:
        assert set(t) == {"launch_pos", "launch_vel", "launch_spin", "aim", "bounce"}
        assert np.hypot(t["aim"][0] - t["bounce"][0], t["aim"][1] - t["bounce"][1]) < 0.02
        assert 5.0 <= np.linalg.norm(t["launch_vel"]) <= 9.0


def test_bench_c_reports_rates_against_the_raw_rollout_baseline():
    res = last_json(ttmjx("bench", "--backend", "c", "--batch", "16", "--json"))
    for k in ("physics_steps_per_s", "throws_per_s", "compile_s", "rollout_baseline_steps_per_s"):
        assert res[k] > 0, k


def test_demos_dataset_plot_and_no_overwrite(tmp_path):
    out = str(tmp_path / "d")
    res = last_json(ttmjx("demos", "--source", "scripted", "--distribution", "narrow", "--n", "24",
                          "--out", out, "--json"))
    assert set(res) == {"n", "hit_rate", "return_rate", "coverage", "seconds"} and res["n"] == 24
    assert res["hit_rate"] >= 0.9  # the narrow threshold, on a small sample
    traj, meta = record.load(out)
    assert traj.size == 24 and meta["source"] == "scripted" and meta["distribution"] == "narrow"
    assert meta["schema_version"] == record.SCHEMA_VERSION and "code_version" in meta
    again = ttmjx("demos", "--n", "4", "--out", out)
    assert again.returncode == 2 and "refusing to overwrite" in again.stderr
    png = last_json(ttmjx("plot-landings", out, "--json"))["plot"]
    assert os.path.getsize(png) > 10_000


def test_bad_input_is_refused_before_any_work(tmp_path):
    bad = ttmjx("throw", "--distribution", "wide")
    assert bad.returncode == 2 and "invalid choice: 'wide'" in bad.stderr
    bad = ttmjx("throw", "--n", "0")
    assert bad.returncode == 2 and "--n must be >= 1, got 0" in bad.stderr
    bad = ttmjx("plot-landings", str(tmp_path / "missing"))
    assert bad.returncode == 2 and "does not exist" in bad.stderr


def test_dataset_errors_name_the_file_and_problem(tmp_path):
    d = tmp_path / "broken"
    d.mkdir()
    with pytest.raises(record.RecordError, match="trajectories.npz: missing"):
        record.load(str(d))
    (d / "trajectories.npz").write_bytes(b"PK\x03\x04 truncated")
    (d / "trajectories.meta.json").write_text(json.dumps({"schema_version": record.SCHEMA_VERSION, "n": 1}))
    with pytest.raises(record.RecordError, match="truncated or corrupt"):
        record.load(str(d))
    (d / "trajectories.meta.json").write_text(json.dumps({"schema_version": 99, "n": 1}))
    with pytest.raises(record.RecordError, match="schema_version 99"):
        record.load(str(d))


@pytest.mark.skipif(ctypes.util.find_library("OSMesa") is None, reason="no OSMesa for headless rendering")
def test_render_writes_an_animated_gif(tmp_path):
    path = str(tmp_path / "throws.gif")
    res = last_json(ttmjx("render", "--n", "1", "--out", path, "--json"))
    assert res["video"] == path
    from PIL import Image
    with Image.open(path) as im:
        assert im.n_frames >= 20 and im.size == (480, 320)
