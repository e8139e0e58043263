"""A short simulation run (`ttmjx sim`): the scripted striker plays n throws on one backend."""
from __future__ import annotations

import time

import jax
import numpy as np

from ttmjx.world import backends, thrower
from ttmjx.world.config import World


def run(cfg: World, backend: str, n: int, seed: int) -> dict:
    from ttmjx.tools import striker
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    key = jax.random.PRNGKey(seed)
    t0 = time.perf_counter()
    be = backends.Backend(cfg, backend)
    th = thrower.sample_throws(key, cfg, n)
    traj = be.rollout_one(striker.striker_policy(cfg), None, key, th, np.zeros((n, 2), np.float32))
    hit = np.asarray(traj.hit)
    return {"backend": backend, "distribution": cfg.throws.name, "throws": n,
            "hit_rate": float(hit.mean()), "return_rate": float(np.asarray(traj.on_opponent).mean()),
            "net_rate": float(np.asarray(traj.net).mean()),
            "mean_steps": float(np.asarray(traj.valid).sum(1).mean()),
            "seconds": time.perf_counter() - t0}
