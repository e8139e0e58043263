"""Several processes on one host (docs/SCALING.md): `tiny` trained by P processes of L simulated
CPU devices each (jax.distributed through JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES,
JAX_PROCESS_ID) must end with the state, bit for bit, and the metrics of one process with
P x L devices: the same mesh, the same computation.

    PYTHONPATH=. python scripts/multihost_check.py [P L]    # default 2 2; a few minutes on 2 cores
Prints one JSON line; exits 1 if the runs differ.
"""
import dataclasses
import json
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def child(run_dir: str, demo_dir: str) -> None:
    """One process of a run (the environment says which)."""
    from training import mesh, runconfig
    mesh.initialize_distributed()
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    cfg = dataclasses.replace(runconfig.tiny(), demo_dir=demo_dir, run_dir=run_dir)
    Run(cfg, evaluate=training_evaluation(cfg), progress=False).run()


def launch(run_dir: str, demo_dir: str, processes: int, local_devices: int) -> None:
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=ROOT,
               XLA_FLAGS=f"--xla_force_host_platform_device_count={local_devices}")
    if processes > 1:
        env.update(JAX_COORDINATOR_ADDRESS="localhost:23571", JAX_NUM_PROCESSES=str(processes))
    procs = [subprocess.Popen([sys.executable, __file__, "--child", run_dir, demo_dir],
                              env=dict(env, JAX_PROCESS_ID=str(i)), stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for i in range(processes)]
    for p in procs:
        out, _ = p.communicate(timeout=1800)
        if p.returncode:
            sys.exit(f"{run_dir}: a process failed\n{out[-3000:]}")


def compare(a: str, b: str) -> dict:
    import jax
    import numpy as np
    from training import checkpoint
    x, y = (jax.tree.leaves(checkpoint.load_checkpoint(d).ck) for d in (a, b))
    rows = [[{k: v for k, v in json.loads(line).items() if k != "seconds"} for line in open(f"{d}/metrics.jsonl")]
            for d in (a, b)]
    return {"same_state": all(np.array_equal(np.asarray(u), np.asarray(v)) for u, v in zip(x, y)),
            "same_metrics": rows[0] == rows[1], "iterations": len(rows[0])}


def main(processes: int, local_devices: int) -> None:
    from training import runconfig
    from ttmjx.tools import demos
    from ttmjx.world import record
    tmp = tempfile.mkdtemp(prefix="multihost_check_")
    demo_dir = f"{tmp}/demos"   # collected once here: the processes would write the same files
    record.save(demo_dir, demos.collect(runconfig.tiny().world, "oracle", 200, seed=5), {"source": "oracle"})
    launch(f"{tmp}/processes", demo_dir, processes, local_devices)
    launch(f"{tmp}/one", demo_dir, 1, processes * local_devices)
    out = {"processes": processes, "devices_per_process": local_devices, "dir": tmp,
           **compare(f"{tmp}/processes", f"{tmp}/one")}
    print(json.dumps(out))
    sys.exit(0 if out["same_state"] and out["same_metrics"] else 1)


if __name__ == "__main__":
    if sys.argv[1:2] == ["--child"]:
        child(*sys.argv[2:4])
    else:
        main(*(int(a) for a in sys.argv[1:3] or (2, 2)))
