"""The export's timing record: the contract records the timing model and ranges the
policy was trained under, hashed; `ttmjx robot run` plays that timing by default and refuses,
with one line and exit code 2, a station outside it (unless told to play it anyway, and then
the summary says so), an export without the record, and an unknown profile name. Presets train
under the cell's timing; ideal timing is an explicit choice."""
from __future__ import annotations

import copy
import dataclasses
import json
import os
import shutil

import jax
import numpy as np
import pytest

from deploy.robot.exported import CONTRACT_FILE, MANIFEST_FILE, load_export, read_contract
from deploy.robot.timing_check import (
    TimingError,
    check_station,
    outside_trained,
    station_timing,
    timing_record,
    trained_timing,
)
from deploy.sim.export import export
from models import PolicyConfig, identity_normalizer, init_params
from training import runconfig
from ttmjx.world import files
from ttmjx.world.config import CELL_TRAINING, IDEAL, TIMING_PROFILES, Timing, World


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """A tiny random-init LSTM exported twice at 20 Hz: trained (so its contract says) under the
    cell's timing, and under ideal timing."""
    pcfg = PolicyConfig(hidden=8, layers=1)
    params = init_params(jax.random.key(0), pcfg, identity_normalizer(13))
    root = tmp_path_factory.mktemp("timing_contract")
    return {name: export(params, pcfg, World(timing=tm), str(root / name), control_hz=20, source="random-init")
            for name, tm in (("cell", CELL_TRAINING), ("ideal", IDEAL))}


def without_timing_record(src: str, dst: str) -> str:
    """A copy of an export as exported before exports carried it: no `timing` section, manifest re-hashed."""
    from deploy.sim.export import write_manifest
    shutil.copytree(src, dst)
    doc = json.load(open(os.path.join(dst, CONTRACT_FILE)))
    del doc["timing"]
    files.write_bytes(os.path.join(dst, CONTRACT_FILE), (json.dumps(doc, indent=1) + "\n").encode())
    os.remove(os.path.join(dst, MANIFEST_FILE))
    write_manifest(dst, {n: open(os.path.join(dst, n), "rb").read() for n in os.listdir(dst)})
    return dst


def test_presets_train_under_the_cells_timing_and_ideal_is_explicit():
    for name in ("default", "cpu", "gpu", "lfp", "gcsl", "paper-sim", "paper-sim-new"):
        tm = runconfig.preset(name).world.timing
        assert tm == CELL_TRAINING and not tm.ideal and tm.delay_spread_s > 0, name
    assert runconfig.preset("tiny").world.timing.ideal_timing            # chosen, for the recorded numbers
    # the explicit choice resets every field of a profile to ideal
    chosen = dataclasses.replace(CELL_TRAINING, ideal_timing=True)
    assert chosen.ideal and chosen.tracker_hz is None and chosen.action_delay_s == 0 == chosen.delay_spread_s
    from ttmjx.cli import parse_train
    a = parse_train(["--world.timing.ideal-timing"])
    assert a.config.world.timing.ideal


def test_the_contract_records_the_trained_timing_and_its_ranges_hashed(exports):
    doc = read_contract(exports["cell"])
    rec = trained_timing(doc, exports["cell"])
    assert rec["timing"] == CELL_TRAINING and rec["ranges"] == json.loads(json.dumps(CELL_TRAINING.trained_ranges()))
    assert rec["ranges"]["tracker_hz"] == 125.0 and rec["ranges"]["joint_hz"] == 250.0
    lo, hi = rec["ranges"]["action_delay_s"]
    assert lo == 0.0 and hi == pytest.approx(0.018)     # nominal 8 ms +- 10 ms, never below zero
    assert rec["randomized_per_episode"] and not rec["ideal"]
    assert doc["timing"] == json.loads(json.dumps(timing_record(CELL_TRAINING)))
    # hashed: a changed range or model no longer matches the record's sha256
    for path in (("ranges", "action_delay_s"), ("model", "delay_spread_s")):
        bad = copy.deepcopy(doc)
        bad["timing"][path[0]][path[1]] = [0.0, 0.5] if path[0] == "ranges" else 0.5
        with pytest.raises(TimingError, match="sha256"):
            trained_timing(bad)
    ideal = trained_timing(read_contract(exports["ideal"]))
    assert ideal["ideal"] and ideal["ranges"]["tracker_hz"] is None


