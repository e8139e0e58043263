"""Seeds as a batch axis (training/seeds.py): seed k of a batch is the experiment `--seed k` runs
alone, on MuJoCo C (the CPU's backend; MJX runs the same vmapped one-run functions)."""
import dataclasses
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from eval.evaluate import training_evaluation
from models.normalizer import identity_normalizer
from models.policy import init_ensemble, make_policy
from training import budget, checkpoint, runconfig
from training.seeds import check_one_batch, pick_seed, seed_configs, seed_run_dirs
from training.trainer import Run
from ttmjx.world import thrower
from ttmjx.world.backends import Backend
from ttmjx.world.env import uniform_goals

# Per-iteration numbers that depend on the machine's speed or on the batch itself.
NOT_COMPARED = ("seconds", "seeds_in_program")


@pytest.fixture(scope="module")
def demo_dir(oracle_demos):
    """tiny's 200 oracle narrow demonstrations, seed 5 (conftest.py: made once for the session)."""
    return oracle_demos


def tiny(demo_dir, run_dir, **kw):
    return dataclasses.replace(runconfig.tiny(), demo_dir=demo_dir, demo_source="oracle", run_dir=str(run_dir), **kw)


def rows(run_dir):
    return [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"))]


def stack(trees):
    return jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *trees)


def test_a_batched_rollout_records_what_each_run_records_alone():
    """S x B throws stepped in one host loop: each run's record equals its own rollout's, the
    steps after its last throw ended included (a run alone stops there and repeats that step)."""
    cfg = runconfig.tiny()
    be, pol, n_members, b = Backend(cfg.world, "c"), make_policy(cfg.policy), 2, 8
    params = [init_ensemble(jax.random.PRNGKey(s), cfg.policy, identity_normalizer(13), n_members) for s in range(2)]
    keys = [jax.random.PRNGKey(100 + s) for s in range(2)]
    throws = [thrower.sample_throws(jax.random.PRNGKey(200 + s), cfg.world, b) for s in range(2)]
    goals = [np.asarray(uniform_goals(jax.random.PRNGKey(300 + s), b, cfg.world.table)) for s in range(2)]
    alone = [be.rollout_one(pol, params[s], keys[s], throws[s], goals[s], members=n_members) for s in range(2)]
    together = be.rollout(pol, stack(params), np.stack([np.asarray(k) for k in keys]), stack(throws),
                                np.stack(goals), members=n_members)
    for s in range(2):
        for name, x, y in zip(together._fields, together, alone[s]):
            np.testing.assert_array_equal(np.asarray(x)[s], np.asarray(y), err_msg=f"run {s}: {name}")


