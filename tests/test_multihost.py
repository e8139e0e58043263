"""Lanes over several processes on one host (docs/SCALING.md): four `tiny` seeds trained by 2
processes of 2 simulated CPU devices each (the launcher's JAX_NUM_PROCESSES and JAX_PROCESS_ID;
each process trains its block of two lanes) end where the same four seeds trained by one process
over 4 devices end: every lane's log and weights. Each run is a
fresh interpreter (XLA's device count is fixed when JAX starts): this file run as a script with
--child."""
import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEEDS, ITERATIONS = 4, 4   # tiny: two pretraining chunks, then two practice rounds


def launch(run_dir: str, demo_dir: str, processes: int, local_devices: int) -> list[str]:
    """`processes` processes of `local_devices` devices each train SEEDS tiny seeds into run_dir;
    a failed one fails the test with its output's tail. Returns every process's output."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT,
               XLA_FLAGS=f"--xla_force_host_platform_device_count={local_devices}")
    if processes > 1:
        env.update(JAX_NUM_PROCESSES=str(processes))
    procs = [subprocess.Popen([sys.executable, __file__, "--child", run_dir, demo_dir],
                              env=dict(env, JAX_PROCESS_ID=str(i)), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(processes)]
    outs = []
    for p in procs:
        out, _ = p.communicate(timeout=1800)
        assert p.returncode == 0, f"{run_dir}: a process failed\n{out[-3000:]}"
        outs.append(out)
    return outs


def lane_dirs(run_dir: str) -> list[str]:
    return [os.path.join(run_dir, f"seed{s}") for s in range(SEEDS)]


def rows(run_dir: str) -> list[dict]:
    """The metrics rows without their wall time and the program's lane count (2 per process
    against 4 in one)."""
    return [{k: v for k, v in json.loads(line).items() if k not in ("seconds", "seeds_in_program")}
            for line in open(os.path.join(run_dir, "metrics.jsonl"))]


@pytest.mark.slow
def test_lanes_over_two_processes_train_as_one_process_with_their_devices(oracle_demos, tmp_path):
    outs = launch(str(tmp_path / "processes"), oracle_demos, 2, 2)
    launch(str(tmp_path / "one"), oracle_demos, 1, 4)
    import jax

    from training import checkpoint
    # each process trained its own block of lanes: seeds 0-1 and 2-3
    assert [json.loads(o.strip().splitlines()[-1])["seeds"] for o in outs] == [[0, 1], [2, 3]]
    assert json.load(open(tmp_path / "processes" / "seeds.json"))["seeds"] == list(range(SEEDS))
    for p_dir, one_dir in zip(lane_dirs(str(tmp_path / "processes")), lane_dirs(str(tmp_path / "one"))):
        got, want = rows(p_dir), rows(one_dir)
        assert [r["iteration"] for r in got] == list(range(ITERATIONS)) == [r["iteration"] for r in want]
        for g, w in zip(got, want):
            assert set(g) == set(w), g["iteration"]
            for k, v in w.items():   # counts exactly; floats to float32 reassociation (XLA:CPU compiles
                # a 2-device and a 4-device client's programs a little differently)
                assert g[k] == (pytest.approx(v, rel=1e-4) if isinstance(v, float) else v), (p_dir, g["iteration"], k)
        a, b = (checkpoint.load_checkpoint(d).ck for d in (p_dir, one_dir))
        for x, y in zip(jax.tree.leaves((a.state.params, a.state.ema)), jax.tree.leaves((b.state.params, b.state.ema))):
            x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
            assert np.linalg.norm(x - y) <= 1e-3 * max(np.linalg.norm(y), 1e-12), (p_dir, x.shape)
        np.testing.assert_array_equal(np.asarray(a.cache.count), np.asarray(b.cache.count))


def child(run_dir: str, demo_dir: str) -> None:
    """One process of the batch (the environment says which): `ttmjx train --seeds 4` in-process."""
    import functools

    from training import runconfig

    from eval.evaluate import training_evaluation
    from training.seeds import seed_configs
    from training.trainer import Run
    cfg = dataclasses.replace(runconfig.tiny(), demo_dir=demo_dir, demo_source="oracle", run_dir=run_dir)
    out = Run(seed_configs(cfg, SEEDS), functools.partial(training_evaluation, heldout=True), progress=False,
              parent=run_dir).run(max_iterations=ITERATIONS)
    print(json.dumps({k: v for k, v in out.items() if k != "runs"}))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(*sys.argv[2:4])
