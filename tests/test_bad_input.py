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
