"""The outputs of an experiment table against docs/DATA.md ("Experiment tables"), field by field,
as the commands write them at the cheapest scale: `ttmjx ablate demos --scale tiny` (two seeds
of a variant with demonstrations, trained as one program, so balls are hit and land) and
`ttmjx baseline ppo --scale tiny` (brax's PPO, two seeds). QT-Opt's in-process table:
tests/test_qtopt.py."""
import contextlib
import io
import json

import pytest

from documented import check_table_out
from ttmjx import cli


def table_cli(*argv) -> dict:
    """`ttmjx ARGV --json` in this process: the object it printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        cli.main([*argv, "--json"])
    return json.loads(out.getvalue().strip().splitlines()[-1])


@pytest.fixture(scope="module")
def demos_table(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("tables") / "demos")
    argv = ["ablate", "demos", "--scale", "tiny", "--seeds", "2", "--cells", "d10", "--trajectories", "32", "--out", out]
    return out, table_cli(*argv), "ttmjx " + " ".join(argv)


@pytest.fixture(scope="module")
def ppo_table(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("tables") / "ppo")
    argv = ["baseline", "ppo", "--scale", "tiny", "--seeds", "2", "--trajectories", "2", "--out", out]
    return out, table_cli(*argv), "ttmjx " + " ".join(argv)


@pytest.mark.slow
def test_an_ablation_table_holds_what_data_md_says(demos_table):
    from eval.ablate import ABLATIONS
    out, printed, command = demos_table
    saved = check_table_out(out, printed, list(ABLATIONS["demos"].variants), "tiny", command)
    d10 = saved["variants"][1]
    assert d10["variant"] == "d10" and d10["seeds"] == [0, 1]
    # the d10 cells hit balls that came down: the distances are numbers, not only nulls
    assert d10["metrics"]["hit_rate"]["n"] == 2 and d10["metrics"]["mean_dist_landed"]["n"] >= 1, d10["metrics"]


@pytest.mark.slow
def test_a_baseline_table_holds_what_data_md_says(ppo_table):
    from eval.baselines import METHODS
    out, printed, command = ppo_table
    saved = check_table_out(out, printed, list(METHODS), "tiny", command)
    assert [v["variant"] for v in saved["variants"] if v["seeds"]] == ["ppo"]
