"""Seconds of three consecutive 2-seed evaluations of the tiny preset on MuJoCo C (32 goals):
the first compiles the rollout, the later ones must reuse it (docs/BENCHMARKS.md: each
evaluation compiled it again while make_policy built a new Policy per call).

    python scripts/dev/eval_reuse.py
"""
import time

import jax
import numpy as np

from eval.evaluate import uniform_runs
from models.normalizer import identity_normalizer
from models.policy import init_ensemble
from training import runconfig
from ttmjx.world.backends import Backend

cfg = runconfig.tiny()
backend = Backend(cfg.world, "c")
one = init_ensemble(jax.random.PRNGKey(0), cfg.policy, identity_normalizer(cfg.policy.obs_size), 2)
params = jax.tree.map(lambda x: np.stack([x, x]), one)
keys = jax.random.split(jax.random.PRNGKey(0), 2)
for i in range(3):
    t0 = time.perf_counter()
    uniform_runs(cfg.world, cfg.policy, params, backend, keys, 32, 2)
    print(f"evaluation {i}: {time.perf_counter() - t0:.2f} s")
