"""Several processes on one host (docs/SCALING.md): `tiny` trained by 2 processes of 2 simulated
CPU devices each (jax.distributed through JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES,
JAX_PROCESS_ID) ends with the state, bit for bit, and the metrics of one process with 4 devices:
the same mesh, the same computation. Each run is a fresh interpreter (XLA's device count is fixed
when JAX starts): this file run as a script with --child."""
import dataclasses
import json
import os
import socket
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def launch(run_dir: str, demo_dir: str, processes: int, local_devices: int) -> None:
    """`processes` processes of `local_devices` devices each train tiny into run_dir; a failed one
    fails the test with its output's tail."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT,
               XLA_FLAGS=f"--xla_force_host_platform_device_count={local_devices}")
    if processes > 1:
        env.update(JAX_COORDINATOR_ADDRESS=f"localhost:{free_port()}", JAX_NUM_PROCESSES=str(processes))
    procs = [subprocess.Popen([sys.executable, __file__, "--child", run_dir, demo_dir],
                              env=dict(env, JAX_PROCESS_ID=str(i)), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(processes)]
    for p in procs:
        out, _ = p.communicate(timeout=1800)
        assert p.returncode == 0, f"{run_dir}: a process failed\n{out[-3000:]}"


def saved(run_dir: str) -> tuple[list, list[dict]]:
    """(the checkpoint's leaves, the metrics rows without their wall time)."""
    import jax
    import numpy as np

    from training import checkpoint
    leaves = [np.asarray(x) for x in jax.tree.leaves(checkpoint.load_checkpoint(run_dir).ck)]
    rows = [{k: v for k, v in json.loads(line).items() if k != "seconds"}
            for line in open(os.path.join(run_dir, "metrics.jsonl"))]
    return leaves, rows


@pytest.mark.slow
def test_two_processes_train_as_one_process_with_their_devices(oracle_demos, tmp_path):
    launch(str(tmp_path / "processes"), oracle_demos, 2, 2)
    launch(str(tmp_path / "one"), oracle_demos, 1, 4)
    (state_p, rows_p), (state_1, rows_1) = saved(str(tmp_path / "processes")), saved(str(tmp_path / "one"))
    assert len(state_p) == len(state_1) and all((u == v).all() for u, v in zip(state_p, state_1))
    assert rows_p == rows_1


def child(run_dir: str, demo_dir: str) -> None:
    """One process of a run (the environment says which)."""
    from training import mesh, runconfig
    mesh.initialize_distributed()
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    cfg = dataclasses.replace(runconfig.tiny(), demo_dir=demo_dir, demo_source="oracle", run_dir=run_dir)
    Run(cfg, evaluate=training_evaluation(cfg), progress=False).run()


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(*sys.argv[2:4])
