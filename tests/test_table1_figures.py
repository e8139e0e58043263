"""scripts/table1_figures.py: each arm's edges-and-net evaluations are its own seeds' files."""
import importlib.util
import json
import os

SCRIPT = os.path.join(os.path.dirname(__file__), "..", "scripts", "table1_figures.py")


def load_script():
    spec = importlib.util.spec_from_file_location("table1_figures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_an_arm_whose_name_ends_another_arms_takes_only_its_own_files(tmp_path):
    """'b0.05' (our offset noise) is the end of 'paper-b0.05' (the paper's): a glob on
    '*-b0.05-seed*' matches both, so the figures once mixed the two arms' seeds."""
    edges = tmp_path / "edges"
    edges.mkdir()
    files = {"noise-b0.05-seed0": 0.10, "noise-b0.05-seed1": 0.12, "noise-paper-b0.05-seed0": 0.05,
             "noise-paper-b0.05-seed1": 0.06, "noise-paper-b0.05-seed2": 0.07, "ensembles-n1-seed0": 0.04,
             "ensembles-n10-seed0": 0.13}
    for name, w30 in files.items():
        (edges / f"{name}.json").write_text(json.dumps({"within_30cm": w30}))
    f = load_script()
    assert [r["within_30cm"] for r in f.edges_rows(str(tmp_path), "b0.05")] == [0.10, 0.12]
    assert [r["within_30cm"] for r in f.edges_rows(str(tmp_path), "paper-b0.05")] == [0.05, 0.06, 0.07]
    assert [r["within_30cm"] for r in f.edges_rows(str(tmp_path), "n1")] == [0.04]
