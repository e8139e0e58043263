"""`ttmjx robot run --station cell --config cell.toml` (the command users are told to use for the
real cell) plays an export through the drivers against `ttmjx robot serve` over
loopback sockets, and writes its episode logs."""
import json
import os
import subprocess
import sys

import pytest

pytest.importorskip("abb_robot_client")
pytest.importorskip("pymodbus")

from conftest import machine_stalled  # noqa: E402
from deploy.robot.drivers import config as cellconfig  # noqa: E402
from deploy.robot.drivers.cell import Launcher  # noqa: E402
from deploy.sim.serve import serving  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RUN = os.path.join(ROOT, "tests", "data", "tiny_run_v0")


def ttmjx(*args, timeout=300):
    env = {**os.environ, "PYTHONPATH": ROOT, "JAX_PLATFORMS": "cpu"}
    return subprocess.run([sys.executable, "-m", "ttmjx", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_robot_run_reaches_the_cell_station(tmp_path):
    from ttmjx.cli import main
    export = tmp_path / "export"
    # the export the run plays, made in this process (a fresh one pays ~10 s of imports and
    # tracing); a failure raises SystemExit. The robot commands below run as a user runs them.
    main(["export", RUN, "--out", str(export), "--control-hz", "20", "--onnx", "off", "--json"])
    missing = ttmjx("robot", "run", "--policy", str(export), "--station", "cell", "--goals", "five")
    assert missing.returncode == 2 and "--config" in missing.stderr and missing.stderr.count("\n") == 1, missing.stderr
    config = tmp_path / "cell.toml"
    cell = cellconfig.loopback_config()
    config.write_text(cellconfig.to_toml(cell))

    def play(out):
        played = ttmjx("robot", "run", "--policy", str(export), "--station", "cell", "--config", str(config),
                       "--goals", "0.7,0.3", "--stale-ms", "250", "--out", str(out), "--json")
        assert played.returncode in (0, 1), played.stderr[-2000:]      # 1: an episode cut short by a stall
        summary = json.loads(played.stdout.strip().splitlines()[-1])
        print({k: summary.get(k) for k in ("episodes", "goals", "mode", "faults")})
        return summary

    with serving(config, "--policy", str(export), "--seed", "3", env={"JAX_PLATFORMS": "cpu"}):
        launcher = Launcher(cell.launcher)
        out = tmp_path / "logs"
        summary = play(out)
        stats = launcher.call("stats")
        if summary["mode"] == "hold" and machine_stalled(summary, stats):
            # Over loopback nothing is lost: feedback older than 250 ms means one of the two
            # processes was held up (a loaded machine). A broken link holds the second run too.
            gaps = stats["counts"]
            print(f"machine stall (faults {summary['faults']}, serve loop gaps over 100 ms "
                  f"{gaps.get('loop_gaps_over_100ms', 0)}, longest {gaps.get('loop_max_gap_ms')} ms): played again")
            out = tmp_path / "logs_again"
            summary = play(out)
        launcher.close()
    assert summary["goals"] == 1 and summary["episodes"] == 1, summary      # the one goal played and logged
    assert os.path.isdir(out) and any(f.endswith(".meta.json") for f in os.listdir(out)), os.listdir(out)


def test_robot_run_cell_without_config_is_one_line(tmp_path):
    done = ttmjx("robot", "run", "--policy", str(tmp_path), "--station", "cell", "--goals", "five")
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert "--config" in done.stderr or "export" in done.stderr, done.stderr
