"""scripts/table1_regions.py: success per third of the goals, by the strict metric."""
import json
import os
import subprocess
import sys

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "scripts", "table1_regions.py")
GOALS = [[0.1, 0.0], [0.2, 0.0], [0.6, 0.0], [0.7, 0.0], [1.1, 0.0], [1.2, 0.0]]


def write_arm(root, arm, seed, landing, on_opponent):
    ablation, variant = arm.split("/")
    d = root / ablation / "results"
    d.mkdir(parents=True, exist_ok=True)
    lands = {"goal": GOALS, "landing": landing, "hit": [x is not None for x in landing], "on_opponent": on_opponent}
    (d / f"{variant}-seed{seed}.json").write_text(json.dumps({"landings": lands}))


def test_each_third_counts_only_strict_successes_of_its_goals(tmp_path):
    # near (0.1, 0.2): one landing on the goal, one 5 cm from it but off the half (a miss);
    # middle (0.6, 0.7): one on the goal, one 50 cm long; far (1.1, 1.2): never hit.
    landing = [[0.1, 0.0], [0.25, 0.0], [0.6, 0.0], [1.2, 0.0], None, None]
    write_arm(tmp_path, "ratio/r0.2", 0, landing, [True, False, True, True, False, False])
    out = subprocess.run([sys.executable, SCRIPT, str(tmp_path), "ratio/r0.2"], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": os.path.join(os.path.dirname(__file__), "..")})
    assert out.returncode == 0, out.stderr
    line = [x for x in out.stdout.splitlines() if x.startswith("ratio/r0.2")][0]
    assert "near / middle / far: 50.0 +- 0.0, 50.0 +- 0.0, 0.0 +- 0.0" in line, line
    # on-half landings: 0.1 (near), 0.6 and 1.2 (middle, far): a third each
    assert "per third: 33% / 33% / 33%" in line and "median +0.00 m" in line, line


def test_an_arm_without_results_is_named(tmp_path):
    out = subprocess.run([sys.executable, SCRIPT, str(tmp_path), "practice/nope"], capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": os.path.join(os.path.dirname(__file__), "..")})
    assert out.returncode != 0 and "no results for 'practice/nope'" in out.stderr
