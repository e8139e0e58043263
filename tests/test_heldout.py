"""The loss on held-out demonstrations (eval.heldout): logged at a run's evaluations, finite,
the same number for the same parameters, lower for a trained policy than for an untrained one,
collected once per run (kept in the run directory), each lane of a batch on its own set, and
drawn by `ttmjx report`; a run without demonstrations has none and the report says so."""
import dataclasses
import functools
import json
import math
import os
import shutil

import jax
import numpy as np
import pytest

from eval.diagnostics import write_report
from eval.evaluate import training_evaluation
from eval.heldout import HELDOUT_DEMOS, HELDOUT_DIR, HELDOUT_SEED_OFFSET, HeldOut, with_heldout_loss
from training import runconfig
from training.checkpoint import load_checkpoint
from training.trainer import Run
from training.update import acting_params, init_train_state
from ttmjx.tools import demos
from ttmjx.world import record


@pytest.fixture(scope="module")
def run(oracle_demos, tmp_path_factory):
    """tiny on the oracle's demonstrations: two pretraining chunks, the LFP evaluation (with the
    held-out loss) and a practice round, so `ttmjx report` has a round to draw."""
    cfg = dataclasses.replace(runconfig.tiny(), demo_dir=oracle_demos, demo_source="oracle",
                              run_dir=str(tmp_path_factory.mktemp("heldout") / "run"))
    Run(cfg, evaluation=functools.partial(training_evaluation, heldout=True), progress=False).run(max_iterations=3)
    return cfg


def rows(cfg):
    return [json.loads(line) for line in open(os.path.join(cfg.run_dir, "metrics.jsonl"))]


def trained_params(cfg):
    return acting_params(load_checkpoint(cfg.run_dir).ck.state)


def no_collecting(monkeypatch):
    def refuse(*a, **k):
        raise AssertionError("held-out demonstrations collected again")
    monkeypatch.setattr(demos, "collect", refuse)


def test_the_heldout_loss_is_logged_deterministic_and_lower_after_training(run, monkeypatch):
    evaluated = [r for r in rows(run) if "eval_within_30cm" in r]
    assert evaluated and all(math.isfinite(r["eval_heldout_loss"]) for r in evaluated)
    r = evaluated[0]
    assert r["eval_heldout_loss"] == pytest.approx(np.mean([r["eval_member0_heldout_loss"],
                                                            r["eval_member1_heldout_loss"]]))
    # the set is in the run directory, of the run's source at another seed than its demonstrations
    held, meta = record.load(os.path.join(run.run_dir, HELDOUT_DIR))
    assert held.size == HELDOUT_DEMOS and meta["seed"] == run.seed + HELDOUT_SEED_OFFSET
    assert meta["source"] == "oracle"
    own, _ = record.load(run.demo_dir)
    assert not np.isin(held.actions[:, 0], own.actions[:, 0]).all()
    # read back, never collected again (a resumed run), and the same number twice
    no_collecting(monkeypatch)
    params = trained_params(run)
    stacked = jax.tree.map(lambda x: x[None], params)
    first, again = HeldOut([run]).metrics(stacked)[0], HeldOut([run]).metrics(stacked)[0]
    assert first == again and math.isfinite(first["heldout_loss"])
    # an untrained policy of the same normalizer imitates the held-out demonstrations worse
    norm = jax.tree.map(lambda x: x[0], params.norm)              # shared by the members
    fresh = acting_params(init_train_state(jax.random.PRNGKey(7), run.policy, run.train, norm))
    untrained = HeldOut([run]).metrics(jax.tree.map(lambda x: x[None], fresh))[0]["heldout_loss"]
    assert first["heldout_loss"] < 0.5 * untrained, (first, untrained)


def test_a_damaged_heldout_set_is_collected_again_the_same(run, tmp_path):
    copy = dataclasses.replace(run, run_dir=str(tmp_path / "run"))
    shutil.copytree(os.path.join(run.run_dir, HELDOUT_DIR), os.path.join(copy.run_dir, HELDOUT_DIR))
    npz = os.path.join(copy.run_dir, HELDOUT_DIR, "trajectories.npz")
    open(npz, "r+b").truncate(100)                                   # a disk that filled mid-write
    params = jax.tree.map(lambda x: x[None], trained_params(run))
    assert HeldOut([copy]).metrics(params) == HeldOut([run]).metrics(params)
    assert record.load(os.path.dirname(npz))[0].size == HELDOUT_DEMOS   # rewritten whole