@pytest.mark.slow
def test_seed_k_of_a_batch_is_seed_k_alone(demo_dir, tmp_path, capsys):
    """Two pretraining chunks, the LFP evaluation and a practice round: every number a run logs,
    and its weights, are those of the same seed trained alone."""
    base = tiny(demo_dir, tmp_path / "batch")
    cfgs = seed_configs(base, 2)
    assert [c.seed for c in cfgs] == [0, 1] and cfgs[1].run_dir == os.path.join(str(tmp_path / "batch"), "seed1")
    out = Run(cfgs, training_evaluation, progress=False, parent=base.run_dir).run(max_iterations=3)
    assert out["iteration"] == 3 and out["seeds"] == [0, 1]
    # seeds.json as docs/DATA.md says: the seeds in order and each one's run directory, relative
    seeds_json = json.load(open(os.path.join(base.run_dir, "seeds.json")))
    assert seeds_json == {"seeds": [0, 1], "run_dirs": ["seed0", "seed1"]}
    for s, d in zip(seeds_json["seeds"], seeds_json["run_dirs"]):
        assert json.load(open(os.path.join(base.run_dir, d, "config.json")))["seed"] == s
    assert seed_run_dirs(base.run_dir) == [c.run_dir for c in cfgs]
    alone_cfg = dataclasses.replace(base, seed=1, run_dir=str(tmp_path / "alone1"))
    Run(alone_cfg, evaluation=training_evaluation, progress=False).run(max_iterations=3)
    batched, alone = rows(cfgs[1].run_dir), rows(alone_cfg.run_dir)
    assert [r["phase"] for r in alone] == ["pretrain", "pretrain", "practice"]
    assert "eval_within_30cm" in alone[1] and "practice_kept" in alone[2]
    for rb, ra in zip(batched, alone, strict=True):
        for k, v in ra.items():
            if k in NOT_COMPARED:
                continue
            if k == "loss":   # float32 arithmetic batched by vmap: equal up to reassociation
                assert rb[k] == pytest.approx(v, rel=1e-4), (ra["iteration"], k)
            else:
                assert rb[k] == v, (ra["iteration"], k, rb[k], v)
    wb, wa = checkpoint.load_checkpoint(cfgs[1].run_dir).ck, checkpoint.load_checkpoint(alone_cfg.run_dir).ck
    for x, y in zip(jax.tree.leaves(wb.state), jax.tree.leaves(wa.state)):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(wb.cache.goal), np.asarray(wa.cache.goal))
    # the seeds differ from each other: two experiments, not one copied
    assert rows(cfgs[0].run_dir)[0]["loss"] != batched[0]["loss"]
    # a seed's directory is an ordinary run: its saved config is seed 1's
    assert json.load(open(os.path.join(cfgs[1].run_dir, "config.json")))["seed"] == 1
    assert pick_seed(base.run_dir, 1) == cfgs[1].run_dir
    # `ttmjx eval BATCH` reports every seed and their spread; --seed-index K one seed
    from ttmjx.cli import EvalArgs, evaluate
    capsys.readouterr()
    evaluate(EvalArgs(run=base.run_dir, goals="8", json=True))
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert out["seeds"] == 2 and [os.path.basename(r["run_dir"]) for r in out["runs"]] == ["seed0", "seed1"]
    assert out["eval_within_30cm_mean"] == pytest.approx(np.mean([r["eval_within_30cm"] for r in out["runs"]]))
    evaluate(EvalArgs(run=base.run_dir, goals="8", seed_index=1, json=True))
    one = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert one["within_30cm"] == out["runs"][1]["eval_within_30cm"]

    # a crash between the seeds' saves: seed 0 one iteration ahead; the batch goes back to 3
    ahead = Run(cfgs[0], progress=False)
    ahead.run(max_iterations=1)
    assert rows(cfgs[0].run_dir)[-1]["iteration"] == 3
    ck = Run(cfgs, None, progress=False).start()
    assert np.asarray(ck.counters.iteration).tolist() == [3, 3]
    assert [r["iteration"] for r in rows(cfgs[0].run_dir)] == [0, 1, 2]


def test_a_batch_must_share_its_configuration(tmp_path):
    a = runconfig.tiny()
    b = dataclasses.replace(a, seed=1, run_dir=str(tmp_path / "b"), demos=100)
    with pytest.raises(ValueError, match=r"differs in \['demos'\]"):
        check_one_batch([dataclasses.replace(a, run_dir=str(tmp_path / "a")), b])
    with pytest.raises(ValueError, match="a directory each"):
        check_one_batch([a, dataclasses.replace(a, seed=1)])
    with pytest.raises(ValueError, match="beyond 2\\*\\*32 - 1"):
        seed_configs(dataclasses.replace(a, seed=2 ** 32 - 2), 3)


