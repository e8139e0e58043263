"""The `ttmjx` commands as a user runs them: JSON last lines, datasets, plots, video, errors,
and every subcommand's --help listing every configuration field."""
import ast
import dataclasses
import json
import os
import re
import subprocess
import sys
import typing

import numpy as np
import pytest
import tyro

from training.runconfig import RunConfig, preset
from ttmjx.cli import COMMANDS, main
from ttmjx.world import record

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def ttmjx(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "ttmjx", *args], capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def last_json(out):
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def here(capsys, *args) -> dict:
    """`ttmjx ARGS --json` in this process (ttmjx.cli.main: the command's own parsing, work and
    output; a failure raises SystemExit with its exit code) -> its JSON last line. For commands
    whose result is under test, not their process: a fresh one pays ~5 s of imports and traces
    its programs again. Exit codes and stderr as a user sees them stay in fresh processes
    (ttmjx above)."""
    capsys.readouterr()
    main(list(args))
    return json.loads(capsys.readouterr().out.strip().splitlines()[-1])


def test_throw_json_reports_frame_and_simulated_bounces(capsys):
    res = here(capsys, "throw", "--distribution", "any", "--n", "5", "--seed", "3", "--json")
    assert res["frame"] == {"table_top_z": 0.76, "table_x": [-1.37, 1.37], "table_y": [-0.7625, 0.7625]}
    assert len(res["throws"]) == 5
    for t in res["throws"]:
        assert set(t) == {"launch_pos", "launch_vel", "launch_spin", "aim", "bounce"}
        assert np.hypot(t["aim"][0] - t["bounce"][0], t["aim"][1] - t["bounce"][1]) < 0.02
        assert 5.0 <= np.linalg.norm(t["launch_vel"]) <= 9.0


@pytest.mark.slow
def test_bench_c_reports_rates_against_the_raw_rollout_baseline():
    res = last_json(ttmjx("bench", "--backend", "c", "--batch", "16", "--json"))
    for k in ("physics_steps_per_s", "throws_per_s", "compile_s", "rollout_baseline_steps_per_s"):
        assert res[k] > 0, k


@pytest.mark.slow    # 38-82 s of compiles for 24 striker throws; the fast set keeps `ttmjx demos` (test_paper_bootstrap)
def test_demos_dataset_plot_and_no_overwrite(tmp_path, capsys):
    out = str(tmp_path / "d")
    # The striker (the paper's bootstrap is `paper`: tests/test_paper_bootstrap.py).
    res = here(capsys, "demos", "--source", "striker", "--distribution", "narrow", "--n", "24", "--out", out, "--json")
    assert set(res) == {"n", "hit_rate", "return_rate", "coverage", "area_within_30cm", "landing_std_x",
                        "landing_std_y", "seconds"} and res["n"] == 24
    assert res["hit_rate"] >= 0.9  # the narrow threshold, on a small sample
    traj, meta = record.load(out)
    assert traj.size == 24 and meta["source"] == "striker" and meta["distribution"] == "narrow"
    assert os.path.getsize(os.path.join(out, "coverage.png")) > 10_000
    assert meta["schema_version"] == record.SCHEMA_VERSION and "code_version" in meta
    again = ttmjx("demos", "--n", "4", "--out", out)
    assert again.returncode == 2 and "already holds files" in again.stderr
    png = here(capsys, "plot-landings", out, "--json")["plot"]
    assert os.path.getsize(png) > 10_000


def test_bad_input_is_refused_before_any_work(tmp_path):
    bad = ttmjx("throw", "--distribution", "wide")
    assert bad.returncode == 2 and bad.stderr.startswith("ttmjx throw: error: invalid choice 'wide'")
    assert "Expected one of ('narrow', 'any', 'varied')" in bad.stderr and bad.stderr.count("\n") == 1
    bad = ttmjx("throw", "--n", "0")
    assert bad.returncode == 2 and bad.stderr.startswith("ttmjx throw: error: --n 0: expected between 1 and ")
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