def test_the_station_plays_the_trained_timing_and_refuses_what_is_outside(exports):
    cell, ideal = (trained_timing(read_contract(exports[k])) for k in ("cell", "ideal"))
    drifting, src = station_timing(cell, None)
    assert src == "export" and drifting.centre() == TIMING_PROFILES["nominal"] and max(drifting.spreads()) > 0
    assert not outside_trained(cell, drifting)
    tm, src = station_timing(cell, "centre")
    assert src == "centre" and tm == TIMING_PROFILES["nominal"] and not outside_trained(cell, tm)
    assert not outside_trained(cell, dataclasses.replace(tm, action_delay_s=0.017))
    late = dataclasses.replace(tm, action_delay_s=0.030)
    assert [s.split()[0] for s in outside_trained(cell, late)] == ["action_delay_s"]
    with pytest.raises(TimingError, match="outside what the policy was trained under"):
        check_station(cell, late, "late")
    summary = check_station(cell, late, "late", allow_untrained=True)
    assert summary["override"] and not summary["within_trained"] and summary["outside"]
    # an ideal-trained policy refuses the cell's timing, and a cell-trained one the ideal station
    assert outside_trained(ideal, TIMING_PROFILES["nominal"]) and outside_trained(cell, TIMING_PROFILES["zero"])
    assert not outside_trained(ideal, Timing())
    with pytest.raises(TimingError, match="unknown station timing profile 'bogus'"):
        station_timing(cell, "bogus")


def _one_line_exit_2(capsys, argv):
    from ttmjx.cli import main
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and len(err.splitlines()) == 1, err
    return err


def test_robot_run_refuses_bad_timing_with_one_line_and_exit_2(exports, tmp_path, capsys):
    run = ["robot", "run", "--station", "sim", "--goals", "0.7,0.3"]
    err = _one_line_exit_2(capsys, [*run, "--policy", exports["cell"], "--timing", "zero"])
    assert "outside what the policy was trained under" in err and "--allow-untrained-timing" in err
    err = _one_line_exit_2(capsys, [*run, "--policy", exports["ideal"]] + ["--timing", "nominal"])
    assert "action_delay_s 8 ms (trained 0 ms..0 ms)" in err
    err = _one_line_exit_2(capsys, [*run, "--policy", exports["cell"], "--timing", "bogus"])
    assert "unknown station timing profile 'bogus'" in err
    old = without_timing_record(exports["cell"], str(tmp_path / "old"))
    load_export(old)                                 # a valid export otherwise
    err = _one_line_exit_2(capsys, [*run, "--policy", old])
    assert "no timing record" in err
    err = _one_line_exit_2(capsys, ["robot", "sweep", "--policy", old, "--out", str(tmp_path / "sw")])
    assert "no timing record" in err
    err = _one_line_exit_2(capsys, ["robot", "parity", "--policy", old, "--n", "1"])
    assert "no timing record" in err and old in err
    err = _one_line_exit_2(capsys, ["robot", "parity", "--policy", exports["cell"], "--timing", "bogus"])
    assert "--timing 'bogus'" in err and "trained, centre" in err
    assert not os.path.exists(tmp_path / "sw" / "sweep.json")


