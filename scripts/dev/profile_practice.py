"""Time the pieces of one practice round of a preset on this machine (GPU: MJX).

    python scripts/dev/profile_practice.py paper-sim
Prints one JSON line per piece: seconds per call after a warm-up call.
"""
import json
import sys
import time

import jax

from training.practice import practice_policy
from training.runconfig import preset
from training.trainer import Run


def timed(name, fn, *args, reps=3):
    out = fn(*args)
    jax.block_until_ready(out)
    t0 = time.perf_counter()
    for _ in range(reps):
        out = fn(*args)
        jax.block_until_ready(out)
    dt = (time.perf_counter() - t0) / reps
    print(json.dumps({"piece": name, "seconds": round(dt, 4)}), flush=True)
    return out


def main(name):
    import dataclasses

    from ttmjx.world import thrower
    from ttmjx.world.env import uniform_goals
    cfg = dataclasses.replace(preset(name), demos=256, run_dir=f"/tmp/prof_{name}")
    run = Run(cfg, progress=False)
    ck = run.initial()
    pr = run.practice
    w, m = cfg.world, cfg.episodes_per_ssp
    key = jax.random.PRNGKey(0)
    for n in (m, 16 * m):
        f = jax.jit(lambda k, n=n: thrower.sample_throws(k, w, n))
        timed(f"sample_throws[{n}]", f, key)
    throws = thrower.sample_throws(key, w, m)
    goals = uniform_goals(key, m, w.table)
    roll = jax.jit(run.backend.rollout_fn(practice_policy(cfg.policy, cfg.train), members=cfg.train.members))
    timed(f"rollout[{m}]", roll, ck.state.params, key, throws, goals)
    timed(f"train_loop[{cfg.steps_between_ssp}]", pr.train_loop, ck.state, ck.cache, key)
    th = pr.round_throws(key, 0)
    timed("fused_iteration", pr.iteration, ck.state, ck.cache, key, th)


if __name__ == "__main__":
    for n in sys.argv[1:]:
        main(n)
