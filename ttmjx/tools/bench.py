"""Throughput of the simulated world (`ttmjx bench`): physics steps and throws per second."""
from __future__ import annotations

import time

import jax
import mujoco
import numpy as np

from ttmjx.world import backends
from ttmjx.world.config import World


def _throws(cfg: World, n: int, seed: int):
    from ttmjx.world import thrower
    return thrower.sample_throws(jax.random.PRNGKey(seed), cfg, n)


def raw_rollout_rate(cfg: World, batch: int, nthread: int | None = None, nstep: int | None = None) -> float:
    """Physics steps/s of plain mujoco.rollout on the same model: one call, whole episodes,
    robot holding its home pose and the ball thrown, no task logic."""
    phys = backends.CPhysics(cfg, nthread)
    be = backends.Backend(cfg, "c", nthread)
    th = _throws(cfg, batch, 0)
    st = be.reset(jax.random.PRNGKey(0), th, np.zeros((batch, 2)))
    init = phys.initial_state(np.asarray(st.qpos, np.float64), np.asarray(st.qvel, np.float64))
    nstep = nstep or cfg.horizon * cfg.substeps
    ctrl = np.repeat(np.asarray(st.target, np.float64)[:, None], nstep, 1)
    phys.pool.rollout(phys.m, phys.datas, init[:, :], ctrl[:, :10], nstep=10)  # warm the pool
    t0 = time.perf_counter()
    phys.pool.rollout(phys.m, phys.datas, init, ctrl, nstep=nstep)
    dt = time.perf_counter() - t0
    phys.close()
    return batch * nstep / dt


def task_rate(cfg: World, backend: str, batch: int, repeats: int = 2, nthread: int | None = None) -> dict:
    """Full rollouts (thrower, task logic, events, a policy) on `backend`: returns compile_s,
    physics_steps_per_s (physics steps actually simulated / s) and throws_per_s."""
    be = backends.Backend(cfg, backend, nthread)
    policy = backends.hold_policy()
    th = _throws(cfg, batch, 0)
    goals = np.zeros((batch, 2), np.float32)
    t0 = time.perf_counter()
    tr = be.rollout_one(policy, None, jax.random.PRNGKey(0), th, goals)
    jax.block_until_ready(tr.obs)
    first = time.perf_counter() - t0
    times, steps = [], 0
    for r in range(repeats):
        t0 = time.perf_counter()
        tr = be.rollout_one(policy, None, jax.random.PRNGKey(r + 1), th, goals)
        jax.block_until_ready(tr.obs)
        times.append(time.perf_counter() - t0)
    # A host backend stops once every throw has ended; a traceable one runs the full horizon.
    t_run = cfg.horizon if be.kind.traceable else int(np.asarray(tr.valid).any(0).sum())
    steps = batch * t_run * cfg.substeps
    best = min(times)
    return {"backend": backend, "batch": batch, "compile_s": max(first - best, 0.0),
            "physics_steps_per_s": steps / best, "throws_per_s": batch / best,
            "control_steps": t_run, "seconds_per_rollout": best}


def bench(cfg: World, backend: str, batch: int, nthread: int | None = None) -> dict:
    out = task_rate(cfg, backend, batch, nthread=nthread)
    kind = backends.backend_kind(backend)
    out["device"] = kind.device(nthread)
    out["mujoco"] = mujoco.__version__
    if not kind.traceable:          # MuJoCo C: against mujoco.rollout alone
        out["rollout_baseline_steps_per_s"] = raw_rollout_rate(cfg, batch, nthread)
        out["fraction_of_baseline"] = out["physics_steps_per_s"] / out["rollout_baseline_steps_per_s"]
    return out
