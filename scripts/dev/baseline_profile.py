"""Where a PPO cell's environment time goes, piece by piece, on the device JAX sees:
the environment reset as it was (every environment solving its own throw, vmapped, once per
episode) against the throw pool that replaced it (one batch of n x pool throws for `pool`
episodes), and one training-step's worth of environment steps through the wrapper brax trains
on. Prints each piece as soon as it is measured (a call's time limit may cut the rest), then
one JSON line; run on the GPU by scripts/dev/gpu_baselines.sh. Each piece: (first call, compile
included; median of later calls) in seconds.

    python3 scripts/dev/baseline_profile.py [--envs 4000] [--pool 16]
"""
import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp

from eval.baselines import goalseye_base
from training.baselines.env import GoalEnv, wrap_fresh
from ttmjx.world import thrower


def timed(fn, *args, reps=3):
    """(first call incl. compile, median of `reps` later calls) in seconds."""
    t = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t
    runs = []
    for _ in range(reps):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t)
    return round(first, 3), round(sorted(runs)[len(runs) // 2], 4)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--envs", type=int, default=4000)
    ap.add_argument("--pool", type=int, default=16)
    ap.add_argument("--steps", type=int, default=160)
    a = ap.parse_args()
    world = goalseye_base("full").world
    env = GoalEnv(world)
    keys = jax.random.split(jax.random.PRNGKey(0), a.envs)
    out = {"device": str(jax.devices()[0]), "envs": a.envs, "pool": a.pool}

    def record(name, value):
        out[name] = value
        print(f"{name}: {value}", file=sys.stderr, flush=True)

    # before: every environment solves its own throw (vmapped), at every episode end
    record("reset_vmapped_s", timed(jax.jit(jax.vmap(env.reset)), keys))
    # after: n x pool throws in one batch, once per `pool` episodes
    solve = jax.jit(lambda k: thrower.sample_throws(k, world, a.envs * a.pool))
    record("solve_pool_s", timed(solve, keys[0]))
    record("solve_n_s", timed(jax.jit(lambda k: thrower.sample_throws(k, world, a.envs)), keys[0]))
    # the environment alone through brax's training wrapper (ours), zero actions, `steps` steps
    wrapped = wrap_fresh(env, episode_length=world.horizon, pool=a.pool)
    s0 = jax.jit(wrapped.reset)(keys)

    @jax.jit
    def unroll(s):
        return jax.lax.scan(lambda s, _: (wrapped.step(s, jnp.zeros((a.envs, 8))), None), s, None,
                            length=a.steps)[0].reward.sum()
    first, run = timed(unroll, s0, reps=2)
    record("env_unroll_s", (first, run))
    record("env_steps_per_s", round(a.envs * a.steps / run))
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
