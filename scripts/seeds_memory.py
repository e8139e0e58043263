"""Memory of one seeds-together RL epoch at `--scale full` (XLA's compile-time memory analysis,
on whatever device JAX uses: no training is run), with the restart's lax.cond predicate shared by
the seeds (resumable.any_seed, as built) and per seed (vmap's select):
    python scripts/seeds_memory.py es 5"""
import sys

import jax

from eval import baselines
from training.baselines import agents, resumable
from training.baselines import env as benv

method, seeds = sys.argv[1], int(sys.argv[2])
cfg = baselines.method_config(method, "full", 0, "/tmp/seeds_memory")
mod = agents._method(method)
sched = agents.schedule(cfg)
one = jax.eval_shape(lambda: mod.initial_state(cfg, sched.num_timesteps, sched.num_evals))
stacked = jax.tree.map(lambda x: jax.ShapeDtypeStruct((seeds,) + x.shape, x.dtype), one)
print(f"{jax.devices()[0].platform}: {method}, {seeds} seeds, state {sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(stacked)) / 2**30:.2f} GiB", flush=True)
for name, pred in (("shared predicate (built)", resumable.any_seed), ("per-seed predicate (select)", lambda p: p)):
    benv.any_seed = pred
    mod._parts.cache_clear()   # a fresh epoch function: jax caches a function's trace
    loop = mod.schedule(cfg, sched.num_timesteps, sched.num_evals, seeds=True).loop
    m = loop.epoch.lower(stacked).compile().memory_analysis()
    print(f"{name}: temporaries {m.temp_size_in_bytes / 2**30:.2f} GiB, arguments {m.argument_size_in_bytes / 2**30:.2f} GiB, "
          f"outputs {m.output_size_in_bytes / 2**30:.2f} GiB", flush=True)