def test_each_lane_of_a_batch_scores_its_own_heldout_set(run, tmp_path, monkeypatch):
    other = dataclasses.replace(run, seed=1, run_dir=str(tmp_path / "seed1"))
    params = trained_params(run)
    lanes = jax.tree.map(lambda x: np.stack([x, x, x]), params)        # 2 runs and a padding lane
    inner = lambda p, backend, keys: [{"within_30cm": 0.5}] * 3       # noqa: E731
    got = with_heldout_loss([run, other], inner)(lanes, None, None)
    assert len(got) == 2 and all(g["within_30cm"] == 0.5 for g in got)
    no_collecting(monkeypatch)                      # both sets are on disk now, each in its run
    one = jax.tree.map(lambda x: x[None], params)
    alone = [HeldOut([c]).metrics(one)[0]["heldout_loss"] for c in (run, other)]
    assert [g["heldout_loss"] for g in got] == pytest.approx(alone, rel=1e-5)
    assert alone[0] != alone[1]                     # two seeds, two held-out sets


def test_the_report_draws_the_heldout_loss(run, tmp_path):
    out = write_report(run.run_dir, str(tmp_path / "report"))
    summary = out["summary"]
    assert summary["heldout"]["logged"] and summary["heldout"]["seed"] == run.seed + HELDOUT_SEED_OFFSET
    logged = [r["eval_heldout_loss"] for r in rows(run) if "eval_within_30cm" in r]
    assert [e["heldout_loss"] for e in summary["evaluations"]] == logged
    with open(out["json"]) as f:
        assert json.load(f)["heldout"]["logged"]
    with open(out["png"], "rb") as f:
        assert f.read(8) == b"\x89PNG\r\n\x1a\n"
    # and the run's TensorBoard log has it beside the other evaluation scalars (training.runlog)
    board = os.path.join(run.run_dir, "tensorboard")
    events = b"".join(open(os.path.join(board, f), "rb").read() for f in os.listdir(board))
    assert b"eval_heldout_loss" in events and b"eval_member1_heldout_loss" in events


def test_a_run_without_demonstrations_has_none_and_the_report_says_so(run, tmp_path):
    gcsl = dataclasses.replace(run, demos=0, pretrain_steps=0, demo_dir=None)
    inner = lambda *a: {"within_30cm": 0.5}      # noqa: E731
    assert with_heldout_loss([gcsl], inner) is inner and with_heldout_loss([gcsl, gcsl], inner) is inner
    # the report of such a run (its rows without the loss) says why, and draws the rest
    for demos_, why in ((0, "no demonstrations"), (run.demos, "not in the run's metrics")):
        d = tmp_path / f"run{demos_}"
        shutil.copytree(run.run_dir, d)
        config = json.load(open(d / "config.json"))
        json.dump({**config, "demos": demos_}, open(d / "config.json", "w"))
        kept = [{k: v for k, v in r.items() if "heldout" not in k} for r in rows(run)]
        (d / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in kept))
        summary = write_report(str(d), str(tmp_path / f"report{demos_}"))["summary"]
        assert not summary["heldout"]["logged"] and why in summary["heldout"]["why"], summary["heldout"]
        assert all("heldout_loss" not in e for e in summary["evaluations"])


@pytest.mark.slow      # ~35 s: the lanes' program; the fast set checks the lanes with a stand-in evaluation
def test_a_batch_of_seeds_logs_each_seeds_loss_on_its_own_set(oracle_demos, tmp_path):
    """`ttmjx train --seeds 2`'s evaluation (training_evaluation with the lanes' configs):
    each seed's logged loss is that of its own checkpoint on its own held-out set, in its directory."""
    from eval.evaluate import training_evaluation
    from training.seeds import seed_configs
    base = dataclasses.replace(runconfig.tiny(), demo_dir=oracle_demos, demo_source="oracle",
                               run_dir=str(tmp_path / "batch"))
    cfgs = seed_configs(base, 2)
    Run(cfgs, functools.partial(training_evaluation, heldout=True), progress=False,
             parent=base.run_dir).run(max_iterations=2)           # the LFP evaluation ends the pretraining
    logged = []
    for c in cfgs:
        row = rows(c)[1]
        assert record.load(os.path.join(c.run_dir, HELDOUT_DIR))[1]["seed"] == c.seed + HELDOUT_SEED_OFFSET
        alone = HeldOut([c]).metrics(jax.tree.map(lambda x: x[None], trained_params(c)))[0]
        assert row["eval_heldout_loss"] == pytest.approx(alone["heldout_loss"], rel=1e-5)
        logged.append(row["eval_heldout_loss"])
    assert logged[0] != logged[1]
