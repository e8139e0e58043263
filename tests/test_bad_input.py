"""Bad input, as a careless operator types it: every invocation below must end with exit code 2
(bad input) or 1 (refused work), one line on stderr that starts with `ttmjx`, no traceback,
and nothing written. The commands run in-process (ttmjx.cli.main), so the table is fast."""
import contextlib
import dataclasses
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
    {empty} an empty directory in it, {qtopt} a QT-Opt baseline run's directory (its state only)."""
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
        ("train --preset tiny", "--train.balance", ["-1", "3"]), ("report", "", ["{tmp}/missing", "{file}", "{empty}"]),
        ("train --preset tiny", "--train.action-noise", ["-0.1"]),
        ("train --preset tiny", "--train.practice-goal-margin", ["-0.1", "nan", "5"]),
        ("train --preset tiny", "--train.practice-keep", ["all", ""]),
        ("train --preset tiny", "--train.lstm-kernel", ["cudnn2"]),
        ("train --preset tiny --train.update-dtype bfloat16", "--train.lstm-kernel", ["cudnn"]),   # float32 only
        ("train --preset tiny --policy.kind lstm", "--train.lstm-kernel", ["cudnn"]),     # a CPU has no cuDNN
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
        ("ablate noise --scale tiny --plan", "--cells", ["d10", "99"]),
        ("ablate demos --scale tiny", "--out", ["{file}"]),
        ("ablate demos --scale tiny --out {empty}", "--report", ["--report"]),     # nothing finished yet
        ("baseline", "", ["nope", "ppo,dqn", ""]), ("baseline ppo --scale tiny", "--seeds", ["0", "abc"]),
        ("baseline ppo", "--scale", ["huge"]), ("baseline ppo --scale tiny", "--trajectories", ["0", "-5"]),
        ("baseline es --scale tiny", "--trajectories", ["1"]), ("baseline ppo --scale full", "--trajectories", ["100"]),
        ("baseline ppo --scale tiny", "--reward.goal", ["nan", "-1"]), ("baseline ppo --scale tiny", "--reward.hit", ["-0.5"]),
        ("baseline ppo --scale tiny", "--reward.goal-scale", ["0", "nan"]), ("baseline ppo --scale tiny", "--out", ["{file}"]),
        ("baseline qtopt --scale full", "--trajectories", ["120001", "299"]),
        ("baseline qtopt", "--qtopt.cem-iterations", ["0", "abc"]), ("baseline qtopt", "--qtopt.cem-elites", ["1", "65"]),
        ("baseline qtopt", "--qtopt.cem-population", ["0"]), ("baseline qtopt", "--qtopt.discounting", ["1", "nan"]),
        ("baseline qtopt", "--qtopt.epsilon", ["1.5"]), ("baseline qtopt", "--qtopt.target-tau", ["0"]),
        ("eval", "", ["{qtopt}"]), ("export --out {tmp}/e", "", ["{qtopt}"]),
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
    (tmp_path / "qtopt_run" / "qtopt_state").mkdir(parents=True)
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
    subst = {"{tmp}": str(scratch), "{file}": str(scratch / "a_file"), "{empty}": str(scratch / "empty"),
             "{qtopt}": str(scratch / "qtopt_run")}
    argv = [a.replace("{tmp}", subst["{tmp}"]).replace("{file}", subst["{file}"]).replace("{empty}", subst["{empty}"])
            .replace("{qtopt}", subst["{qtopt}"]) for a in argv]
    before = listing(scratch)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), pytest.raises(SystemExit) as ex:
        cli.main(argv)
    msg = err.getvalue()
    assert ex.value.code in (1, 2), (argv, ex.value.code, msg[-500:])
    assert "Traceback" not in msg, msg
    assert msg.startswith("ttmjx") and msg.count("\n") == 1, repr(msg)
    assert listing(scratch) == before, sorted(listing(scratch) - before)


