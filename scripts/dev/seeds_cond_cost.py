"""What a per-seed lax.cond predicate costs a seeds-together RL cell: one control step of the RL
environment (training/baselines/env.py wrap_fresh, the world of `--scale full`) for S seeds x N
environments stacked under the seeds' vmap, where no episode ends (159 of every 160 steps),
with the restart's predicate shared by the seeds (resumable.any_seed, as built) and per seed
(vmap turns the cond into a select: every step solves every environment's throw pool and resets
every environment). Prints seconds per step after compiling:
    python scripts/dev/seeds_cond_cost.py SEEDS ENVS POOL [STEPS]      # e.g. 2 64 16 4"""
import sys
import time

import jax
import jax.numpy as jnp

from eval import baselines
from training.baselines import env as benv
from training.baselines import resumable

seeds, envs, pool = (int(a) for a in sys.argv[1:4])
steps = int(sys.argv[4]) if len(sys.argv) > 4 else 4
cfg = baselines.method_config("ppo", "full", 0, "/tmp/seeds_cond_cost")
env = benv.wrap_fresh(benv.GoalEnv(cfg.run.world, cfg.reward), episode_length=cfg.run.world.horizon, pool=pool)
states = [jax.jit(env.reset)(jax.random.split(jax.random.PRNGKey(s), envs)) for s in range(seeds)]
stacked = jax.tree.map(lambda *x: jnp.stack(x), *states)
actions = jnp.zeros((seeds, envs, env.action_size))
print(f"{jax.devices()[0].platform}: {seeds} seeds x {envs} environments, a pool of {pool} throws each", flush=True)
for name, pred in (("shared predicate (built)", resumable.any_seed), ("per-seed predicate (select)", lambda p: p)):
    benv.any_seed = pred

    def run(s, a):   # a new function per setting: jax caches a function's trace
        return jax.lax.scan(lambda s, _: (env.step(s, a), None), s, None, length=steps)[0]
    fn = resumable.over_seeds(run)
    t0 = time.perf_counter()
    jax.block_until_ready(fn(stacked, actions))
    t1 = time.perf_counter()
    jax.block_until_ready(fn(stacked, actions))
    t2 = time.perf_counter()
    print(f"{name}: {(t2 - t1) / steps:.3f} s per control step ({t1 - t0:.1f} s with compiling)", flush=True)
