"""The same run on 1..N devices (training.mesh, docs/SCALING.md): `tiny` trained on 1 and on 4
simulated CPU devices reaches the same result, a 4-device checkpoint resumes on 1 device, no
compiled step moves the data pool between devices, and counts that cannot be placed are refused
before anything compiles.

XLA's device count is fixed when JAX starts, so the 4-device half runs in ONE subprocess (this
file run as a script with --xla_force_host_platform_device_count=4); this process has 1 device.
"""
import dataclasses
import json
import os
import re
import shutil
import subprocess
import sys

import jax
import numpy as np
import pytest

from recorded import assert_reproduces_a_recording, tiny_recorded

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

# What "the same result" means between 1 and 4 devices. On 4 devices each of tiny's 2 members
# trains on 2 devices: its 16 windows are split 8 + 8 and the loss and gradient are summed in two
# halves, then added (an all-reduce), so float32 sums are reordered (~1e-7 relative per step).
# Adam and 4 practice rounds (whose rollouts feed the slightly different actions through contact
# physics) amplify that over 120 updates; measured: losses 4e-5 relative, weights 3.3e-4 at most
# (largest weight ~0.33), the same episodes kept, the same success counts, the mean landing
# distance 0.2%. The bounds below are ~10x those.
LOSS_RTOL = 1e-3
WEIGHT_ATOL = 5e-3        # |w_4 - w_1|, on weights up to ~0.33
DIST_RTOL = 2e-2          # eval_mean_dist
RATE_ATOL = 1.5 / 32      # practice and evaluation rates: one throw or goal of 32 may flip
# Iterations 0..3 (2 pretraining chunks, 2 practice rounds) before the rollouts' physics turns
# float reassociation into different landings (test_four_devices_reach_the_one_device_result).
DETERMINISTIC_ITERATIONS = 4
# Counts compared exactly: the schedule, and the episodes kept (a flip would show in cache_size).
EXACT = ("iteration", "phase", "trajectories", "updates", "cache_size", "eval_goals")


def tiny(demo_dir, run_dir, **kw):
    """tiny as recorded (tests/recorded.py tiny_recorded: practice as before_renovation.json was
    recorded, every checkpoint kept)."""
    return tiny_recorded(demo_dir, run_dir, **kw)