def no_opengl() -> str:
    """Why this machine cannot render ('' if it can)."""
    from ttmjx.tools import render
    try:
        render.gl_context_class()
    except render.NoOpenGLError as e:
        return str(e)
    return ""


@pytest.mark.slow
@pytest.mark.skipif(bool(no_opengl()), reason=no_opengl())
def test_render_writes_an_animated_gif(tmp_path):
    path = str(tmp_path / "throws.gif")
    res = last_json(ttmjx("render", "--n", "1", "--out", path, "--json"))
    assert res["video"] == path
    from PIL import Image
    with Image.open(path) as im:
        assert im.n_frames >= 20 and im.size == (480, 320)


# -- the command table and --help -------------------------------------------------------------
def help_of(capsys, monkeypatch, *argv) -> str:
    """`ttmjx ARGV --help` in this process (exit 0), boxes and line breaks folded away."""
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    return " ".join(re.sub(r"[│╭╮╰╯─]", " ", capsys.readouterr().out).split())


def flags(cls, prefix="--"):
    """The flag of every field of an args dataclass, nested configuration fields included
    (a field named with tyro.conf.arg(name="") adds no prefix; positionals have no flag)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        meta = getattr(hints[f.name], "__metadata__", ())
        if tyro.conf.Positional in meta:
            continue
        flag = prefix + f.name.replace("_", "-")
        nested = hints[f.name].__origin__ if meta else f.default
        if dataclasses.is_dataclass(nested):
            unprefixed = any(getattr(m, "name", None) == "" for m in meta)
            yield from flags(nested if isinstance(nested, type) else type(nested), prefix if unprefixed else flag + ".")
        else:
            yield flag


def test_every_subcommand_help_lists_every_field(capsys, monkeypatch):
    assert [*COMMANDS] == ["throw", "bench", "render", "sim", "demos", "plot-landings", "train", "eval",
                           "report", "ablate", "baseline", "export", "robot run", "robot sweep", "robot parity", "robot serve", "robot bench"]
    assert len(list(flags(COMMANDS["train"].args))) > 100     # RunConfig's nested fields
    for name, cmd in COMMANDS.items():
        text = help_of(capsys, monkeypatch, *name.split())
        assert text.startswith(f"usage: ttmjx {name} ")
        for flag in flags(cmd.args):
            assert re.search(re.escape(flag) + r"[ ,]", text), f"ttmjx {name} --help lacks {flag}"
    assert "robot bench" in help_of(capsys, monkeypatch) and "run" in help_of(capsys, monkeypatch, "robot")


@pytest.mark.parametrize("name", ["tiny", "paper-sim-new"])
def test_train_help_shows_the_presets_defaults(name, capsys, monkeypatch):
    text = help_of(capsys, monkeypatch, "train", "--preset", name)
    cfg = preset(name)
    for flag, value in (("--train.members INT", cfg.train.members), ("--world.control-hz INT", cfg.world.control_hz),
                        ("--run-dir STR", cfg.run_dir), ("--policy.kind STR", cfg.policy.kind)):
        # the flag, its help (up to the next flag) and its default
        assert re.search(re.escape(flag) + r" (?:(?! --\w).)*?\(default: " + re.escape(str(value)) + r"\)", text), \
            (flag, value)


def test_train_overrides_on_top_of_a_preset():
    from ttmjx.cli import parse_train
    a = parse_train(["--preset", "paper-sim-new", "--seed", "2", "--train.members", "4", "--world.control-hz", "20",
                     "--train.window", "16", "--demo-dir", "d", "--total-trajectories", "9", "--no-practice", "--json",
                     "--max-iterations", "3"])
    assert a.json and a.max_iterations == 3 and isinstance(a.config, RunConfig)
    cfg = a.config
    assert (cfg.preset, cfg.seed, cfg.train.members, cfg.demo_dir, cfg.total_trajectories, cfg.practice) == \
        ("paper-sim-new", 2, 4, "d", 9, False)
    assert cfg.run_dir == "runs/paper-sim-new-seed2" and cfg.policy.hidden == 1024
    assert cfg.world.control_hz == 20 and cfg.world.substeps == 50     # physics_dt derived again
    assert parse_train(["--preset", "tiny", "--seed", "2", "--run-dir", "x"]).config.run_dir == "x"


def test_json_line_is_valid_json(capsys):
    from ttmjx.cli import Report, report
    report(Report(json=True), {"a": float("nan"), "b": [np.float64("inf"), 1.5], "c": {"d": -np.inf}}, "text")
    assert json.loads(capsys.readouterr().out) == {"a": None, "b": [None, 1.5], "c": {"d": None}}


def package(module: str) -> str:
    """training.checkpoint -> training; ttmjx.world.config -> ttmjx.world (ttmjx holds three layers)."""
    parts = module.split(".")
    return ".".join(parts[:2] if parts[0] == "ttmjx" else parts[:1])


def test_no_module_imports_a_private_name_of_another_package():
    """The layers meet through public names only (tests/test_layers.py: no upward imports, no
    module loaded by name)."""
    paths = [os.path.join(d, f) for pkg in ("ttmjx", "models", "training", "eval", "deploy")
             for d, _, files in os.walk(os.path.join(ROOT, pkg)) for f in files if f.endswith(".py")]
    assert os.path.join(ROOT, "ttmjx", "cli.py") in paths
    for path in paths:
        mine = package(os.path.relpath(path, ROOT)[:-3].replace(os.sep, "."))
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, ast.ImportFrom) and node.module and package(node.module) != mine:
                private = [a.name for a in node.names if a.name.startswith("_")]
                assert not private, f"{path}:{node.lineno} imports {private} from {node.module}"


def test_importing_mjx_and_brax_is_quiet_unless_asked():
    """MJX's optional Warp backend prints "Failed to import warp" when Warp is absent; ttmjx
    imports MJX (and brax, which imports it) without that noise; TTMJX_VERBOSE=1 lets it through."""
    code = ("from ttmjx.world.backends import MjxPhysics; from ttmjx.world.config import World; "
            "MjxPhysics(World()); import training.baselines.env; print('done')")
    quiet = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                           env={k: v for k, v in os.environ.items() if k != "TTMJX_VERBOSE"})
    assert quiet.returncode == 0, quiet.stderr[-2000:]
    assert quiet.stdout == "done\n" and "Failed to import" not in quiet.stderr, (quiet.stdout, quiet.stderr)
    try:
        import warp  # noqa: F401
        return                      # Warp installed: nothing to print either way
    except ImportError:
        pass
    verbose = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                             env=dict(os.environ, TTMJX_VERBOSE="1"))
    assert verbose.returncode == 0 and "Failed to import warp" in verbose.stdout, verbose.stdout


@pytest.mark.parametrize("signal_name, exc, code", [("SIGTERM", "stopped", 143), ("SIGINT (Ctrl-C)", "interrupt", 130)])
def test_a_stop_says_whether_the_same_command_resumes(signal_name, exc, code, capsys):
    """A command that keeps its work (train, ablate, ...) tells the user to run it again to
    resume; one that writes nothing or writes whole (bench, eval, ...) does not promise a resume."""
    from ttmjx import cli, commandline

    def stopped(_args):
        raise commandline.Stopped(15) if exc == "stopped" else KeyboardInterrupt

    def one_line(name: str) -> str:
        commands = {name: cli.COMMANDS[name]._replace(run=stopped, parse=lambda rest: None)}
        with pytest.raises(SystemExit) as e:
            commandline.run(commands, [name])
        assert e.value.code == code
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith(f"ttmjx {name}: error: stopped by {signal_name}; "), err
        return err
    for name in ("train", "ablate", "baseline", "demos", "robot run", "robot sweep"):
        assert one_line(name).endswith("what was saved is kept: run the same command to resume")
    for name in ("bench", "eval", "report", "export", "throw", "sim", "render", "plot-landings", "robot bench",
                 "robot serve"):
        assert one_line(name).endswith("it keeps no partial output: run the same command again")
