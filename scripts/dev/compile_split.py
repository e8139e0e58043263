"""How much of an RL program's XLA:CPU compile is the MJX world step: lowering and compile
times, compilation cache off, of the tiny world's GoalEnv reset and step (one env, vmapped over
the tiny SAC cell's envs, 8 steps in a scan), to set beside the RL tests' program compiles
(docs/BENCHMARKS.md, "The test loop").
Default compile options, as the RL programs have (the fusion-emitter option of
ttmjx.tools.calibration is for its own program only).

    .venv/bin/python scripts/dev/compile_split.py
"""
import json
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from eval import baselines  # noqa: E402
from training.baselines.env import GoalEnv  # noqa: E402


def compile_seconds(f, *args) -> dict:
    """{lower_s, compile_s} of jit(f) on args; nothing cached, so each is a cold compile."""
    t0 = time.perf_counter()
    lowered = jax.jit(f).lower(*args)
    t1 = time.perf_counter()
    lowered.compile()
    return {"lower_s": round(t1 - t0, 1), "compile_s": round(time.perf_counter() - t1, 1)}


def main() -> None:
    jax.config.update("jax_enable_compilation_cache", False)
    cfg = baselines.method_config("sac", "tiny", 0, "/tmp/compile_split_run", trajectories=2)
    env, key, n = GoalEnv(cfg.run.world, cfg.reward), jax.random.PRNGKey(0), cfg.sac.num_envs
    one, many = jax.jit(env.reset)(key), jax.jit(jax.vmap(env.reset))(jax.random.split(key, n))
    a1, an = jnp.zeros(env.action_size), jnp.zeros((n, env.action_size))

    def unroll(s, a):   # the shape of an RL program's env part: steps under a scan
        return jax.lax.scan(lambda c, _: (jax.vmap(env.step)(c, a), None), s, None, length=8)[0]

    out = {}
    for name, f, args in [("reset, one env", env.reset, (key,)), ("step, one env", env.step, (one, a1)),
                          (f"step, vmapped over {n} envs", jax.vmap(env.step), (many, an)),
                          (f"8 steps in a scan, {n} envs", unroll, (many, an))]:
        out[name] = compile_seconds(f, *args)
        print(name, out[name], flush=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
