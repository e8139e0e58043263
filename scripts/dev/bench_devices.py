"""Time one practice round and one update loop of a preset on 1..N devices of this host
(docs/SCALING.md): the numbers for the multi-GPU table.

    python scripts/dev/bench_devices.py paper-sim-new 1 2        # on a 2-GPU machine
Prints one JSON line per device count: the mesh, seconds per round (rollouts of
episodes_per_ssp throws + steps_between_ssp updates) and per update loop after a warm-up call,
throughput, and the speed-up over the first count.
"""
import dataclasses
import json
import sys
import time

import jax
import numpy as np

from training.runconfig import preset
from training.trainer import Run


def seconds(fn, *args, reps: int = 3) -> float:
    """Seconds per call of fn(*args) after one warm-up (compile) call."""
    jax.block_until_ready(fn(*args))
    t0 = time.perf_counter()
    for _ in range(reps):
        jax.block_until_ready(fn(*args))
    return (time.perf_counter() - t0) / reps


def bench(name: str, devices: int) -> dict:
    cfg = dataclasses.replace(preset(name), demos=256, devices=devices, run_dir=f"/tmp/bench_devices_{name}")
    run = Run(cfg, progress=False)
    ck = run.initial()
    key = np.asarray(ck.key)
    throws = run.practice.round_throws(key, 0)
    rnd = seconds(run.practice.iteration, ck.state, ck.cache, key, throws)
    loop = seconds(run.practice.train_loop, ck.state, ck.cache, key)
    return {"preset": name, "devices": devices, "mesh": dict(run.layout.mesh.shape), "backend": run.backend.name,
            "round_s": round(rnd, 4), "train_loop_s": round(loop, 4),
            "episodes_per_s": round(cfg.episodes_per_ssp / rnd, 1),
            "updates_per_s": round(cfg.steps_between_ssp * cfg.train.members / loop, 1)}


def main(name: str, counts: list[int]) -> None:
    first = None
    for n in counts:
        row = bench(name, n)
        first = first or row
        row["round_speedup"] = round(first["round_s"] / row["round_s"], 2)
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], [int(n) for n in sys.argv[2:]] or [1, jax.device_count()])
