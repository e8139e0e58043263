"""How many constraint-solver iterations this scene needs, and what smaller caps change
(docs/BENCHMARKS.md, "The constraint solver's caps"). B thrower throws of PRESET, the robot held,
one episode each:

* MuJoCo C (plain mj_step): the solver's iterations per physics step and its line-search
  evaluations, with MuJoCo's default caps (100, 50);
* MJX on this CPU (its `solve` patched to report its iteration count, which MJX does not write
  back): the iterations per world and step, and over the batch (the batch's while loop runs to
  its slowest world), at the default caps and at each CAPS pair, with every ball's largest
  distance from the default caps' track.

    python scripts/dev/solver_iterations.py [--preset paper-sim] [--throws 64] [--caps 10,8 8,4]
"""
import argparse
import inspect
import json
import os
import sys

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from training.runconfig import preset  # noqa: E402
from ttmjx.world import ballphysics, scene, thrower  # noqa: E402
from ttmjx.world.backends import Backend, _quat_rotate  # noqa: E402
from ttmjx.world.env import uniform_goals  # noqa: E402


def report_mjx_iterations():
    """Make MJX's solve write its iteration count into data._impl.solver_niter."""
    import mujoco.mjx._src.solver as solver
    src = inspect.getsource(solver.solve)
    src = src.replace("'_impl.efc_force': ctx.efc_force,",
                      "'_impl.efc_force': ctx.efc_force, '_impl.solver_niter': ctx.solver_niter,")
    assert "solver_niter': ctx" in src, "MJX's solve changed: update this patch"
    exec(compile(src, solver.__file__, "exec"), solver.__dict__)   # forward.py calls solver.solve


def c_counts(world, states) -> dict:
    """MuJoCo C's iterations and line-search evaluations per physics step, over every throw."""
    m = scene.model(world, fluid=True)
    d = mujoco.MjData(m)
    nit, nev = [], []
    for b in range(states.qpos.shape[0]):
        d.qpos[:], d.qvel[:], d.ctrl[:] = (np.asarray(x[b]) for x in (states.qpos, states.qvel, states.target))
        for _ in range(world.horizon * world.substeps):
            mujoco.mj_step(m, d)
            n = int(d.solver_niter[0])
            nit.append(n)
            nev.append(max((d.solver[i].neval for i in range(min(n, len(d.solver)))), default=0))
    return {"iterations_max": max(nit), "iterations_hist": np.bincount(nit).tolist(),
            "line_search_evaluations_max": max(nev)}


def mjx_episode(world, states):
    """(ball [B, T, 3], iterations [B, T]) of one held-robot episode on MJX at world's caps."""
    from mujoco import mjx
    be = Backend(world, "mjx")
    ph, lay = be.physics, be.physics.lay
    bq, bv = lay.ball_qpos, lay.ball_qvel

    def control_step(qpos, qvel, ctrl):
        def substep(d, c):
            vel, spin = d.qvel[bv:bv + 3], _quat_rotate(d.qpos[bq + 3:bq + 7], d.qvel[bv + 3:bv + 6])
            force, torque = ballphysics.air_force_torque(vel, spin, world.ball)
            xfrc = jnp.zeros_like(d.xfrc_applied).at[ph.ball_body].set(jnp.concatenate([force, torque]))
            d = mjx.step(ph.mx, d.replace(ctrl=c, xfrc_applied=xfrc))
            return d, (d.qpos[bq:bq + 3], d._impl.solver_niter)
        d, ys = jax.lax.scan(substep, ph._data0.replace(qpos=qpos, qvel=qvel),
                             jnp.broadcast_to(ctrl, (world.substeps, 8)))
        return d.qpos, d.qvel, ys
    step = jax.jit(jax.vmap(control_step))
    qpos, qvel, balls, iters = states.qpos, states.qvel, [], []
    for _ in range(world.horizon):
        qpos, qvel, (ball, it) = step(qpos, qvel, states.target)
        balls.append(np.asarray(ball)), iters.append(np.asarray(it))
    return np.concatenate(balls, 1), np.concatenate(iters, 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="paper-sim")
    ap.add_argument("--throws", type=int, default=64)
    ap.add_argument("--caps", nargs="*", default=["10,8", "8,4"], help="iterations,line-search pairs")
    a = ap.parse_args()
    report_mjx_iterations()
    world = preset(a.preset).world.with_solver_caps(100, 50)
    throws = thrower.sample_throws(jax.random.key(1), world, a.throws)
    goals = uniform_goals(jax.random.key(2), a.throws, world.table, 0.1)
    states = Backend(world, "c").reset(jax.random.key(3), throws, goals)
    out = {"preset": a.preset, "throws": a.throws, "c_at_100_50": c_counts(world, states)}
    ref, it = mjx_episode(world, states)
    out["mjx_at_100_50"] = {"iterations_max": int(it.max()), "steps_iterating_per_world": float((it > 0).mean()),
                            "steps_iterating_in_the_batch": float((it.max(0) > 0).mean())}
    for caps in a.caps:
        c = tuple(int(x) for x in caps.split(","))
        ball, _ = mjx_episode(world.with_solver_caps(*c), states)
        out[f"mjx_at_{c[0]}_{c[1]}_ball_max_diff_m"] = float(np.linalg.norm(ball - ref, axis=-1).max())
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
