"""`ttmjx ablate`: the table of variants resolves to valid configs, the 95% interval is Student's,
and a real two-cell ablation at the tiny scale writes results, a table, curves and landing maps
that hold the cells' numbers, resumes a half-finished cell from its checkpoint and skips
finished cells when run again."""
import contextlib
import io
import json
import math
import os

import pytest

from eval import ablate
from eval import tables
from eval.evaluate import training_evaluation
from training.trainer import Run
from ttmjx import cli


# -- the table of ablations -------------------------------------------------------------------
@pytest.mark.parametrize("name", ablate.ABLATION_NAMES)
def test_every_variant_resolves_at_every_scale(name):
    for scale in ablate.SCALE_NAMES:
        for variant, overrides in ablate.ABLATIONS[name].variants.items():
            assert not variant.isdigit() and not {":", ","} & set(variant), variant   # --cells can name it
            try:
                cfg = ablate.variant_config(name, variant, scale, seed=3, run_dir="r")
            except ValueError as e:      # a bootstrap variant whose demonstrator this build lacks
                assert name == "bootstrap" and "demo_source=" in str(e) and variant in str(e), e
                continue
            assert cfg.seed == 3 and cfg.run_dir == "r"
            for key, value in overrides.items():
                got = cfg
                for part in key.split("."):
                    got = getattr(got, part)
                want = value.fn(ablate.SCALES[scale].base(ablate.ABLATIONS[name].setting)) \
                    if isinstance(value, ablate.Derived) else value
                assert got == want, (name, variant, scale, key)


def test_derived_overrides_follow_the_base():
    cfg = ablate.variant_config("ensembles", "n3", "tiny", 0, "r")
    assert (cfg.train.members, cfg.episodes_per_ssp) == (3, 33)          # 32 rounded up to 3's multiple
    goalseye = ablate.variant_config("practice", "goalseye", "tiny", 0, "r")
    same_updates = ablate.variant_config("practice", "lfp-equal-updates", "tiny", 0, "r")
    same_data = ablate.variant_config("practice", "lfp-equal-data", "tiny", 0, "r")
    assert not same_updates.practice and same_updates.demos == goalseye.demos
    # tiny: 40 pretraining steps (2 rounds of 20) + 4 practice rounds of 20 updates
    assert ablate.goalseye_updates(goalseye) == 120 == same_data.pretrain_steps
    assert same_data.demos == goalseye.total_trajectories == 328 and not same_data.practice


def test_lfp_at_the_r02_updates_trains_as_many_updates_as_goalseye_at_r02():
    kw = dict(scale="full", seed=0, run_dir="r", trajectories=120_000)
    goalseye = ablate.variant_config("ratio", "r0.2", **kw)
    lfp = ablate.variant_config("practice", "lfp-r0.2-updates", **kw)
    assert goalseye.practice and not lfp.practice and lfp.demos == goalseye.demos
    assert ablate.goalseye_updates(lfp) == ablate.goalseye_updates(goalseye) == 25_400


def test_the_ratio_sweep_changes_updates_per_trajectory_and_nothing_before_practice():
    from training.schedule import pretrain_iterations
    base = ablate.full_base("sim")
    for variant, ratio in (("r0.05", 0.05), ("r0.2", 0.2), ("r1", 1.0)):
        cfg = ablate.variant_config("ratio", variant, "full", 0, "r", trajectories=120_000)
        assert cfg.steps_between_ssp / cfg.episodes_per_ssp == pytest.approx(ratio)
        assert (cfg.steps_between_ssp, cfg.pretrain_steps, pretrain_iterations(cfg), cfg.demos) == \
            (base.steps_between_ssp, base.pretrain_steps, pretrain_iterations(base), base.demos)
        # a checkpoint as often per practice episode as the base run's
        assert cfg.checkpoint_every * cfg.episodes_per_ssp == base.checkpoint_every * base.episodes_per_ssp
    assert ablate.variant_config("ratio", "r0.05", "full", 0, "r").episodes_per_ssp == base.episodes_per_ssp