def test_memory_is_budgeted_for_every_seed_before_compiling():
    """The estimate grows linearly with the seeds; too many are refused with the figure."""
    cfg = runconfig.paper_sim()
    one = sum(budget.check_fits(cfg, available=10**13).values())
    five = sum(budget.check_fits(cfg, available=10**13, seeds=5).values())
    assert five == 5 * one
    with pytest.raises(ValueError, match=r"--seeds 40 \(runs in one program\) need ~[0-9.]+ GiB.*or the seed count"):
        budget.check_fits(cfg, available=80 * budget.GiB, seeds=40)
    # the lane count that fits is said: 0.9 x 80 GiB over one run's estimate
    fit = int(0.9 * 80 * budget.GiB // one)
    with pytest.raises(ValueError, match=rf"or the seed count: {fit} lane\(s\) fit a device$"):
        budget.check_fits(cfg, available=80 * budget.GiB, seeds=40)
    with pytest.raises(ValueError, match=rf"^40 lanes on each of 4 devices need .*: {fit} lane\(s\) fit a device, "
                                         rf"{4 * fit} over the 4 devices$"):
        budget.check_fits(cfg, available=80 * budget.GiB, seeds=40, devices=4)


def test_seed_index_picks_a_seed_or_names_the_choice(tmp_path):
    batch = tmp_path / "batch"
    batch.mkdir()
    (batch / "seeds.json").write_text(json.dumps({"seeds": [3, 4], "run_dirs": ["seed3", "seed4"]}))
    assert pick_seed(str(batch), 1) == os.path.join(str(batch), "seed4")
    with pytest.raises(ValueError, match=r"holds 2 seeds \(seed3, seed4\): choose one with --seed-index 0..1"):
        pick_seed(str(batch), None)
    with pytest.raises(ValueError, match="--seed-index 2: .* expected 0..1"):
        pick_seed(str(batch), 2)
    with pytest.raises(ValueError, match="a single run"):
        pick_seed(str(tmp_path), 1)
    # a single run cannot be started inside a batch's directory
    with pytest.raises(ValueError, match="holds a batch of seeds"):
        Run(dataclasses.replace(runconfig.tiny(), run_dir=str(batch)), progress=False)


@pytest.mark.parametrize("value", ["0", "-2"])
def test_train_refuses_a_seed_count_below_one_in_one_line(value, tmp_path):
    p = subprocess.run([sys.executable, "-m", "ttmjx", "train", "--preset", "tiny", "--seeds", value,
                        "--run-dir", str(tmp_path / "r")], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [f"ttmjx train: error: --seeds {value}: expected between 1 and 1000"]
    assert not os.path.exists(tmp_path / "r")


def test_arms_that_differ_only_in_their_demonstrations_share_one_program(tmp_path):
    """The demonstrations ablation at full scale: d10, d100 and d1000 have the same schedule
    and differ only in their starting pools, so their 2 x 3 seeds are one program; d0 (no
    demonstrations, no pretraining) is another."""
    from eval import ablate
    from eval.table_cells import seed_groups
    cells = ablate.plan("demos", "full", 2, str(tmp_path / "abl"))
    groups = [sorted(c.name for c in g) for g in seed_groups(cells, str(tmp_path / "abl" / "results"))]
    assert groups == [["d0-seed0", "d0-seed1"],
                      ["d10-seed0", "d10-seed1", "d100-seed0", "d100-seed1", "d1000-seed0", "d1000-seed1"]]
    base = runconfig.tiny()
    arm = lambda demos, name: dataclasses.replace(base, demos=demos, run_dir=str(tmp_path / name))  # noqa: E731
    check_one_batch([arm(100, "a"), arm(98, "b")])            # 8 practice rounds each
    with pytest.raises(ValueError, match=r"differs in \['demos'\] \(and in its schedule"):
        check_one_batch([arm(100, "a"), arm(150, "b")])      # 8 against 6 rounds


@pytest.mark.slow
def test_the_training_benchmark_times_every_piece_of_a_batched_round():
    """`ttmjx bench --train tiny --seeds 2`: every piece timed after its compiling call, the rates
    from the round, the projection from the preset's schedule."""
    from eval.bench_train import bench_training
    out = bench_training("tiny", seeds=2, reps=1, log=lambda m: None)
    pieces = ("pretrain_step", "practice_step", "throws_block", "rollout", "relabel_insert", "updates", "round",
              "evaluation")
    assert all(out[f"{p}_s"] > 0 and out[f"{p}_first_call_s"] > 0 for p in pieces)
    cfg = runconfig.tiny()
    assert out["episodes_per_round"] == 2 * cfg.episodes_per_ssp
    # the rates of a round as the run steps it (which includes the compiled round)
    assert out["trajectories_per_s"] == pytest.approx(2 * cfg.episodes_per_ssp / out["practice_step_s"])
    sch = out["schedule"]
    assert (sch["pretrain_chunks"], sch["practice_rounds"], sch["checkpoints"], sch["throw_blocks"]) == (2, 4, 6, 1)
    # the whole run: the process's start, its setup (demonstrations, starting states and saves),
    # every iteration as Run.step plays it, the evaluations and checkpoints
    assert out["startup_s"] > 0 and out["setup_s"] > 0 and out["save_s"] > 0
    assert out["projected_run_s"] >= (out["startup_s"] + out["setup_s"] + sch["pretrain_chunks"] * out["pretrain_step_s"]
                                      + sch["practice_rounds"] * out["practice_step_s"]
                                      + sch["evaluations"] * out["evaluation_s"] + sch["checkpoints"] * out["save_s"])
    assert out["peak_host_rss_gib"] > 0
