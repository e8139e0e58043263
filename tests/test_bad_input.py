"""Bad input, as a careless operator types it: every invocation below must end with exit code 2
(bad input) or 1 (refused work), one line on stderr that starts with `ttmjx`, no traceback,
and nothing written. The commands run in-process (ttmjx.cli.main), so the table is fast."""
import contextlib
import io
import os
import shutil

import numpy as np
import pytest

from ttmjx import cli

DATA = os.path.join(os.path.dirname(__file__), "data")
RUN = os.path.join(DATA, "tiny_run_v0")          # a real (two-member) run directory, read only


def cases():
    """(id, argv) of bad invocations; {tmp} is a scratch directory, {file} a file in it,
    {empty} an empty directory in it."""
    c = [("no-command", []), ("unknown-command", ["fly"]), ("robot-alone", ["robot"]),
         ("robot-unknown", ["robot", "fly"]), ("unknown-flag", ["throw", "--bogus", "1"]),
         ("flag-without-value", ["throw", "--n"]), ("flag-given-value", ["throw", "--spin", "yes"])]
    for cmd, field, values in [
        ("throw", "--n", ["0", "-1", "abc", "1.5", "1000000000"]), ("throw", "--seed", ["abc", "1.5"]),
        ("throw", "--distribution", ["wide", ""]), ("throw", "--control-hz", ["50", "abc"]),
        ("bench", "--batch", ["0", "-5", "abc", "999999999"]), ("bench", "--threads", ["0", "-1", "x"]),
        ("bench", "--backend", ["gpu"]),
        ("render", "--n", ["0", "100"]), ("render", "--source", ["robot"]), ("render", "--out", ["{tmp}", "{file}/x.gif"]),
        ("sim", "--n", ["0", "abc", "1000000000"]), ("sim", "--backend", ["x"]),
        ("demos --out {tmp}/d", "--n", ["0", "abc", "-3"]), ("demos --out {tmp}/d", "--source", ["human"]),
        ("demos --out {tmp}/d", "--backend", ["x"]), ("demos", "--out", ["{file}", "{file}/sub"]),
        ("plot-landings {empty}", "--out", ["{tmp}"]),
        ("train --preset tiny", "--max-iterations", ["0", "-1", "abc"]),
        ("train --preset tiny", "--seed", ["abc"]), ("train", "--preset", ["nope", ""]),
        ("train --preset tiny", "--train.members", ["0", "-2"]), ("train --preset tiny", "--train.window", ["500", "0"]),
        ("train --preset tiny", "--train.learning-rate", ["-1", "0", "nan"]),
        ("train --preset tiny", "--train.capacity", ["0", "1000000000"]),
        ("train --preset tiny", "--train.batch-size", ["0"]), ("train --preset tiny", "--train.grad-clip", ["0"]),
        ("train --preset tiny", "--train.ema-decay", ["1.5", "-0.1"]),
        ("train --preset tiny", "--train.demo-fraction", ["2"]),
        ("train --preset tiny", "--train.action-noise", ["-0.1"]),
        ("train --preset tiny", "--train.practice-goal-margin", ["-0.1", "nan", "5"]),
        ("train --preset tiny", "--train.practice-keep", ["all", ""]),
        ("train --preset tiny", "--episodes-per-ssp", ["33", "0"]),
        ("train --preset tiny", "--world.control-hz", ["-10", "0"]),
        ("train --preset tiny", "--world.episode-s", ["0", "-1"]),
        ("train --preset tiny", "--world.frame-stack", ["0", "3"]),
        ("train --preset tiny", "--world.throws.name", ["wide"]),
        ("train --preset tiny", "--policy.kind", ["gru"]), ("train --preset tiny", "--policy.obs-size", ["14"]),
        ("train --preset tiny", "--policy.hidden", ["0"]), ("train --preset tiny", "--demos", ["-1"]),
        ("train --preset tiny", "--backend", ["tpu"]), ("train --preset tiny", "--eval-goals", ["0"]),
        ("train --preset tiny", "--keep-checkpoints", ["0"]), ("train --preset tiny", "--pretrain-steps", ["-1"]),
        ("train --preset tiny", "--total-trajectories", ["-5"]), ("train --preset tiny", "--checkpoint-every", ["0"]),
        ("train --preset tiny --run-dir {tmp}/r", "--demo-dir", ["{tmp}/missing", "{empty}", "{file}"]),
        ("train --preset tiny --run-dir {tmp}/r", "--data", ["{tmp}/missing", "{empty}"]),
        ("train --preset tiny", "--run-dir", ["{file}"]),
        ("eval", "", ["{tmp}/missing", "{file}", "{empty}"]),
        ("eval " + RUN, "--goals", ["abc", "0", "-3", "{tmp}/goals.csv", "{tmp}/missing.csv", "{tmp}/off_table.csv",
                                    "{tmp}/own_half.csv", "{tmp}/no_header.csv", "{tmp}/wide.npy", "{tmp}/nan.npy",
                                    "{tmp}/goals.txt", "{empty}"]),
        ("eval " + RUN + " --goals {tmp}/good.csv", "--out", ["{file}", "{tmp}", "{file}/sub"]),
        ("eval " + RUN, "--per-goal", ["0"]),
        ("eval " + RUN, "--member", ["-1", "99"]), ("eval " + RUN, "--backend", ["x"]),
        ("eval " + RUN, "--distribution", ["wide"]), ("eval " + RUN, "--seed", ["abc"]),
        ("export " + RUN, "--out", ["{file}"]), ("export --out {tmp}/e", "", ["{tmp}/missing", "{empty}"]),
        ("export " + RUN + " --out {tmp}/e", "--member", ["-1", "9"]),
        ("export " + RUN + " --out {tmp}/e", "--step", ["-1", "99"]),
        ("export " + RUN + " --out {tmp}/e", "--control-hz", ["50"]),
        ("export " + RUN + " --out {tmp}/e", "--onnx", ["maybe"]),
        ("robot run --station sim --goals five", "--policy", ["{tmp}/missing", "{empty}", "{file}"]),
        ("robot run --policy {empty} --goals five", "--station", ["moon"]),
        ("robot run --policy {empty} --station fake", "--goals", ["abc", "0.7", "nan,0", "5,5", "{tmp}/g.npy", ""]),
        ("robot run --policy {empty} --station fake --goals five", "--n", ["0", "-1", "abc"]),
        ("robot run --policy {empty} --station fake --goals five", "--stale-ms", ["0", "-5", "nan"]),
        ("robot run --policy {empty} --station fake --goals five", "--out", ["{file}", "{tmp}"]),
        ("robot run --policy {empty} --station sim --goals five", "--distribution", ["wide"]),
        ("ablate", "", ["nope", ""]), ("ablate demos", "--seeds", ["0", "-1", "abc"]),
        ("ablate demos", "--scale", ["huge", "gpu"]), ("ablate demos --scale tiny", "--trajectories", ["0", "-5"]),
        ("ablate demos --scale tiny", "--cells", ["nope", "0:99", "3:1", "", ":", "d10,x"]),
        ("ablate noise --scale tiny --plan", "--cells", ["d10", "20"]),
        ("ablate demos --scale tiny", "--out", ["{file}"]),
        ("ablate demos --scale tiny --out {empty}", "--report", ["--report"]),     # nothing finished yet
        ("baseline", "", ["nope", "ppo,qtopt", ""]), ("baseline ppo --scale tiny", "--seeds", ["0", "abc"]),
        ("baseline ppo", "--scale", ["huge"]), ("baseline ppo --scale tiny", "--trajectories", ["0", "-5"]),
        ("baseline es --scale tiny", "--trajectories", ["1"]), ("baseline ppo --scale full", "--trajectories", ["100"]),
        ("baseline ppo --scale tiny", "--reward.goal", ["nan", "-1"]), ("baseline ppo --scale tiny", "--reward.hit", ["-0.5"]),
        ("baseline ppo --scale tiny", "--reward.goal-scale", ["0", "nan"]), ("baseline ppo --scale tiny", "--out", ["{file}"]),
        ("robot bench", "--hidden", ["0"]), ("robot bench", "--layers", ["0"]), ("robot bench", "--members", ["0"]),
        ("robot bench", "--steps", ["0"]), ("robot bench", "--threads", ["0"]), ("robot bench", "--kind", ["gru"]),
        ("robot bench", "--engine", ["torch"]), ("robot bench", "--obs-size", ["14"]), ("robot bench", "--frame-stack", ["0"]),
    ]:
        for v in values:
            argv = cmd.split() + ([field] if field else []) + ([v] if v != field else [])
            c.append((f"{cmd.split()[0]}{(' ' + field) if field else ''}={v}".replace(" ", "_"), argv))
    return c