def test_invalid_variants_are_named():
    with pytest.raises(ValueError, match=r"^RunConfig has no field 'nope'"):
        ablate.apply(ablate.SCALES["tiny"].base("sim"), {"nope.x": 1})
    # RunConfig refuses an unknown demonstrator itself (ablate.check_choices covers Literal fields
    # whose dataclass does not check them).
    with pytest.raises(ValueError, match=r"demo_source='human', expected 'paper', 'striker', 'es' or 'oracle'"):
        ablate.apply(ablate.SCALES["tiny"].base("sim"), {"demo_source": "human", "backend": "c"})
    bad = ablate.apply(ablate.SCALES["tiny"].base("sim"), {"backend": "c"})
    object.__setattr__(bad, "backend", "tpu")
    with pytest.raises(ValueError, match=r"backend='tpu'; expected one of \("):
        ablate.check_choices(bad)
    with pytest.raises(ValueError, match="TrainConfig.members=0"):
        ablate.apply(ablate.SCALES["tiny"].base("sim"), {"train.members": 0})


def test_cell_selection():
    order = ablate.cell_order("demos", 2)
    assert order[:5] == [("d0", 0), ("d10", 0), ("d100", 0), ("d1000", 0), ("d0", 1)]    # seed-major
    assert ablate.select("demos", order, "0:2") == order[:2]
    assert ablate.select("demos", order, "d10,7,6:") == [("d10", 0), ("d10", 1), ("d100", 1), ("d1000", 1)]
    for spec, msg in (("8", "out of range"), ("2:1", "out of range"), ("x", "variant of demos"), ("", "expected")):
        with pytest.raises(ValueError, match=msg):
            ablate.select("demos", order, spec)


# -- statistics ------------------------------------------------------------------------------
def test_interval_is_students_t():
    """References worked by hand: t_{0.975} = 12.7062 (1 df), 4.3027 (2), 2.7764 (4), 2.0930 (19)."""
    assert tables.interval([0.5]) == {"mean": 0.5, "half": None, "n": 1}
    two = tables.interval([1.0, 3.0])                     # s = sqrt(2): half = t * s / sqrt(2)
    assert two["mean"] == 2.0 and math.isclose(two["half"], 12.7062)
    three = tables.interval([0.2, 0.3, 0.4, None, float("nan")])   # s = 0.1; unlanded cells dropped
    assert three["n"] == 3 and math.isclose(three["half"], 4.3027 * 0.1 / math.sqrt(3), rel_tol=1e-9)
    five = tables.interval([1, 2, 3, 4, 5])               # s = sqrt(2.5)
    assert math.isclose(five["half"], 2.7764 * math.sqrt(2.5) / math.sqrt(5), rel_tol=1e-9)
    assert tables.t975(19) == 2.0930 and tables.t975(27) == 2.0595 and tables.t975(10_000) == 1.9799
    assert tables.interval([None]) == {"mean": None, "half": None, "n": 0}
    assert tables.cell_text(two, 100, 1) == "200.0 +- 1270.6" and tables.cell_text(tables.interval([0.25]), 100, 1) == "25.0"