def rows(run_dir):
    return [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl"))]


def compiles_during(fn):
    """Run fn() (expected to raise ValueError) -> (message, number of JAX compilations)."""
    from jax import monitoring
    seen = []

    def listen(name, *args, **kwargs):
        seen.append(name)
    monitoring.register_event_duration_secs_listener(listen)
    try:
        fn()
    except ValueError as e:
        return str(e), sum("compil" in name for name in seen)
    finally:
        monitoring.unregister_event_duration_listener(listen)
    raise AssertionError("no ValueError")


BYTES = {"pred": 1, "s8": 1, "u8": 1, "bf16": 2, "f16": 2, "s32": 4, "u32": 4, "f32": 4, "s64": 8, "f64": 8}


def collectives(hlo: str) -> list[tuple[str, int, list[str]]]:
    """(op, bytes, shapes) of every cross-device operation in compiled HLO text."""
    out = []
    for m in re.finditer(r"= (.*?) (all-reduce|all-gather|all-to-all|collective-permute|reduce-scatter)\(", hlo):
        shapes = re.findall(r"(\w+)\[([\d,]*)\]", m.group(1))
        size = sum(BYTES[t] * int(np.prod([int(d) for d in dims.split(",") if d])) for t, dims in shapes)
        out.append((m.group(2), size, [f"{t}[{dims}]" for t, dims in shapes]))
    return out


# -- the 4-device half (runs in the subprocess) -------------------------------------------------
def placement_report(run) -> dict:
    """Where a 4-device run's parts live and what its compiled steps move between devices."""
    from training import checkpoint
    from training.practice import Practice
    from ttmjx.world.backends import Backend
    cfg, lay = run.cfg, run.layout
    ck = run.place(checkpoint.template(cfg))
    loop = run.practice.train_loop.lower(ck.state, ck.cache, jax.random.PRNGKey(0)).compile().as_text()
    # The MJX round (the accelerators' path) is compiled, not run: MJX physics on a CPU is slow.
    mjx = Practice(cfg.world, cfg.policy, cfg.train, Backend(cfg.world, "mjx"), cfg.episodes_per_ssp,
                   cfg.steps_between_ssp, lay)
    throws = mjx.round_throws(jax.random.PRNGKey(0), 0)
    counted = jax.numpy.int32(cfg.episodes_per_ssp)        # every episode of the round joins the pool
    rnd = mjx._round.lower(ck.state, ck.cache, jax.random.PRNGKey(1), throws, counted).compile().as_text()
    leaf = jax.tree.leaves(ck.state.params)[0]
    return {"mesh": dict(lay.mesh.shape), "params_spec": str(leaf.sharding.spec),
            "params_devices": len(leaf.sharding.device_set), "cache_replicated": ck.cache.obs.sharding.is_fully_replicated,
            "cache_row_bytes": sum(x.nbytes for x in jax.tree.leaves(ck.cache)[:7]) // ck.cache.capacity,
            "train_loop": collectives(loop), "mjx_round": collectives(rnd)}


def refusals(demo_dir, tmp) -> dict:
    """The messages of counts that 4 devices cannot place, and the compilations before them."""
    from training.trainer import Run
    cases = {"members": dict(devices=2, episodes_per_ssp=36, train=dict(members=3)),
             "throws": dict(devices=4, episodes_per_ssp=34),
             "batch": dict(devices=4, train=dict(batch_size=15)),
             "devices": dict(devices=5)}
    out = {}
    for name, kw in cases.items():
        train = dataclasses.replace(tiny(demo_dir, tmp).train, **kw.pop("train", {}))
        out[name] = compiles_during(lambda: Run(tiny(demo_dir, f"{tmp}/{name}", train=train, **kw), progress=False))
    return out


def worker(out_path: str, demo_dir: str, tmp: str) -> None:
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    jax.config.update("jax_compilation_cache_dir", os.environ.get("TTMJX_JAX_CACHE", os.path.join(ROOT, ".jax_cache")))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    report = {"device_count": jax.device_count(), "refused": refusals(demo_dir, tmp)}
    cfg = tiny(demo_dir, f"{tmp}/d4", devices=4)   # every checkpoint kept: the parent resumes one
    run = Run(cfg, evaluate=training_evaluation(cfg), progress=False)
    report["d4"] = run.run()
    report["placement"] = placement_report(run)
    json.dump(report, open(out_path, "w"))


# -- the tests (this process: one device) -----------------------------------------------------
@pytest.fixture(scope="module")
def demo_dir(oracle_demos):
    """tiny's 200 oracle (goal-directed striker) narrow demonstrations (those of
    tests/data/before_renovation.json; conftest.py: made once for the session)."""
    return oracle_demos


@pytest.fixture(scope="module")
def runs(demo_dir, tmp_path_factory, request):
    """tiny on 4 simulated CPU devices (the subprocess: the run, the placement and compiled
    collectives, the refusals) and, meanwhile, on this process's one device: the session's
    recorded tiny run (conftest.py recorded_tiny_run, also tests/test_trainer.py's reference),
    trained here unless a module before this one did.

    The 1-device run is made in this process, not in the subprocess: XLA's CPU client with 4
    simulated devices compiles even a one-device program a little differently (its last bits
    differ), so only a 1-device process computes what one device computed before
    (before_renovation.json). Returns (the subprocess's directory, its report, the 1-device run)."""
    tmp = tmp_path_factory.mktemp("runs")
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT,
               XLA_FLAGS=f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4")
    out = tmp / "report.json"
    p = subprocess.Popen([sys.executable, __file__, str(out), demo_dir, str(tmp)], env=env, cwd=ROOT,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    d1, _ = request.getfixturevalue("recorded_tiny_run")
    log, _ = p.communicate(timeout=1500)
    assert p.returncode == 0, log[-5000:]
    return tmp, json.load(open(out)), d1


def assert_same_result(got: list[dict], want: list[dict]):
    """Metric rows of two runs agree: counts exactly, floats within the tolerances above."""
    assert [r["iteration"] for r in got] == [r["iteration"] for r in want]
    for g, w in zip(got, want):
        assert sorted(set(g) - {"seconds"}) == sorted(set(w) - {"seconds"}), g["iteration"]
        for k in set(w) - {"seconds"}:
            if k in EXACT:
                assert g[k] == w[k], (g["iteration"], k)
                continue
            rel, abs_ = ((LOSS_RTOL, 0) if k == "loss" else (DIST_RTOL, 0) if k.endswith(("mean_dist", "mean_dist_landed"))
                         else (0, RATE_ATOL))
            assert g[k] == pytest.approx(w[k], rel=rel, abs=abs_), (g["iteration"], k, g[k], w[k])


def assert_same_weights(a_dir, b_dir, step=None):
    from training import checkpoint
    a, b = (checkpoint.load_checkpoint(str(d), step).ck.state for d in (a_dir, b_dir))
    for x, y in zip(jax.tree.leaves((a.params.net, a.ema.net)), jax.tree.leaves((b.params.net, b.ema.net))):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=WEIGHT_ATOL)


@pytest.mark.slow
def test_one_device_is_the_mesh_of_one_and_computes_the_recorded_numbers(runs):
    _, _, d1 = runs
    assert_reproduces_a_recording(rows(d1))


@pytest.mark.slow
def test_four_devices_reach_the_one_device_result(runs):
    """The same computation up to float reassociation while that is all that separates the two
    runs: pretraining and the first two practice rounds (iterations 0-3; their rollouts play
    weights ~1e-7 apart). From the third round on, the rollouts' contact physics turns those
    last bits into different landings (a hit's timing moves a landing by centimetres): the
    runs are then two draws of one experiment, compared only in their schedule (measured on a
    2-core x86-64 CPU: losses 1e-6 apart through iteration 3, 0.4% at iteration 4; the last
    evaluation 3 vs 2 goals of 32 within 30 cm)."""
    tmp, report, d1 = runs
    assert report["device_count"] == 4 and report["d4"]["finished"]
    got, want = rows(tmp / "d4"), rows(d1)
    assert_same_result(got[:DETERMINISTIC_ITERATIONS], want[:DETERMINISTIC_ITERATIONS])
    schedule = ("iteration", "phase", "trajectories", "updates")
    assert [[r[k] for k in schedule] for r in got] == [[r[k] for k in schedule] for r in want]
    assert_same_weights(tmp / "d4", d1, step=DETERMINISTIC_ITERATIONS)


@pytest.mark.slow
def test_members_and_windows_are_split_and_the_pool_stays_put(runs):
    """tiny's 2 members on 4 devices: a (2 x 2) mesh, each member on 2 devices; the cache
    replicated. No compiled step moves more than one round's M new episodes between devices
    (the pool is 2048 rows); the MJX round gathers exactly those, played on separate devices."""
    _, report, _ = runs
    p = report["placement"]
    assert p["mesh"] == {"member": 2, "batch": 2}
    assert p["params_spec"] == "P('member',)" and p["params_devices"] == 4 and p["cache_replicated"]
    one_round = 32 * p["cache_row_bytes"]
    for step in ("train_loop", "mjx_round"):
        assert p[step], f"{step}: no collective at all (not sharded?)"
        assert max(size for _, size, _ in p[step]) <= one_round, (step, p[step])
    assert any(op == "all-reduce" for op, _, _ in p["train_loop"])          # a member's gradient halves
    assert any(op == "all-gather" and s.startswith("f32[32,160,") for op, _, sh in p["mjx_round"] for s in sh)


@pytest.mark.slow
def test_a_four_device_checkpoint_resumes_on_one_device(runs, demo_dir, tmp_path):
    tmp, _, _ = runs
    from eval.evaluate import training_evaluation
    from training import checkpoint
    from training.trainer import Run
    run_dir = tmp_path / "resumed"
    shutil.copytree(tmp / "d4", run_dir)
    ckpts = str(run_dir / "checkpoints")
    checkpoint.discard(ckpts, [s for s in checkpoint.steps(ckpts) if s > 3])   # as if stopped after iteration 3
    cfg = tiny(demo_dir, run_dir)   # devices=None: all of this process's one device
    out = Run(cfg, evaluate=training_evaluation(cfg), progress=False).run()
    assert out["finished"] and jax.device_count() == 1
    got, want = rows(run_dir), rows(tmp / "d4")
    assert got[:3] == want[:3]                                   # kept from the 4-device run
    assert_same_result(got, want)
    assert_same_weights(run_dir, tmp / "d4")


@pytest.mark.slow
def test_counts_that_cannot_be_placed_are_refused_before_compiling(runs, demo_dir, tmp_path):
    """One line naming the counts, before any compilation (the CLI exits 2 on ValueError)."""
    from training.trainer import Run
    _, report, _ = runs
    want = {"members": r"train.members=3 cannot be placed on 2 devices: .*\(--devices 1, 3\)",
            "throws": r"episodes_per_ssp=34 gives each of train.members=2 members 17 throws, which 2 devices \(of 4\)",
            "batch": r"train.batch_size=15 cannot be split evenly over the 2 devices \(of 4\)",
            "devices": r"devices=5 but only 4 cpu device\(s\) are available"}
    for name, pattern in want.items():
        message, compiled = report["refused"][name]
        assert re.search(pattern, message) and "\n" not in message and compiled == 0, (name, message, compiled)
    message, compiled = compiles_during(lambda: Run(tiny(demo_dir, tmp_path, devices=2), progress=False))
    assert message == "devices=2 but only 1 cpu device(s) are available" and compiled == 0


def test_several_processes_start_from_jax_or_launcher_environment_variables():
    from training.mesh import distributed_settings, initialize_distributed
    explicit = {"JAX_COORDINATOR_ADDRESS": "10.0.0.1:1234", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "1"}
    assert distributed_settings(explicit) == {"coordinator_address": "10.0.0.1:1234", "num_processes": 2,
                                              "process_id": 1}
    assert distributed_settings({"SLURM_NTASKS": "4"}) == {}          # JAX detects the rest
    assert distributed_settings({"OMPI_COMM_WORLD_SIZE": "2"}) == {}
    assert distributed_settings({"SLURM_NTASKS": "1"}) is None       # one process: nothing to join
    assert distributed_settings({}) is None and not initialize_distributed({})


if __name__ == "__main__":
    worker(*sys.argv[1:4])