# -- the message names the culprit ---------------------------------------------------------
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
    ("robot run --policy {empty} --station fake --goals {tmp}/junk.json", 2, ["junk.json", ".csv (header x,y) or .npy"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/wide.npy", 2, ["wide.npy", "[N, 2]"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/garbage.npy", 2, ["garbage.npy", ".npy"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/goals.csv", 2, ["goals.csv", "not finite"]),
    ("robot run --policy {empty} --station fake --goals {tmp}/own_half.csv", 2, ["own_half.csv", "opponent's half"]),
    # options of another station, parsed and ignored before
    ("robot run --policy {empty} --station fake --goals five --config {tmp}/cell.toml", 2,
     ["--config", "cell station", "'fake'"]),
    ("robot run --policy {empty} --station fake --goals five --timing centre", 2, ["--timing", "'fake'"]),
    ("eval " + RUN + " --goals {tmp}/wide.npy", 2, ["wide.npy", "[N, 2]"]),
    ("eval " + RUN + " --goals {tmp}/missing.npy", 2, ["missing.npy", "does not exist"]),
    ("eval " + RUN + " --goals {tmp}/goals.csv", 2, ["goals.csv", "not finite"]),
    # data of another control rate or observation layout, refused when it enters
    (TRAIN + " --demo-dir {tmp}/demos50", 2, ["--demo-dir", "50 Hz", "100 Hz"]),
    (TRAIN + " --demo-dir {tmp}/demos_vel", 2, ["--demo-dir", "ball_velocity_obs=True", "False"]),
    (TRAIN + " --data {tmp}/logs50", 2, ["--data", "50 Hz", "100 Hz", "ep0"]),
    (TRAIN + " --data {tmp}/logs16", 2, ["--data", "16-value", "13"]),
    (TRAIN + " --data {tmp}/logs_order", 2, ["--data", "joint order"]),
    # an --out or --run-dir onto or under a file: the flag and the path ("File exists", "Not a directory" before)
    ("train --preset tiny --max-iterations 1 --run-dir {tmp}/a_file/r", 2,
     ["ttmjx train: error:", "--run-dir", "a_file/r", "not a writable directory"]),
    ("train --preset tiny --max-iterations 1 --run-dir {tmp}/a_file", 2, ["--run-dir", "a_file", "is a file"]),
    ("eval " + RUN + " --goals {tmp}/good.csv --out {tmp}/a_file", 2, ["--out", "a_file", "is a file"]),
    ("demos --n 1 --out {tmp}/a_file/sub", 2, ["--out", "a_file/sub", "not a writable directory"]),
    ("export " + RUN + " --out {tmp}/a_file/sub", 2, ["--out", "a_file/sub", "not a writable directory"]),
    ("robot run --station fake --goals five --out {tmp}/a_file/sub", 2,
     ["ttmjx robot run: error:", "--out", "a_file/sub", "not a writable directory"]),
    ("robot run --station fake --goals five --out {tmp}/a_file", 2, ["--out", "a_file", "is a file"]),
    ("ablate demos --scale tiny --out {tmp}/a_file/sub", 2, ["ttmjx ablate: error:", "--out", "a_file/sub"]),
    ("baseline ppo --scale tiny --out {tmp}/a_file", 2, ["ttmjx baseline: error:", "--out", "a_file", "is a file"]),
    ("report {empty} --out {tmp}/a_file/sub", 2, ["ttmjx report: error:", "--out", "a_file/sub"]),
    # the paper procedure's sizes named as flags ("final=1 episodes" before)
    ("demos --source paper --rebuild all --n 1 --out {tmp}/d", 2, ["ttmjx demos: error:", "--n 1", "at least 100"]),
    ("demos --source paper --rebuild all --es-generations 1 1 --out {tmp}/d", 2,
     ["--es-generations 1 1", "too few to converge"]),
    # throws too slow for the flight limit: both fields named (the limit alone before)
    (TRAIN + " --world.throws.narrow-speed 0.5 1", 2, ["--world.throws.max-flight-s", "--world.throws.narrow-speed",
                                                        "up to 1 m/s", "no throw"]),
    # meaningless work: a budget that ends before any environment has played one whole episode
    ("baseline ppo --scale tiny --trajectories 1 --out {tmp}/b", 2,
     ["ttmjx baseline: error:", "trajectory budget 1", "2 environments", "whole 160-step episode", "smallest budget is 2"]),
    ("baseline goalseye --scale tiny --trajectories 1 --out {tmp}/b", 2,
     ["baseline goalseye", "trajectory budget 1", "200 demonstrations", "practice round", "smallest budget is 232"]),
    ("baseline gcsl --scale tiny --trajectories 1 --out {tmp}/b", 2, ["baseline gcsl", "smallest budget is 32"]),
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


# One of each kind above, as a user meets it: a fresh process, its exit code and its last line.
AS_SUBPROCESS = [0, 6, 7, 10, 12, 15, 18, 21, 25, 26, 31, 33, 35]


@pytest.mark.parametrize("index", AS_SUBPROCESS, ids=[NAMED[i][0].replace(TRAIN, "train") for i in AS_SUBPROCESS])
def test_the_message_names_the_culprit_in_a_fresh_process(index, named_scratch):
    argv, code, words = NAMED[index]
    argv = argv.replace("{tmp}", str(named_scratch)).replace("{empty}", str(named_scratch / "empty")).split()
    before = listing(named_scratch)
    one_line_error(run(*argv), code, "ttmjx", *words)
    assert listing(named_scratch) == before


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


# -- the same, as a user meets them: subprocesses, signals, resumes, a full disk -------------------
import json  # noqa: E402
import resource  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from conftest import private_compilation_cache  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENV = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}


def command(*args) -> list[str]:
    """`ttmjx ARGS` as argv (the console script's entry, ttmjx/entry.py)."""
    return [sys.executable, "-m", "ttmjx", *map(str, args)]


def run(*args, timeout=300, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(command(*args), capture_output=True, text=True, timeout=timeout, env=ENV, cwd=ROOT, **kw)


def run_here(*args) -> None:
    """`ttmjx ARGS` through the console script's entry in this process, for a reference result
    the test compares with (not for what only a fresh process shows: signals, exit codes, a
    file-size limit): a fresh process pays ~5 s of imports and traces its programs again
    (~10-25 s on 2 cores). A failure raises SystemExit with the command's exit code."""
    from ttmjx.entry import main
    main([str(a) for a in args])


def last_line(err: str) -> str:
    """The command's own last stderr line (JAX, absl and progress bars may write before it)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def one_line_error(done, code: int, prefix: str, *words):
    """Exit `code`, a last stderr line that starts with `prefix` and holds every word, no traceback."""
    msg = last_line(done.stderr)
    assert done.returncode == code, (done.returncode, done.stderr[-2000:])
    assert msg.startswith(prefix) and "Traceback" not in done.stderr, done.stderr[-2000:]
    for w in words:
        assert w in msg, (w, msg)
    return msg


def one_line_error_here(args, code: int, prefix: str, *words):
    """one_line_error for `ttmjx ARGS` run in this process (run_here), as the tables above run
    their refusals; AS_SUBPROCESS and the robot side's bounds below are met in fresh processes."""
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err), \
            pytest.raises(SystemExit) as ex:
        run_here(*args)
    return one_line_error(subprocess.CompletedProcess(args, ex.value.code, "", err.getvalue()), code, prefix, *words)


def stop_when(proc: subprocess.Popen, ready, sig=signal.SIGTERM, timeout=240) -> subprocess.CompletedProcess:
    """Send `sig` to `proc` once ready() holds; its exit code and output."""
    t0 = time.monotonic()
    while not ready():
        assert proc.poll() is None, f"ended before the signal: {proc.returncode}: {proc.communicate()[1][-2000:]}"
        assert time.monotonic() - t0 < timeout, "never ready"
        time.sleep(0.01)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.fixture(scope="module")
def tiny_export(tmp_path_factory):
    """tests/data/tiny_run_v0 exported (no ONNX graph), read only."""
    out = str(tmp_path_factory.mktemp("export") / "ex")
    run_here("export", RUN, "--out", out, "--onnx", "off")
    return out


@pytest.mark.slow
def test_sigterm_during_ablate_saves_the_cell_and_the_same_command_resumes(tmp_path):
    """SIGTERM while a cell trains: its run saves a checkpoint, the command exits 143 naming it (no
    table yet is not an error), and the same command resumes the cell and finishes the table."""
    out = tmp_path / "ab"
    argv = ["ablate", "practice", "--scale", "tiny", "--seeds", "1", "--cells", "goalseye",
            "--trajectories", "232", "--out", str(out), "--json"]
    metrics = out / "runs" / "goalseye-seed0" / "metrics.jsonl"
    proc = subprocess.Popen(command(*argv), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, cwd=ROOT)
    done = stop_when(proc, lambda: metrics.exists() and metrics.stat().st_size > 0)
    msg = one_line_error(done, 143, "ttmjx ablate: error: stopped by SIGTERM", "checkpoint saved in",
                         str(out / "runs" / "goalseye-seed0"), "same command")
    assert "no finished cells" not in done.stderr, msg
    assert os.listdir(out / "runs" / "goalseye-seed0" / "checkpoints") and not (out / "results").exists()
    again = run(*argv)
    assert again.returncode == 0, again.stderr[-2000:]
    summary = json.loads(again.stdout.strip().splitlines()[-1])
    assert summary["stopped_by_signal"] == 0 and (out / "results" / "goalseye-seed0.json").exists()
    assert "resuming" in again.stdout + again.stderr


def session_without_wall_time(path) -> dict:
    s = json.loads(open(path).read())
    return {k: v for k, v in s.items() if k not in ("wall_s", "realtime_factor", "out")}


@pytest.mark.slow
def test_robot_run_out_interrupted_resumes_to_the_uninterrupted_session(tiny_export, tmp_path, capsys):
    """`ttmjx robot run --out DIR` stopped by SIGTERM keeps its episodes (exit 143); the same
    command resumes DIR (the logged episodes replayed and checked, not rewritten) and ends with
    the session an uninterrupted run writes; once finished, it reports it again."""
    argv = ["robot", "run", "--policy", tiny_export, "--station", "sim", "--goals", "five", "--seed", "2"]
    run_here(*argv, "--out", tmp_path / "whole", "--json")      # the uninterrupted session, for reference
    out = tmp_path / "cut"
    proc = subprocess.Popen(command(*argv, "--out", out, "--json"), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, cwd=ROOT)
    done = stop_when(proc, lambda: (out / "episode_0001.deploy.npz").exists())
    one_line_error(done, 143, "ttmjx robot run: error: stopped by SIGTERM", "run the same command")
    logged = sorted(f for f in os.listdir(out) if f.endswith(".deploy.npz"))
    assert 2 <= len(logged) < 5 and not (out / "session.json").exists(), logged
    first = (out / "episode_0000.npz").stat().st_mtime_ns
    again = run(*argv, "--out", out, "--json")
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"resuming {out}: {len(logged)} of 5 episodes logged" in again.stderr, again.stderr[-2000:]
    assert (out / "episode_0000.npz").stat().st_mtime_ns == first           # kept, not rewritten
    assert session_without_wall_time(out / "session.json") == session_without_wall_time(tmp_path / "whole" / "session.json")
    capsys.readouterr()
    run_here(*argv, "--out", out, "--json")                      # once finished: reported again
    finished = capsys.readouterr().err
    assert "finished earlier" in finished, finished[-2000:]
    other = run(*argv[:-1], "3", "--out", out)            # another seed: another session
    one_line_error(other, 2, "ttmjx robot run: error:", str(out), "another session", "seed")


@pytest.mark.slow
def test_an_interrupted_robot_sweep_goes_on_where_it_stopped(tiny_export, tmp_path):
    """sweep.json is written after every point; SIGTERM after the first, then the same command:
    only the missing points are played and the sweep is the uninterrupted one."""
    argv = ["robot", "sweep", "--policy", tiny_export, "--n", "2", "--points", "2", "--series", "ball,action",
            "--max-ms", "50"]
    run_here(*argv, "--out", tmp_path / "whole")                 # the uninterrupted sweep, for reference
    out = tmp_path / "cut"
    proc = subprocess.Popen(command(*argv, "--out", out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=ENV, cwd=ROOT)
    done = stop_when(proc, lambda: (out / "sweep.json").exists())
    one_line_error(done, 143, "ttmjx robot sweep: error: stopped by SIGTERM", "run the same command")
    assert len(json.loads((out / "sweep.json").read_text())["points"]) < 4
    again = run(*argv, "--out", out)
    assert again.returncode == 0, again.stderr[-2000:]
    assert json.loads((out / "sweep.json").read_text()) == json.loads((tmp_path / "whole" / "sweep.json").read_text())
    one_line_error(run(*argv[:5], "3", *argv[6:], "--out", out), 2, "ttmjx robot sweep: error:", "sweep.json",
                   "another sweep", "goals")


@pytest.mark.slow
def test_ctrl_c_during_robot_run_keeps_the_episodes_and_exits_130(tiny_export, tmp_path):
    out = tmp_path / "logs"
    # 200 episodes: the signal lands mid-session however fast the machine plays them
    # Ctrl-C as a terminal sends it: a shell without job control starts `cmd &` (so maybe this
    # test process) with SIGINT ignored, and the child would inherit that.
    proc = subprocess.Popen(command("robot", "run", "--policy", tiny_export, "--station", "sim", "--goals", "five",
                                    "--n", "200", "--out", out), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, cwd=ROOT, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    done = stop_when(proc, lambda: (out / "episode_0000.deploy.npz").exists(), sig=signal.SIGINT)
    one_line_error(done, 130, "ttmjx robot run: error: stopped by SIGINT", "run the same command")
    assert (out / "episode_0000.meta.json").exists() and (out / "session.plan.json").exists()


def test_the_robot_side_names_its_bounds_at_the_door():
    done = run("robot", "run", "--station", "fake", "--goals", "five", "--n", "0")
    one_line_error(done, 2, "ttmjx robot run: error:", "--n 0", "between 1 and 100000")
    one_line_error(run("robot", "run", "--station", "fake", "--goals", "five", "--stale-ms", "nan"), 2,
                   "ttmjx robot run: error:", "--stale-ms", "NaN")
    one_line_error(run("robot", "run", "--station", "cell", "--goals", "five"), 2, "ttmjx robot run: error:",
                   "--station cell needs --policy")
    one_line_error(run("robot", "bench", "--frame-stack", "100000"), 2, "ttmjx robot bench: error:",
                   "--frame-stack 100000", "between 1 and 64")


def test_outputs_that_hold_something_else_are_refused_naming_it(recorded_tiny_run, tiny_export, tmp_path):
    """ablate --out, robot run --out (on the simulated or the fake station) and robot sweep --out
    pointing at a training run (or an export): refused with the directory and what it holds,
    nothing written there. In this process (one_line_error_here): refusals before any work."""
    run_dir = str(recorded_tiny_run[0])
    before = listing(run_dir)
    one_line_error_here(["ablate", "practice", "--scale", "tiny", "--seeds", "1", "--out", run_dir, "--plan"], 2,
                        "ttmjx ablate: error:", run_dir, "a training run", "checkpoints/")
    one_line_error_here(["robot", "run", "--policy", tiny_export, "--station", "sim", "--goals", "five", "--out",
                         run_dir], 2, "ttmjx robot run: error:", run_dir, "a training run", "config.json")
    one_line_error_here(["robot", "run", "--station", "fake", "--goals", "five", "--out", run_dir], 2,
                        "ttmjx robot run: error:", run_dir, "a training run")
    one_line_error_here(["robot", "run", "--station", "fake", "--goals", "five", "--out", tiny_export], 2,
                        "ttmjx robot run: error:", tiny_export, "an export")
    one_line_error_here(["robot", "sweep", "--policy", tiny_export, "--out", run_dir], 2, "ttmjx robot sweep: error:",
                        run_dir, "config.json")
    assert listing(run_dir) == before


def edited_export(src, dst, section: str, **fields) -> str:
    """A copy of the export `src` at `dst` with contract.json's `section` fields replaced and the
    manifest's hashes made to match (a hand-edited contract, not a damaged file)."""
    from deploy.robot.exported import sha256_bytes
    shutil.copytree(src, dst)
    doc = json.loads((dst / "contract.json").read_text())
    doc[section].update(fields)
    (dst / "contract.json").write_text(json.dumps(doc))
    man = json.loads((dst / "manifest.json").read_text())
    man["files"]["contract.json"]["sha256"] = sha256_bytes((dst / "contract.json").read_bytes())
    (dst / "manifest.json").write_text(json.dumps(man))
    return str(dst)


def test_an_export_claiming_an_absurd_rate_or_contradicting_itself_is_refused_naming_the_field(tiny_export,
                                                                                            tmp_path):
    """A contract of 1e9 Hz was accepted (the fake station then ran until killed); a policy
    section whose frame width differs from the runtime section's was said as "the robot gives"
    what the contract claims, naming neither the export nor the fields. Refused at load, before
    any episode, in this process (one_line_error_here)."""
    fast = edited_export(tiny_export, tmp_path / "fast", "runtime", control_hz=1e9)
    one_line_error_here(["robot", "run", "--policy", fast, "--station", "fake", "--goals", "five"], 2,
                        "ttmjx robot run: error:", os.path.join(fast, "contract.json"), "control_hz=1000000000.0",
                        "1 to 1000 Hz")
    wide = edited_export(tiny_export, tmp_path / "wide", "policy", obs_size=16)
    one_line_error_here(["robot", "run", "--policy", wide, "--station", "fake", "--goals", "five"], 2,
                        "ttmjx robot run: error:", os.path.join(wide, "contract.json"),
                        "policy.obs_size 16 differs from runtime.obs_size 13")


def test_a_stale_bound_below_the_sensors_sample_age_is_refused_before_any_episode(tiny_export, tmp_path):
    """--stale-ms 5 on the fake station (joints 250 Hz 2 ms late, ball 125 Hz 4 ms late: a ball
    sample up to 12 ms old) held before any episode and ended with exit 1 and a summary of 0
    episodes; the simulated station states its sensors' ages too. Exit 2 naming the flag and the
    bound, nothing written; at the bound the session plays."""
    out = tmp_path / "logs"
    one_line_error_here(["robot", "run", "--station", "fake", "--goals", "five", "--stale-ms", "5", "--out", out], 2,
                        "ttmjx robot run: error:", "--stale-ms 5", "ball samples are up to 12 ms old",
                        "at least 12 ms")
    one_line_error_here(["robot", "run", "--policy", tiny_export, "--station", "sim", "--goals", "five",
                         "--stale-ms", "0.1", "--out", out], 2, "ttmjx robot run: error:", "--stale-ms 0.1",
                        "samples are up to")
    assert not out.exists()
    run_here("robot", "run", "--station", "fake", "--goals", "0.7,0.3", "--stale-ms", "12", "--out", out)
    assert json.loads((out / "session.json").read_text())["episodes"] == 1


def free_ports(kind, n: int) -> list[int]:
    """n ports of `kind` (socket.SOCK_DGRAM or SOCK_STREAM) nothing listens on now."""
    import socket
    socks = [socket.socket(socket.AF_INET, kind) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def test_a_stale_bound_below_the_cells_sample_age_is_refused_before_the_drivers_open(tiny_export, tmp_path):
    """--stale-ms on the cell station was not checked at all: a bound below the age its samples
    reach by design (the ball's: one tracker period plus the trained latency and jitter; the
    joints': one EGM cycle) would hold before any episode. Exit 2 naming the flag, the value, the
    age and the bound, before a driver opens and with nothing written; at the bound the command
    goes on to the drivers (here none answers: one line naming the drive, pymodbus's own line
    no longer before it). A fresh process for the export trained under the cell's timing."""
    import socket

    import jax

    from deploy.sim.export import export
    from models import PolicyConfig, identity_normalizer, init_params
    from ttmjx.world.config import CELL_TRAINING, World
    pcfg = PolicyConfig(hidden=8, layers=1)
    params = init_params(jax.random.key(0), pcfg, identity_normalizer(13))
    cell_timed = export(params, pcfg, dataclasses.replace(World(), timing=CELL_TRAINING), str(tmp_path / "ex"),
                        control_hz=20, source="random-init")
    egm, tracker = free_ports(socket.SOCK_DGRAM, 2)
    (gantry,) = free_ports(socket.SOCK_STREAM, 1)
    toml = tmp_path / "cell.toml"
    toml.write_text(f"[egm]\nport = {egm}\n[gantry]\nport = {gantry}\n[tracker]\nport = {tracker}\n")
    out = tmp_path / "logs"
    t = CELL_TRAINING
    ball_ms = 1e3 * (1 / t.tracker_hz + t.tracker_latency_s + t.delay_spread_s + t.jitter_s)    # 29 ms
    argv = ["robot", "run", "--policy", cell_timed, "--station", "cell", "--config", toml, "--goals", "five",
            "--out", out]
    one_line_error(run(*argv, "--stale-ms", "28"), 2, "ttmjx robot run: error:", "--stale-ms 28",
                   f"the cell's ball samples are up to {ball_ms:.3g} ms old", "125 Hz", "latency up to 20 ms",
                   f"expected at least {ball_ms:.3g} ms")
    # an export trained seeing the ball every physics step: the joints' EGM cycle bounds it
    one_line_error_here(argv[:2] + ["--policy", tiny_export] + argv[4:] + ["--stale-ms", "3"], 2,
                        "ttmjx robot run: error:", "--stale-ms 3", "the cell's joint samples are up to 4 ms old",
                        "one EGM cycle at 250 Hz", "expected at least 4 ms")
    assert not out.exists()
    done = run(*argv, "--stale-ms", f"{ball_ms:.3g}")
    one_line_error(done, 2, "ttmjx robot run: error:", "gantry: cannot connect", f"127.0.0.1:{gantry}")
    assert done.stderr.strip().count("\n") == 0, done.stderr


def test_baseline_on_the_cpu_states_the_expected_time_before_it_starts(tmp_path, capsys, monkeypatch):
    """`ttmjx baseline ppo --scale tiny` ran ~77 minutes on 2 CPU cores saying nothing of it: one
    stderr line before the first cell, with the steps, the time and the GPU (the training
    itself replaced here: the line is all this test is about)."""
    from eval import baselines, table_cells

    def started(*args, **kwargs):
        raise SystemExit(7)
    monkeypatch.setattr(table_cells, "run_cells", started)
    monkeypatch.setattr(baselines.jax, "default_backend", lambda: "cpu")
    monkeypatch.setattr(baselines.os, "cpu_count", lambda: 2)
    with pytest.raises(SystemExit) as ex:
        run_here("baseline", "ppo", "--scale", "tiny", "--out", tmp_path / "b")
    said = [ln for ln in capsys.readouterr().err.splitlines() if "on the CPU" in ln]
    assert ex.value.code == 7 and len(said) == 1, said
    assert all(w in said[0] for w in ("5 RL cell(s)", "262,400 environment steps", "about 77 min", "a GPU")), said
    monkeypatch.setattr(baselines.jax, "default_backend", lambda: "gpu")
    with pytest.raises(SystemExit):
        run_here("baseline", "ppo", "--scale", "tiny", "--out", tmp_path / "b")
    assert "on the CPU" not in capsys.readouterr().err


def test_ablate_plan_refuses_a_cell_run_started_with_another_config(tmp_path):
    """`ablate --plan` said "to do" for a cell whose unfinished run was started with another
    configuration (other run-configuration flags), which the real run's trainer then refused: the plan refuses
    it as the run would, one line naming the run directory and the fields."""
    from eval import ablate
    from training.runconfig import to_json
    out = tmp_path / "ab"
    cell = ablate.plan("demos", "tiny", 1, str(out), "d10")[0]
    os.makedirs(cell.run_dir)
    other = dataclasses.replace(cell.config, train=dataclasses.replace(cell.config.train, learning_rate=1e-2))
    (out / "runs" / "d10-seed0" / "config.json").write_text(json.dumps(to_json(other)))
    before = listing(out)
    for argv in (["--plan"], []):
        one_line_error_here(["ablate", "demos", "--scale", "tiny", "--seeds", "1", "--cells", "d10", "--out", out,
                             *argv], 2, "ttmjx ablate: error:", cell.run_dir, "different config", "'train'",
                            "delete")
    assert listing(out) == before


def test_robot_sweep_has_no_config_option_and_list_lengths_are_checked():
    """Refused while parsing, in this process (one_line_error_here)."""
    one_line_error_here(["robot", "sweep", "--policy", RUN, "--out", "x", "--config", "cell.toml"], 2,
                        "ttmjx robot sweep: error:", "--config")
    one_line_error_here(["train", "--preset", "tiny", "--world.throws.narrow-launch", "1.75", "0.35"], 2,
                        "ttmjx train: error:", "--world.throws.narrow-launch", "3 values", "got 2")
    one_line_error_here(["train", "--preset", "tiny", "--world.robot.lower", "1", "1"], 2,
                        "ttmjx train: error:", "--world.robot.lower", "8 entries", "got 2")


def can_mount_tmpfs() -> bool:
    try:
        return subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k none /tmp"],
                              capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def on_a_full_disk(argv: list[str], where: str, size_kb: int) -> subprocess.CompletedProcess:
    """argv with `where` full after size_kb: a tmpfs of that size mounted there in a private mount
    namespace where the machine allows one (ENOSPC), else a file-size limit (RLIMIT_FSIZE: EFBIG,
    the same path through every write)."""
    os.makedirs(where, exist_ok=True)
    if can_mount_tmpfs():
        return subprocess.run(["unshare", "-rm", "sh", "-c", f'mount -t tmpfs -o size={size_kb}k none "$0" && exec "$@"',
                               where, *argv], capture_output=True, text=True, timeout=300, env=ENV, cwd=ROOT)

    def limit():
        resource.setrlimit(resource.RLIMIT_FSIZE, (size_kb * 1024, size_kb * 1024))
    env = {**ENV, **private_compilation_cache(os.path.join(os.path.dirname(where), "jax_cache"))}
    return subprocess.run(argv, capture_output=True, text=True, timeout=300, env=env, cwd=ROOT, preexec_fn=limit)


@pytest.mark.slow
def test_a_full_disk_during_a_checkpoint_is_one_line_naming_the_file(oracle_demos, tmp_path):
    """Orbax's write failing for want of space: one line (not its ~120 lines of tracebacks) with
    the file and the checkpoint, exit 1; the same command runs on when there is space."""
    where = str(tmp_path / "disk")
    argv = command("train", "--preset", "tiny", "--demo-dir", oracle_demos, "--demo-source", "oracle",
                   "--run-dir", os.path.join(where, "run"), "--max-iterations", "1")
    done = on_a_full_disk(argv, where, 1000)
    msg = one_line_error(done, 1, "ttmjx train: error:", os.path.join(where, "run", "checkpoints"),
                         "while saving checkpoint 0", "newest complete checkpoint stays")
    assert "No space left on device" in msg or "File too large" in msg, msg
    assert len([ln for ln in done.stderr.splitlines() if not ln.startswith("WARNING:")]) <= 2, done.stderr[-3000:]


def test_after_a_failed_save_stderr_passes_only_the_main_threads_writes(tmp_path):
    """The save's threads go on failing after the OSError (seen once in a fresh clone: three
    "RuntimeError: Event loop is closed" tracebacks behind the one line, one of them inside it);
    from then on only the main thread's writes reach stderr."""
    import errno
    import io
    import threading

    from training import checkpoint
    real, buf = sys.stderr, io.StringIO()
    sys.stderr = buf
    try:
        with pytest.raises(OSError, match="while saving checkpoint 0"):
            with checkpoint._disk_errors(str(tmp_path), 0):
                raise OSError(errno.ENOSPC, "No space left on device", str(tmp_path / "0" / "state"))
        late = threading.Thread(target=lambda: sys.stderr.write("Traceback (most recent call last):\n"))
        late.start()
        late.join()
        sys.stderr.write("ttmjx train: error: the one line\n")
    finally:
        sys.stderr = real
    assert buf.getvalue() == "ttmjx train: error: the one line\n"


@pytest.mark.slow
def test_demos_on_a_full_disk_names_the_file_and_leaves_nothing(tmp_path):
    """A dataset cut short by a full disk leaves no partial files: the same command runs again."""
    out = tmp_path / "d"
    env = {**ENV, **private_compilation_cache(tmp_path / "jax_cache")}   # its cut writes stay its own
    done = subprocess.run(command("demos", "--source", "oracle", "--n", "20", "--out", out), capture_output=True,
                          text=True, timeout=300, env=env, cwd=ROOT,
                          preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000)))
    one_line_error(done, 1, "ttmjx demos: error:", str(out / "trajectories.npz"), "File too large")
    assert not out.exists(), os.listdir(out)


def resume_tiny(run_dir, oracle_demos) -> subprocess.CompletedProcess:
    """The recorded tiny run's command, on run_dir (a copy of it, damaged by the caller)."""
    return run("train", "--preset", "tiny", "--demo-dir", oracle_demos, "--demo-source", "oracle",
               "--train.practice-goal-margin", "0", "--train.practice-keep", "near_half",
               "--train.action-noise-form", "integrating", "--keep-checkpoints", "10", "--run-dir", run_dir, "--json")


@pytest.mark.parametrize("damage", ["invalid", "empty", "deleted"])
def test_a_damaged_config_json_is_repaired_from_the_checkpoint_on_resume(damage, recorded_tiny_run, oracle_demos,
                                                                         tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(recorded_tiny_run[0], run_dir)
    path = run_dir / "config.json"
    good = json.loads(path.read_text())
    {"invalid": lambda: path.write_text('{"seed": 0,'), "empty": lambda: path.write_text(""),
     "deleted": path.unlink}[damage]()
    done = resume_tiny(run_dir, oracle_demos)
    assert done.returncode == 0, done.stderr[-2000:]
    said = [ln for ln in done.stderr.splitlines() if "config.json" in ln]
    assert said and str(path) in said[0] and "rewritten from the config saved in checkpoint" in said[0], done.stderr[-2000:]
    assert {"invalid": "not valid JSON", "empty": ": empty;", "deleted": ": missing;"}[damage] in said[0], said[0]
    repaired = json.loads(path.read_text())
    assert {k: v for k, v in repaired.items() if k != "run_dir"} == {k: v for k, v in good.items() if k != "run_dir"}



def test_an_emptied_checkpoints_dir_beside_old_metrics_is_refused_and_the_metrics_kept(recorded_tiny_run,
                                                                                       oracle_demos, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(recorded_tiny_run[0], run_dir)
    shutil.rmtree(run_dir / "checkpoints")
    (run_dir / "checkpoints").mkdir()
    before = (run_dir / "metrics.jsonl").read_text()
    done = resume_tiny(run_dir, oracle_demos)
    one_line_error(done, 2, "ttmjx train: error:", str(run_dir), "checkpoints/ holds no checkpoint", "metrics.jsonl")
    assert (run_dir / "metrics.jsonl").read_text() == before


@pytest.mark.slow
def test_a_torn_metrics_line_is_said_on_resume_and_the_rows_kept(recorded_tiny_run, oracle_demos, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(recorded_tiny_run[0], run_dir)
    metrics = run_dir / "metrics.jsonl"
    whole = metrics.read_text()
    metrics.write_text(whole + '{"iteration": 9, "lo')             # a crash in the middle of a write
    done = resume_tiny(run_dir, oracle_demos)
    assert done.returncode == 0, done.stderr[-2000:]
    said = [ln for ln in (done.stdout + done.stderr).splitlines() if "cut short" in ln]   # the run's progress log
    assert said and str(metrics) in said[0], (done.stdout + done.stderr)[-2000:]
    assert metrics.read_text() == whole


@pytest.mark.slow
def test_a_deleted_metrics_log_is_said_on_resume(recorded_tiny_run, oracle_demos, tmp_path):
    """A resumed run whose metrics.jsonl was deleted lost the rows before its checkpoint without
    a word: one warning line on stderr naming the file and the rows lost; the run goes on."""
    run_dir = tmp_path / "run"
    shutil.copytree(recorded_tiny_run[0], run_dir)
    metrics = run_dir / "metrics.jsonl"
    n = len(metrics.read_text().splitlines())
    metrics.unlink()
    done = resume_tiny(run_dir, oracle_demos)
    assert done.returncode == 0, done.stderr[-2000:]
    said = [ln for ln in done.stderr.splitlines() if "metrics.jsonl" in ln]
    assert len(said) == 1 and said[0].startswith("[ttmjx] warning:") and str(metrics) in said[0], done.stderr[-2000:]
    assert f"the rows of {n} of the {n} iterations" in said[0] and "missing" in said[0], said[0]


def test_a_corrupt_demos_file_in_a_resumed_run_is_refused_naming_it(recorded_tiny_run, tmp_path):
    """The run's own demonstrations (RUN/demos, its demo_dir unset) damaged: exit 1 naming the
    file, nothing changed (a restart from scratch would have found it; a resume never did)."""
    from training.runconfig import from_json
    from training.trainer import Run
    run_dir = tmp_path / "run"
    shutil.copytree(recorded_tiny_run[0], run_dir)
    cfg = from_json(json.loads((run_dir / "config.json").read_text()))
    demos = run_dir / "demos"
    shutil.copytree(cfg.demo_dir, demos)            # as a run without --demo-dir collects them
    (demos / "trajectories.npz").write_bytes((demos / "trajectories.npz").read_bytes()[:1000])
    cfg = dataclasses.replace(cfg, demo_dir=None, run_dir=str(run_dir))
    before = listing(run_dir)
    from training.rundir import DamagedRun
    with pytest.raises(DamagedRun, match=str(demos / "trajectories.npz") + ": truncated or corrupt"):
        Run(cfg, progress=False).runs[0].check_demos()
    assert listing(run_dir) == before
    from ttmjx.commandline import run as run_command, Command
    err = io.StringIO()
    with contextlib.redirect_stderr(err), pytest.raises(SystemExit) as ex:
        run_command({"train": Command(None, lambda a: Run(cfg, progress=False).runs[0].check_demos(), "", parse=lambda r: None)},
                    ["train"])
    one_line_error(subprocess.CompletedProcess([], ex.value.code, "", err.getvalue()), 1, "ttmjx train: error:",
                   str(demos / "trajectories.npz"), "truncated or corrupt", "delete")


def test_a_stop_that_lands_where_python_drops_exceptions_is_sent_again():
    """An exception raised in a garbage-collector callback (JAX registers one), a weakref callback
    or a finalizer is printed and dropped: a SIGTERM or Ctrl-C whose handler runs there must
    still stop the command."""
    import gc
    import threading
    import weakref
    from ttmjx import commandline
    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach only the main thread")

    def in_gc_callback(send):
        def callback(phase, info):
            if phase == "start":
                gc.callbacks.remove(callback)
                send()
        gc.callbacks.append(callback)
        gc.collect()

    def in_weakref_callback(send):
        class Thing:
            pass
        thing = Thing()
        ref = weakref.ref(thing, lambda r: send())   # noqa: F841 (kept alive until thing dies)
        del thing

    def stops(sig, stop, where):
        sent = []

        def send():
            sent.append(sig)
            os.kill(os.getpid(), sig)       # its handler runs at the next bytecode: in the callback
            sum(range(10_000))
        with pytest.raises(stop):
            with commandline.stop_on_sigterm():
                where(send)
                time.sleep(2)               # the signal sent again lands here
        assert sent == [sig], where

    before = signal.signal(signal.SIGINT, signal.default_int_handler)   # as in a terminal (see above)
    try:
        for where in (in_gc_callback, in_weakref_callback):
            stops(signal.SIGTERM, commandline.Stopped, where)
            stops(signal.SIGINT, KeyboardInterrupt, where)
    finally:
        signal.signal(signal.SIGINT, before)