def test_robot_run_plays_the_trained_timing_by_default_and_says_when_overridden(exports, capsys):
    from ttmjx.cli import main
    run = ["robot", "run", "--station", "sim", "--goals", "0.7,0.3", "--seed", "1", "--json"]
    main([*run, "--policy", exports["cell"]])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["episodes"] == 1 and out["timing"]["source"] == "export" and out["timing"]["within_trained"]
    # by default the station drifts as the policy was trained: each throw draws its delays within
    # the trained ranges; `--timing centre` plays the trained centre, fixed
    assert out["timing"]["station"] == dataclasses.asdict(CELL_TRAINING)
    ranges = trained_timing(read_contract(exports["cell"]))["ranges"]
    (ball, joint, act), = out["throw_delays_s"]
    for v, name in ((ball, "tracker_latency_s"), (joint, "joint_latency_s"), (act, "action_delay_s")):
        assert ranges[name][0] <= v <= ranges[name][1]
    assert (ball, joint, act) != (0.010, 0.004, 0.008)
    main([*run, "--policy", exports["cell"], "--timing", "centre"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["timing"]["station"] == dataclasses.asdict(TIMING_PROFILES["nominal"])
    assert out["throw_delays_s"] == [[0.010, 0.004, 0.008]]
    main([*run[:-1], "--policy", exports["ideal"], "--timing", "nominal", "--allow-untrained-timing"])
    text = capsys.readouterr().out
    assert "TIMING OUTSIDE THE TRAINED RANGE" in text


def test_delays_added_to_an_ideal_timing_leave_it():
    from deploy.robot.timing_check import with_added
    tm = with_added(IDEAL, tracker_latency_s=0.025)
    assert tm.tracker_latency_s == 0.025 and not tm.ideal and not tm.ideal_timing


def test_the_action_delay_can_spread_on_its_own():
    tm = dataclasses.replace(CELL_TRAINING, action_delay_spread_s=0.02)
    ranges = tm.trained_ranges()
    assert ranges["action_delay_s"] == pytest.approx([0.0, 0.028])
    assert ranges["tracker_latency_s"] == pytest.approx([0.0, 0.02])
    assert tm.centre() == TIMING_PROFILES["nominal"] and tm.max_delay_s() == pytest.approx(0.029)
    rec = trained_timing({"timing": timing_record(tm)})
    assert not outside_trained(rec, dataclasses.replace(TIMING_PROFILES["nominal"], action_delay_s=0.025))
    assert outside_trained(rec, dataclasses.replace(TIMING_PROFILES["nominal"], tracker_latency_s=0.025))


def test_a_16_value_export_plays_with_the_trackers_velocity_and_its_extrapolation(tmp_path):
    """The GPU presets observe the ball velocity (16 values): their export plays on the station,
    the runner giving the slope of the tracker's two newest samples (what the training world's
    timing model shows), and following the line as far as the training world did."""
    from deploy.robot.episode_log import load_episode
    from deploy.sim.station import run_sim
    from ttmjx.world import observation
    pcfg = PolicyConfig(hidden=8, layers=1, obs_size=16)
    params = init_params(jax.random.key(0), pcfg, identity_normalizer(16))
    tm = dataclasses.replace(CELL_TRAINING, extrapolate_s=0.05)
    ex = export(params, pcfg, World(ball_velocity_obs=True, timing=tm), str(tmp_path / "ex16"),
                control_hz=20, source="random-init")
    runtime = read_contract(ex)["runtime"]
    assert runtime["obs_size"] == 16 and runtime["extrapolate_s"] == 0.05
    out = run_sim(ex, [[0.7, 0.3]], str(tmp_path / "log"), seed=2)
    assert out["episodes"] == 1
    ep = load_episode(str(tmp_path / "log"), "episode_0000")
    x = ep.extras
    obs = observation.to_width(ep.traj.obs[0], 16, ep.traj.ball_vel[0])   # what the policy saw
    assert ep.traj.obs.shape[-1] == 13
    (lo, hi), (t_lo, t_hi) = x["ball_used_xyz"].transpose(1, 0, 2), x["ball_used_t"].T
    seen = t_hi > t_lo                                    # ticks whose line has two samples
    assert seen.sum() > 10
    slope = (hi - lo) / (t_hi - t_lo)[:, None]
    np.testing.assert_allclose(obs[seen][:, observation.BALL_VEL], slope[seen], rtol=1e-4, atol=1e-3)
    s = (np.clip(x["t_grid"], t_lo, t_hi + 0.05) - t_lo) / np.where(seen, t_hi - t_lo, 1.0)
    np.testing.assert_allclose(observation.ball_pos(obs)[seen], (lo + s[:, None] * (hi - lo))[seen], atol=1e-5)


def test_a_station_without_an_export_takes_a_named_profile_or_refuses_it():
    """`ttmjx robot serve` without --policy: the named profile (nominal by default), an unknown
    name refused with the choices."""
    from deploy.robot.timing_check import profile_timing
    from ttmjx.world.config import TIMING_PROFILES
    assert profile_timing(None) == TIMING_PROFILES["nominal"]
    assert all(profile_timing(n) == t for n, t in TIMING_PROFILES.items())
    with pytest.raises(TimingError, match=r"unknown station timing profile .bogus.; expected one of zero, nominal"):
        profile_timing("bogus")
