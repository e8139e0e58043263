"""Memory of one seeds-together RL epoch at `--scale full` (XLA's compile-time memory analysis,
agents.program_memory, on whatever device JAX uses: no training is run), with the restart's
lax.cond predicate shared by the seeds (resumable.any_seed, as built) and per seed (vmap's select):
    python scripts/dev/seeds_memory.py es 5"""
import sys

import jax

from eval import baselines
from training.baselines import agents
from training.baselines import env as benv
from training.baselines import resumable

method, seeds = sys.argv[1], int(sys.argv[2])
cfg = baselines.method_config(method, "full", 0, "/tmp/seeds_memory")
print(f"{jax.devices()[0].platform}: {method}, {seeds} seeds", flush=True)
for name, pred in (("shared predicate (built)", resumable.any_seed), ("per-seed predicate (select)", lambda p: p)):
    benv.any_seed = pred
    agents._method(method)._parts.cache_clear()   # a fresh epoch function: jax caches a function's trace
    m = agents.program_memory(cfg, seeds)
    print(f"{name}: temporaries {m.temp_size_in_bytes / 2**30:.2f} GiB, arguments {m.argument_size_in_bytes / 2**30:.2f} GiB, "
          f"outputs {m.output_size_in_bytes / 2**30:.2f} GiB", flush=True)
