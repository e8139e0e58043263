"""Step latency of an exported policy's engines on one CPU core: the numpy policy
(deploy/robot/numpy_policy.py) or its ONNX graph on onnxruntime (deploy/robot/onnx_policy.py), with random
weights of a given size. `ttmjx robot bench` is its command line; `benchmark` times in a fresh
subprocess, so the BLAS / OpenMP thread settings apply before numpy loads.

numpy only (onnxruntime for engine='onnx'): the robot side imports it.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

from deploy.robot.contract import REAL_OBS_SIZE
from deploy.robot.numpy_policy import ExportedPolicy, PolicySpec, random_tensors

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
               "BLIS_NUM_THREADS", "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS")


def _time_steps(policy: ExportedPolicy, steps: int, warmup: int, seed: int,
                prepare: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Wall seconds of `steps` single policy steps (after `warmup`) on random frames, and of the
    `prepare` calls between them (zeros if prepare=False)."""
    rng = np.random.default_rng(seed)
    o, k = policy.spec.obs_size, max(policy.spec.input_frames, 1)
    frames = rng.standard_normal((warmup + steps, k, o)).astype(np.float32)
    state = policy.reset()
    times, prep = np.empty(steps), np.zeros(steps)
    for t in range(warmup + steps):
        if t % 32 == 0:
            state = policy.reset()          # episodes of 32 ticks, as at 20 Hz
        p0 = time.perf_counter()
        if prepare:
            policy.prepare(state)
        t0 = time.perf_counter()
        state, _ = policy.step(state, frames[t, -1], frames[t])
        t1 = time.perf_counter()
        if t >= warmup:
            times[t - warmup], prep[t - warmup] = t1 - t0, t0 - p0
    return times, prep


def _stats(ms: np.ndarray, prefix: str = "") -> dict:
    return {f"{prefix}p50_ms": float(np.percentile(ms, 50)), f"{prefix}p90_ms": float(np.percentile(ms, 90)),
            f"{prefix}p99_ms": float(np.percentile(ms, 99)), f"{prefix}max_ms": float(ms.max()),
            f"{prefix}mean_ms": float(ms.mean())}


ENGINES = ("numpy", "onnx")


def _bench_policy(engine: str, spec: PolicySpec, members: int, seed: int, threads: int) -> tuple:
    """(policy with random weights, versions) of an engine: numpy or the ONNX graph on
    onnxruntime with `threads` intra-op threads."""
    tensors = random_tensors(spec, members, seed)
    if engine == "numpy":
        return ExportedPolicy(spec, tensors), {"numpy": np.__version__}
    if engine != "onnx":
        raise ValueError(f"engine {engine!r}; expected one of {ENGINES}")
    from deploy.robot.onnx_policy import OnnxPolicy, import_onnxruntime, model_bytes
    ort = import_onnxruntime()
    policy = OnnxPolicy(spec, members, model_bytes(spec, tensors), threads=threads)
    return policy, {"numpy": np.__version__, "onnxruntime": ort.__version__}


def bench_here(kind: str = "lstm", hidden: int = 1024, layers: int = 2, members: int = 1,
               frame_stack: int = 8, steps: int = 2000, warmup: int = 200, seed: int = 0,
               obs_size: int = REAL_OBS_SIZE, engine: str = "numpy", threads: int = 1) -> dict:
    """Time single steps in THIS process (thread settings are whatever numpy started with):
    `p50_ms`... the whole step; for the numpy LSTM also `prepared_p50_ms`... the step after
    `prepare` (the critical path when prepare runs between ticks), `prepare_p50_ms`... prepare
    itself. obs_size: values per frame (13 on the robot; 16 with the ball velocity)."""
    spec = PolicySpec(kind, hidden, layers, obs_size, frame_stack).check()
    policy, versions = _bench_policy(engine, spec, members, seed, threads)
    full, _ = _time_steps(policy, steps, warmup, seed)
    out = {"engine": engine, "kind": kind, "hidden": hidden, "layers": layers, "members": members,
           "obs_size": obs_size, "frame_stack": spec.input_frames, "steps": steps,
           **_stats(1e3 * full), **versions}
    if kind == "lstm" and engine == "numpy":
        crit, prep = _time_steps(policy, steps, warmup, seed + 1, prepare=True)
        out.update({**_stats(1e3 * crit, "prepared_"), **_stats(1e3 * prep, "prepare_")})
    return out


def benchmark(kind: str = "lstm", hidden: int = 1024, layers: int = 2, members: int = 1,
              steps: int = 2000, warmup: int = 200, threads: int = 1, cpu: int | None = None,
              timeout_s: float = 600.0, engine: str = "numpy", obs_size: int = REAL_OBS_SIZE,
              frame_stack: int = 8) -> dict:
    """Step latency (p50/p90/p99/max, ms) of a numpy (or, engine='onnx', onnxruntime) policy
    on `threads` BLAS / intra-op threads, pinned to one CPU core (`cpu`, default: the last one
    this process may use), in a fresh subprocess so OMP/OPENBLAS/MKL_NUM_THREADS apply before
    numpy loads. Returns the JSON the child prints, plus the settings."""
    if engine not in ENGINES:
        raise ValueError(f"engine {engine!r}; expected one of {ENGINES}")
    if engine == "onnx":           # here, for a one-line error rather than the child's traceback
        from deploy.robot.onnx_policy import import_onnx, import_onnxruntime
        import_onnx(), import_onnxruntime()
    env = dict(os.environ)
    for v in THREAD_VARS:
        env[v] = str(threads)
    if cpu is None and hasattr(os, "sched_getaffinity"):
        cpu = max(os.sched_getaffinity(0))
    settings = {"kind": kind, "hidden": hidden, "layers": layers, "members": members,
                "frame_stack": frame_stack, "steps": steps, "warmup": warmup, "obs_size": obs_size,
                "engine": engine, "threads": threads}
    cmd = [sys.executable, "-c", "import sys; from deploy.robot.policy_bench import child; sys.exit(child(sys.argv[1:]))",
           json.dumps(settings), "" if cpu is None else str(cpu)]
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout_s, cwd=root)
    if out.returncode != 0:
        raise RuntimeError(f"benchmark subprocess failed ({out.returncode}): {out.stderr[-2000:]}")
    res = json.loads(out.stdout.strip().splitlines()[-1])
    res.update({"threads": threads, "cpu": cpu})
    return res


def child(argv: list[str]) -> int:
    """The benchmark's subprocess: argv = [settings as JSON (bench_here's keywords), cpu or '']:
    pin to the core, time, print one JSON line."""
    settings, cpu = json.loads(argv[0]), argv[1] if len(argv) > 1 else ""
    if cpu and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {int(cpu)})
    res = bench_here(**settings)
    res["threads_env"] = {v: os.environ.get(v) for v in THREAD_VARS[:3]}
    print(json.dumps(res))
    return 0
