"""One override language: `ttmjx train`, `ttmjx ablate` and `ttmjx baseline` read the run
configuration's flags with the same code (training/overrides.py), each on top of its base (a
preset, a table's scale), and the flags reach every cell's configuration."""
import pytest

from eval import ablate, baselines
from training import overrides
from training.runconfig import preset
from ttmjx import cli


def test_the_flags_reach_every_baseline_cell(tmp_path):
    """GCSL, LFP and GoalsEye cells take the flags as their run configuration; RL cells take them
    in their run (world, policy); --seed is the first seed; the summary's command names them."""
    argv = ["gcsl,lfp,goalseye,ppo", "--scale", "tiny", "--seeds", "2", "--seed", "3", "--demo-source", "striker",
            "--world.throws.spin", "--eval-goals", "8", "--out", str(tmp_path / "b")]
    a = cli.parse_baseline(argv)
    assert a.config.seed == 3
    changed = ablate.cell_overrides(baselines.goalseye_base("tiny"), a.config, taken=("seed",))
    assert changed == {"world.throws.spin": True, "demo_source": "striker", "eval_goals": 8}
    cells = baselines.plan(baselines.parse_methods(a.method), "tiny", a.seeds, str(tmp_path / "b"),
                           first_seed=a.config.seed, changed=changed)
    runs = [getattr(c.config, "run", c.config) for c in cells]
    assert len(cells) == 8 and sorted({r.seed for r in runs}) == [3, 4]
    assert all(r.world.throws.spin and r.eval_goals == 8 for r in runs)
    assert all(c.config.demo_source == "striker" for c in cells if not hasattr(c.config, "run"))
    by_name = {c.name: c.config for c in cells}
    assert [by_name[f"{m}-seed3"].demos for m in ("gcsl", "lfp", "goalseye")] == [0, 328, 200]   # theirs win
    assert baselines.command_line(a.method, "tiny", 2, 3, None, None, changed).endswith(
        "--seeds 2 --seed 3 --world.throws.spin --demo-source striker --eval-goals 8")


def test_train_reads_the_same_flags_with_the_same_code():
    """The refusal of a timing flag that ideal timing would reset is one rule for every command."""
    with pytest.raises(ValueError, match="--world.timing.tracker-latency-s would be ignored.*preset tiny"):
        cli.parse_train(["--preset", "tiny", "--world.timing.tracker-latency-s", "0.01"])
    with pytest.raises(ValueError, match="--world.timing.tracker-latency-s would be ignored.*ablation demos's base"):
        cli.parse_ablate(["demos", "--scale", "tiny", "--world.timing.tracker-latency-s", "0.01"])
    a = cli.parse_train(["--preset", "tiny", "--seed", "2"])
    assert a.config.run_dir == preset("tiny").run_dir + "-seed2"


def test_flags_round_trip():
    """changed_fields -> flags_of -> tyro gives the same configuration back; --set pairs become flags."""
    base = preset("tiny")
    argv = ["--demo-source", "striker", "--no-practice", "--world.throws.spin"]
    cfg = cli.parse_train(["--preset", "tiny", *argv]).config
    changed = overrides.changed_fields(base, cfg)
    assert overrides.flags_of(changed) == ["--world.throws.spin", "--demo-source", "striker", "--no-practice"]
    assert cli.parse_train(["--preset", "tiny", *overrides.flags_of(changed)]).config == cfg
    assert overrides.setting_flag("world.timing.ideal_timing=false") == "--world.timing.no-ideal-timing"
    assert overrides.setting_flag("train.action_noise=0.2") == "--train.action-noise 0.2"
    assert overrides.set_refusal(["demos", "--seeds", "2"]) is None
