"""Lanes over devices (training.mesh.lane_layout, docs/SCALING.md): the compiled programs of a
batch of lanes split over 4 simulated CPU devices move nothing between devices (lanes share
nothing: no collective at all), and a batch trained over 4 devices resumes on 1.

XLA's device count is fixed when JAX starts, so the 4-device half runs in ONE subprocess (this
file run as a script with --xla_force_host_platform_device_count=4); this process has 1 device.
That lane k over several devices computes what it computes alone: tests/test_lanes.py; over
several processes: tests/test_multihost.py.
"""
import dataclasses
import functools
import json
import os
import re
import subprocess
import sys

import jax
import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LANES, FIRST = 4, 3   # lanes of the batch; iterations trained on 4 devices before the resume on 1
COLLECTIVE = re.compile(r"= ([^=]*?) (all-reduce|all-gather|all-to-all|collective-permute|reduce-scatter)(-start)?\(")


def batch(demo_dir, run_dir) -> list:
    """LANES seeds of tiny (oracle demonstrations), every checkpoint kept."""
    from training import runconfig
    from training.seeds import seed_configs
    base = dataclasses.replace(runconfig.tiny(), demo_dir=demo_dir, demo_source="oracle", run_dir=str(run_dir),
                               keep_checkpoints=10)
    return seed_configs(base, LANES)


def collectives(hlo: str) -> list[str]:
    """The cross-device operations of compiled HLO text, as "op result-type"."""
    return [f"{m.group(2)} {m.group(1).strip()}" for m in COLLECTIVE.finditer(hlo)]


# -- the 4-device half (runs in the subprocess) -------------------------------------------------
def compiled_collectives(run) -> dict:
    """The collectives of the lanes' compiled update loop and of their MJX practice round (the
    accelerators' path, compiled, not run: MJX physics on a CPU is slow)."""
    from training.practice import Practice
    from ttmjx.world.backends import Backend
    cfg, lay = run.cfg, run.layout
    ck = run.assemble([r.initial() for r in run.runs])
    keys = run.place(jax.random.split(jax.random.PRNGKey(0), run.lanes))
    loop = run.practice.train_loop.lower(ck.state, ck.cache, keys, run.knobs).compile().as_text()
    mjx = Practice(cfg.world, cfg.policy, cfg.train, Backend(cfg.world, "mjx"), cfg.episodes_per_ssp,
                   cfg.steps_between_ssp, lay, seeds=run.lanes)
    throws = mjx.round_throws(np.asarray(ck.key), 0)
    counted = run.place(np.full(run.lanes, cfg.episodes_per_ssp, np.int32))
    rnd = mjx._round.lower(ck.state, ck.cache, keys, throws, counted, run.knobs).compile().as_text()
    leaf = jax.tree.leaves(ck.state.params)[0]
    return {"devices": run.devices, "params_devices": len(leaf.sharding.device_set),
            "params_spec": str(leaf.sharding.spec), "train_loop": collectives(loop), "mjx_round": collectives(rnd)}


def worker(out_path: str, demo_dir: str, tmp: str) -> None:
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    run = Run(batch(demo_dir, tmp), functools.partial(training_evaluation, heldout=True), progress=False, parent=tmp)
    report = {"device_count": jax.device_count(), "placement": compiled_collectives(run)}
    report["trained"] = run.run(max_iterations=FIRST)["iteration"]
    json.dump(report, open(out_path, "w"))


@pytest.fixture(scope="module")
def four_devices(oracle_demos, tmp_path_factory):
    """The subprocess's batch (trained FIRST iterations over 4 devices) and its report."""
    tmp = tmp_path_factory.mktemp("lanes4")
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT,
               XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4")
    out = tmp / "report.json"
    p = subprocess.run([sys.executable, __file__, str(out), oracle_demos, str(tmp / "batch")], env=env, cwd=ROOT,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=1500)
    assert p.returncode == 0, p.stdout[-5000:]
    return oracle_demos, tmp / "batch", json.load(open(out))


@pytest.mark.slow
def test_lanes_over_four_devices_move_nothing_between_devices(four_devices):
    """Each device holds a block of lanes (one each here). The update loop has no collective: the
    lanes are independent programs side by side. The whole MJX practice round moves no data either:
    its only collectives are scalar predicates, MJX's solver loop asking whether any world of the
    batch still iterates (a while loop vmapped over episodes and lanes continues while any does),
    so the lanes wait for the slowest world's solver, as the episodes of one lane already do."""
    _, _, report = four_devices
    p = report["placement"]
    assert report["device_count"] == 4 and p["devices"] == 4
    assert p["params_devices"] == 4 and p["params_spec"] == "P('lane',)"
    assert p["train_loop"] == [], p["train_loop"]
    assert all(c == "all-reduce pred[]" for c in p["mjx_round"]), p["mjx_round"]


@pytest.mark.slow
def test_a_batch_trained_over_four_devices_resumes_on_one(four_devices):
    """The checkpoints of each lane are its own (one lane each, whatever devices wrote them):
    the same command on one device resumes every lane where it stopped and trains on."""
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    demo_dir, root, report = four_devices
    assert report["trained"] == FIRST
    before = {s: open(os.path.join(root, f"seed{s}", "metrics.jsonl")).read().splitlines() for s in range(LANES)}
    out = Run(batch(demo_dir, root), functools.partial(training_evaluation, heldout=True), progress=False,
              parent=str(root)).run(max_iterations=1)
    assert out["iteration"] == FIRST + 1 and jax.device_count() == 1
    for s in range(LANES):
        lines = open(os.path.join(root, f"seed{s}", "metrics.jsonl")).read().splitlines()
        assert lines[:FIRST] == before[s] and len(lines) == FIRST + 1      # kept, then one more
        assert json.loads(lines[-1])["iteration"] == FIRST


def test_several_processes_take_their_block_of_lanes_from_the_launchers_variables():
    from training.mesh import launcher_process, process_lanes
    assert launcher_process({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}) == (1, 2)
    assert launcher_process({"SLURM_NTASKS": "4", "SLURM_PROCID": "3"}) == (3, 4)
    assert launcher_process({"OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "0"}) == (0, 2)
    assert launcher_process({}) == (0, 1) and launcher_process({"SLURM_NTASKS": "1"}) == (0, 1)
    with pytest.raises(ValueError, match=r"^JAX_PROCESS_ID=2 with JAX_NUM_PROCESSES=2: expected 0\.\.1$"):
        launcher_process({"JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"})
    # each process trains a block of the lanes, as even as the counts allow, and every lane once
    assert [process_lanes(7, 3, i) for i in range(3)] == [(0, 3), (3, 5), (5, 7)]
    assert [process_lanes(4, 2, i) for i in range(2)] == [(0, 2), (2, 4)] and process_lanes(1) == (0, 1)
    with pytest.raises(ValueError, match=r"^2 lane\(s\) over 3 processes: every process needs at least one lane"):
        process_lanes(2, 3, 0)


if __name__ == "__main__":
    worker(*sys.argv[1:4])