CASES = cases()


def test_the_table_is_large():
    assert len(CASES) >= 100, len(CASES)


@pytest.fixture()
def scratch(tmp_path, monkeypatch):
    (tmp_path / "empty").mkdir()
    (tmp_path / "a_file").write_text("not a dataset\n")
    (tmp_path / "goals.csv").write_text("x,y\n0.7,nan\n")
    (tmp_path / "good.csv").write_text("x,y\n0.7,0.0\n")
    (tmp_path / "off_table.csv").write_text("x,y\n0.7,0.0\n0.7,0.9\n")       # beyond a side line
    (tmp_path / "own_half.csv").write_text("x,y\n-0.5,0.0\n")
    (tmp_path / "no_header.csv").write_text("0.7,0.0\n")
    (tmp_path / "goals.txt").write_text("x,y\n0.7,0.0\n")                   # neither .csv nor .npy
    np.save(tmp_path / "wide.npy", np.zeros((4, 3)))
    np.save(tmp_path / "nan.npy", np.array([[0.7, 0.0], [np.nan, 0.1]]))
    monkeypatch.chdir(tmp_path)
    return tmp_path


def listing(root) -> set:
    return {os.path.relpath(os.path.join(d, f), root) for d, ds, fs in os.walk(root) for f in fs + ds}