# -- a real ablation at the tiny scale ---------------------------------------------------------
def ablate_cli(*argv) -> tuple[dict, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        cli.main(["ablate", *argv])
    return json.loads(out.getvalue().strip().splitlines()[-1]), out.getvalue() + err.getvalue()


@pytest.mark.slow
def test_tiny_demos_ablation_end_to_end_resumes_and_skips(tmp_path):
    out = str(tmp_path / "abl")
    argv = ["demos", "--scale", "tiny", "--seeds", "2", "--cells", "0:2", "--trajectories", "32", "--out", out]
    # A half-finished cell: d10-seed0 interrupted after its first iteration, as a killed call leaves it.
    half = ablate.plan("demos", "tiny", 2, out, "1", trajectories=32)[0]
    Run(half.config, evaluation=training_evaluation, progress=False).run(max_iterations=1)

    summary, text = ablate_cli(*argv, "--json")
    assert "resuming " + half.run_dir in text
    source = half.config.demo_source                     # the scale's bootstrap demonstrator
    assert summary["cells_run"] == ["d0-seed0", "d10-seed0"] and summary["bootstrap"] == f"{source} (and none: GCSL)"
    results = {v: json.load(open(os.path.join(out, "results", f"{v}-seed0.json"))) for v in ("d0", "d10")}
    for v, r in results.items():
        assert r["config"]["total_trajectories"] == 32 and r["config"]["demos"] == int(v[1:])
        assert len(r["landings"]["goal"]) == len(r["landings"]["landing"]) == r["final"]["goals"] == 32
        assert r["curve"] and r["curve"][-1]["trajectories"] >= 32 and r["wall_s"] > 0
    # the table holds each cell's numbers (one seed: the value, no interval)
    table = open(os.path.join(out, "table.md")).read()
    assert f"bootstrap: {source} (and none: GCSL)" in table.splitlines()[0]
    for v, r in results.items():
        f = r["final"]
        row = f"| {v} | 1 | " + " | ".join(
            "-" if f[k] is None else f"{s * f[k]:.{d}f}" for k, _, s, d in tables.COLUMNS if k in f) + " |"
        assert row in table, (row, table)
    assert "| d100 | 0 | - |" in table
    saved = json.load(open(os.path.join(out, "summary.json")))
    assert saved["variants"][1]["metrics"]["within_30cm"]["values"] == [results["d10"]["final"]["within_30cm"]]
    for png in ("curves.png", "landings/d0.png", "landings/d10.png"):
        with open(os.path.join(out, png), "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n"

    # Again: nothing retrained (the results and the runs' logs untouched), the outputs rebuilt.
    stamps = {p: os.stat(p).st_mtime_ns for r in results.values()
              for p in (os.path.join(r["run_dir"], "metrics.jsonl"), os.path.join(out, "results", f"{r['variant']}-seed0.json"))}
    again, text = ablate_cli(*argv, "--json")
    assert text.count("finished earlier") == 2 and "resuming" not in text
    assert {p: os.stat(p).st_mtime_ns for p in stamps} == stamps
    assert again["variants"] == summary["variants"]
    # A different config for a finished cell is refused, not silently reused.
    with pytest.raises(SystemExit) as e, contextlib.redirect_stderr(io.StringIO()) as err:
        cli.main(["ablate", *argv[:-4], "--trajectories", "64", "--out", out])
    assert e.value.code == 2 and "different config (fields ['total_trajectories'])" in err.getvalue()


def test_t_table_agrees_with_scipy_where_installed():
    stats = pytest.importorskip("scipy.stats")
    for df, t in tables.T975.items():
        assert abs(stats.t.ppf(0.975, df) - t) < 1e-4, df


def test_a_program_too_big_for_the_device_is_refused_in_one_line_with_nothing_written(tmp_path, monkeypatch, capsys):
    """`ttmjx ablate` asks for the device memory of each program of seeds before compiling it:
    refused with the estimate and the device's size, exit 2, no run directory left behind."""
    from training import budget
    from ttmjx import cli
    monkeypatch.setattr(budget, "device_bytes", lambda: 1024 ** 2)
    out = tmp_path / "abl"
    monkeypatch.setattr("sys.argv", ["ttmjx", "ablate", "demos", "--scale", "tiny", "--seeds", "2",
                                     "--cells", "d10", "--out", str(out)])
    with pytest.raises(SystemExit) as e:
        cli.main()
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("[ablate")]
    assert e.value.code == 2 and len(err) == 1, err      # the progress lines aside, one line
    assert err[0].startswith("ttmjx ablate: error: --seeds 2 (runs in one program) need ~")
    assert "GiB of device memory" in err[0] and "the device has 0.0 GiB" in err[0]
    assert not [f for _, _, names in os.walk(out) for f in names]
    assert not os.listdir(out / "runs")


def test_config_flags_reach_every_cell_before_the_variants_own(tmp_path):
    """`ttmjx ablate` takes the run configuration's flags as `ttmjx train` does (parsed by the
    same code), e.g. Table I on another bootstrap: `--demo-source striker`; each is set on every
    cell before the variant's own fields, and the summary's command names them."""
    argv = ["practice", "--scale", "tiny", "--demo-source", "striker", "--train.learning-rate", "5e-4",
            "--world.timing.ideal-timing", "--devices", "1", "--out", str(tmp_path / "t")]
    a = cli.parse_ablate(argv)
    changed = ablate.cell_overrides(ablate.base_config("practice", "tiny"), a.config, taken=("devices",))
    assert changed == {"train.learning_rate": 5e-4, "demo_source": "striker"}   # in field order; tiny's timing is ideal already
    cells = ablate.plan("practice", "tiny", 2, str(tmp_path / "t"), changed=changed, devices=a.config.devices)
    assert len(cells) == 10
    assert all(c.config.demo_source == "striker" and c.config.train.learning_rate == 5e-4
               and c.config.devices == 1 for c in cells)
    assert [c.config.practice for c in cells[:5]] == [True, True, False, False, False]   # the variants' own fields win
    assert ablate.command_line("practice", "tiny", 2, None, None, None, changed, 1) == \
        "ttmjx ablate practice --scale tiny --seeds 2 --train.learning-rate 0.0005 --demo-source striker --devices 1"
    # the flags start from the ablation's base at its scale: ensembles' full base has 10 members
    full = cli.parse_ablate(["ensembles", "--scale", "full", "--train.members", "5", "--episodes-per-ssp", "4000"])
    assert ablate.cell_overrides(ablate.base_config("ensembles", "full"), full.config) == {"train.members": 5}
    # fields each cell sets itself are refused with the flag to write
    for flag, says in ((["--seed", "3"], "--seed 3: the cells' seeds"),
                       (["--total-trajectories", "9"], "--trajectories"), (["--run-dir", "r"], "--out OUT")):
        with pytest.raises(ValueError, match=says):
            ablate.cell_overrides(ablate.base_config("demos", "tiny"),
                                  cli.parse_ablate(["demos", "--scale", "tiny", *flag]).config)


@pytest.mark.parametrize("given, says", [
    (["--set", "demo_source=paper"], "--set demo_source=paper: write --demo-source paper"),
    (["--set", "train.members=4", "practice=false", "--seeds", "1"],
     "--set train.members=4 practice=false: write --train.members 4 --no-practice"),
    (["--set=world.timing.ideal_timing=true"], "--set world.timing.ideal_timing=true: write --world.timing.ideal-timing"),
])
def test_the_retired_set_is_refused_with_the_new_spelling(given, says, capsys):
    """`--set FIELD=VALUE` (ablate's own grammar) is gone: one line saying how to write exactly
    what was given as the flags `train` takes, exit 2, for ablate and baseline alike."""
    for command in (["ablate", "demos", "--scale", "tiny"], ["baseline", "gcsl", "--scale", "tiny"]):
        with pytest.raises(SystemExit) as e:
            cli.main([*command, *given])
        err = capsys.readouterr().err.strip().splitlines()
        assert e.value.code == 2 and err == [f"ttmjx {command[0]}: error: {says}"], err


def test_a_budget_that_no_cell_practises_in_is_refused(tmp_path):
    """`--trajectories 1`: every practising cell would stop at its demonstrations, so the table
    would measure no practice; refused naming the flag, the value and the least that practises.
    A budget where some cells practise (tiny's demos ablation: d1000 exceeds it) stays allowed."""
    from eval import ablate
    with pytest.raises(ValueError, match=r"^--trajectories 1: no cell of practice would practise \(each has at least "
                                         r"200 demonstrations\); expected more than 200$"):
        ablate.plan("practice", "tiny", 1, str(tmp_path / "p"), trajectories=1)
    assert len(ablate.plan("demos", "tiny", 1, str(tmp_path / "d"))) == 4