@pytest.mark.parametrize("name,argv", CASES, ids=[n for n, _ in CASES])
def test_bad_input_is_one_line_and_changes_nothing(name, argv, scratch):
    subst = {"{tmp}": str(scratch), "{file}": str(scratch / "a_file"), "{empty}": str(scratch / "empty")}
    argv = [a.replace("{tmp}", subst["{tmp}"]).replace("{file}", subst["{file}"]).replace("{empty}", subst["{empty}"])
            for a in argv]
    before = listing(scratch)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as ex:
        cli.main(argv)
    msg = err.getvalue()
    assert ex.value.code in (1, 2), (argv, ex.value.code, msg[-500:])
    assert "Traceback" not in msg, msg
    assert msg.startswith("ttmjx") and msg.count("\n") == 1, repr(msg)
    assert listing(scratch) == before, sorted(listing(scratch) - before)


# -- issue 26: the message names the culprit -------------------------------------------------
TRAIN = "train --preset tiny --run-dir {tmp}/r --max-iterations 1"
NAMED = [   # (argv, exit code, substrings the one line must hold)
    # physics and geometry that failed inside MuJoCo's XML compiler or with a ZeroDivisionError
    (TRAIN + " --world.table.length -2", 2, ["--world.table.length", "-2", "> 0"]),
    (TRAIN + " --world.ball.mass 0", 2, ["--world.ball.mass", "0", "> 0"]),
    (TRAIN + " --world.physics-dt 0", 2, ["--world.physics-dt", "0", "> 0"]),
    (TRAIN + " --world.ball.radius nan", 2, ["--world.ball.radius", "nan", "finite"]),
    (TRAIN + " --world.robot.lower 1 1 1 1 1 1 1 1", 2, ["--world.robot.lower", "gantry_x", "lower < upper"]),
    (TRAIN + " --world.robot.home 0 0 0 0 0 0 0 9", 2, ["--world.robot.home", "j6", "outside"]),
    # reversed ranges, wrong lengths, tolerances and flight times under which no throw is valid
    (TRAIN + " --world.throws.narrow-speed 9 6", 2, ["--world.throws.narrow-speed", "9 6", "LO <= HI"]),
    (TRAIN + " --world.throws.narrow-launch 1.75 0.35", 2, ["--world.throws.narrow-launch", "3 values", "got 2"]),
    (TRAIN + " --world.throws.solve-tol 0", 2, ["--world.throws.solve-tol", "> 0"]),
    (TRAIN + " --world.throws.max-flight-s 0.1", 2, ["--world.throws.max-flight-s", "0.1", "no throw"]),
    # relations between fields: no practice, demonstrations dropped
    (TRAIN + " --total-trajectories 100", 2, ["--total-trajectories 100", "--demos 200", "no practice"]),
    (TRAIN + " --train.capacity 1", 2, ["--train.capacity 1", "--demos 200", "199"]),
    # seeds that would wrap onto others
    (TRAIN + " --seed -1", 2, ["--seed -1", "4294967295"]),
    (TRAIN + " --seed 4294967296", 2, ["--seed 4294967296", "4294967295"]),
    ("throw --seed 4294967296", 2, ["--seed", "4294967295"]),
    # an option parsed and ignored: the tiny preset's timing is ideal
    (TRAIN + " --world.timing.tracker-latency-s 0.01", 2, ["--world.timing.tracker-latency-s", "ignored"]),
    (TRAIN + " --world.timing.jitter-s -1", 2, ["--world.timing.jitter-s", "-1"]),
    # config classes' own messages name the flag, not the class
    (TRAIN + " --train.window 0", 2, ["--train.window 0", ">= 1"]),
    # goal files of the robot runner name the file
    ("robot run --policy {empty} --station fake --goals {tmp}/missing.npy", 2, ["missing.npy", "does not exist"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/missing.csv", 2, ["missing.csv", "does not exist"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/junk.json", 2, ["junk.json", "not valid JSON"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/wide.npy", 2, ["wide.npy", "[N, 2]"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/garbage.npy", 2, ["garbage.npy", ".npy"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/goals.csv", 2, ["goals.csv", "not finite"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/own_half.csv", 2, ["own_half.csv", "opponent's half"]),
    ("eval " + RUN + " --goals {tmp}/wide.npy", 2, ["wide.npy", "[N, 2]"]),
    ("eval " + RUN + " --goals {tmp}/missing.npy", 2, ["missing.npy", "does not exist"]),
    ("eval " + RUN + " --goals {tmp}/goals.csv", 2, ["goals.csv", "not finite"]),
    # data of another control rate or observation layout, refused when it enters
    (TRAIN + " --demo-dir {tmp}/demos50", 2, ["--demo-dir", "50 Hz", "100 Hz"]),
    (TRAIN + " --demo-dir {tmp}/demos_vel", 2, ["--demo-dir", "ball_velocity_obs=True", "False"]),
    (TRAIN + " --data {tmp}/logs50", 2, ["--data", "50 Hz", "100 Hz", "ep0"]),
    (TRAIN + " --data {tmp}/logs16", 2, ["--data", "16-value", "13"]),
    (TRAIN + " --data {tmp}/logs_order", 2, ["--data", "joint order"]),
]


def write_dataset(d, world_fields: dict, horizon: int = 160):
    import json
    from ttmjx.world import record
    os.makedirs(d)
    np.savez(os.path.join(d, "trajectories.npz"), x=np.zeros(1))
    with open(os.path.join(d, "trajectories.meta.json"), "w") as f:
        json.dump({"schema_version": record.SCHEMA_VERSION, "n": 200, "horizon": horizon, "world": world_fields}, f)


def write_log(d, **contract):
    import json
    from ttmjx.world.config import JOINT_NAMES
    os.makedirs(d)
    c = {"control_hz": 100.0, "obs_size": 13, "joint_names": list(JOINT_NAMES), **contract}
    with open(os.path.join(d, "ep0.meta.json"), "w") as f:
        json.dump({"schema_version": 1, "n": 1, "contract": c}, f)


@pytest.fixture()
def named_scratch(scratch):
    (scratch / "junk.json").write_text("nonsense\n")
    (scratch / "garbage.npy").write_bytes(b"garbage")
    write_dataset(str(scratch / "demos50"), {"control_hz": 50}, horizon=80)
    write_dataset(str(scratch / "demos_vel"), {"control_hz": 100, "ball_velocity_obs": True})
    write_log(str(scratch / "logs50"), control_hz=50.0)
    write_log(str(scratch / "logs16"), obs_size=16)
    write_log(str(scratch / "logs_order"), joint_names=["j1", "gantry_x", "gantry_y", "j2", "j3", "j4", "j5", "j6"])
    return scratch


@pytest.mark.parametrize("argv,code,words", NAMED, ids=[a.replace(TRAIN, "train") for a, _, _ in NAMED])
def test_the_message_names_the_culprit(argv, code, words, named_scratch):
    argv = argv.replace("{tmp}", str(named_scratch)).replace("{empty}", str(named_scratch / "empty")).split()
    before = listing(named_scratch)
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err), \
            pytest.raises(SystemExit) as ex:
        cli.main(argv)
    msg = err.getvalue()
    assert ex.value.code == code, (argv, ex.value.code, msg)
    assert msg.startswith("ttmjx") and msg.count("\n") == 1 and "Traceback" not in msg, repr(msg)
    for w in words:
        assert w in msg, (w, msg)
    assert listing(named_scratch) == before            # nothing written: no run directory either


def test_logs_of_another_rate_are_refused_where_they_are_loaded(tmp_path):
    """The trainer's own loader checks the contract too (a resumed run's --data)."""
    from training.pool import load_logs
    from ttmjx.world.config import World
    write_log(str(tmp_path / "logs50"), control_hz=50.0)
    with pytest.raises(ValueError, match=r"50 Hz .* 100 Hz"):
        load_logs([str(tmp_path / "logs50")], 160, World())


def test_a_staged_directory_is_whole_or_absent(tmp_path):
    """export and eval --out write through files.staged_dir: a failure part-way (a full disk, a
    kill) leaves the final name as it was, and the same command can run again."""
    from ttmjx.world import files
    out = tmp_path / "export"
    with pytest.raises(OSError, match="No space"):
        with files.staged_dir(str(out)) as stage:
            files.write_bytes(os.path.join(stage, "weights.safetensors"), b"w" * 100)
            raise OSError(28, "No space left on device")
    assert not out.exists() and os.listdir(tmp_path) == []
    with files.staged_dir(str(out), last=("manifest.json",)) as stage:
        for name in ("manifest.json", "weights.safetensors"):
            files.write_bytes(os.path.join(stage, name), name.encode())
    assert sorted(os.listdir(out)) == ["manifest.json", "weights.safetensors"] and os.listdir(tmp_path) == ["export"]
    (tmp_path / "empty").mkdir()        # an empty --out is replaced whole
    with files.staged_dir(str(tmp_path / "empty")) as stage:
        files.write_bytes(os.path.join(stage, "summary.json"), b"{}")
    assert os.listdir(tmp_path / "empty") == ["summary.json"]


def test_eval_out_is_whole_or_absent_on_a_full_disk(tmp_path, monkeypatch):
    """A full disk while eval writes its records leaves no episodes.csv behind: the same command
    runs again into the same --out."""
    from eval import report
    from ttmjx.world import files
    real = files.write_bytes

    def full_after_first(path, data):
        if path.endswith("tracks.npz"):
            raise OSError(28, "No space left on device", path)
        real(path, data)
    monkeypatch.setattr(files, "write_bytes", full_after_first)
    from ttmjx.world.config import World
    from ttmjx.world.record import Trajectories
    b, t = 2, 4
    shapes = {"obs": (b, t, 13), "ball_vel": (b, t, 3), "actions": (b, t, 8), "valid": (b, t), "goal": (b, 2),
              "hit": (b,), "hit_step": (b,), "landing": (b, 2), "on_opponent": (b,), "bounce_own": (b,), "net": (b,),
              "launch_pos": (b, 3), "launch_vel": (b, 3), "launch_spin": (b, 3), "aim": (b, 2)}
    traj = Trajectories(**{k: np.zeros(v, bool if k in ("valid", "hit", "on_opponent", "bounce_own", "net")
                                       else np.int32 if k == "hit_step" else np.float32) for k, v in shapes.items()})
    out = tmp_path / "ev"
    with pytest.raises(OSError, match="No space"):
        report.write_eval_dir(str(out), {"a": 1}, traj, World())
    assert not out.exists() and os.listdir(tmp_path) == []
    monkeypatch.setattr(files, "write_bytes", real)
    report.write_eval_dir(str(out), {"a": 1}, traj, World())     # the same command again
    assert sorted(os.listdir(out)) == ["episodes.csv", "summary.json", "tracks.npz"]


def test_a_torn_metrics_line_is_dropped_and_said_and_a_damaged_one_named(tmp_path):
    from training.runlog import MetricsLog
    log = MetricsLog(str(tmp_path))
    (tmp_path / "metrics.jsonl").write_text('{"iteration": 0}\n{"iteration": 1}\n{"itera')
    assert log.rows() == [{"iteration": 0}, {"iteration": 1}] and log.torn == '{"itera'
    (tmp_path / "metrics.jsonl").write_text('{"iteration": 0}\nnot json\n{"iteration": 2}\n')
    with pytest.raises(ValueError, match=r"metrics.jsonl: line 2 is not a JSON row"):
        log.rows()
