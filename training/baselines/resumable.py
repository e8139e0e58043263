"""The outer loop of an RL cell whose whole state lives outside the trainer's call (ES: es.py, PPO:
ppo.py): epochs until the budget, the learning curve's policies where brax's loop hands them
out, and an Orbax checkpoint (training/checkpoint.py: checksums, a full disk as one line) of the
state and the curve so far under RUN/<method>_state/, so that a stopped cell resumes where it
stopped and ends bit-for-bit where the uninterrupted cell ends."""
from __future__ import annotations

import dataclasses
import os
import time
from typing import Any, Callable

import jax
import jax.numpy as jnp

from training import checkpoint


@dataclasses.dataclass(frozen=True)
class Loop:
    """One method's epoch and how to read its state."""
    epoch: Callable[[Any], tuple[Any, dict]]   # state -> (state, metrics), jitted
    steps: Callable[[Any], int]                # environment steps run so far
    acting: Callable[[Any], tuple[Any, Any]]   # state -> (normalizer, policy params): a curve point
    unit: int                                  # environment steps per epoch


def state_dir(run_dir: str, method: str) -> str:
    return os.path.join(run_dir, f"{method}_state")


def _tree(state, points: list) -> dict:
    return {"state": state, "points": {str(i): {"steps": jnp.int32(s), "normalizer": n, "policy": p}
                                       for i, (s, n, p) in enumerate(points)}}


def save(directory: str, step: int, state, points: list, cfg_json: dict) -> None:
    """The state and the curve's (steps, normalizer, policy) so far as checkpoint `step`."""
    checkpoint.save(directory, step, _tree(state, points), {**cfg_json, "curve_points": len(points)}, keep=2)


def resume(directory: str, like, like_point, cfg_json: dict) -> tuple[Any, list] | None:
    """(state, points) of the newest checkpoint whose files match their checksums, or None if
    there is none (damaged ones are removed: the run redoes them). `like` and `like_point`: the
    structure of the state and of one point (jax.ShapeDtypeStructs will do). ValueError if it
    was saved with another configuration than `cfg_json`."""
    saved = checkpoint.steps(directory)
    damaged = [s for s in saved if checkpoint.damage(directory, s)]
    if damaged:
        checkpoint.discard(directory, damaged)
    good = [s for s in saved if s not in damaged]
    if not good:
        return None
    saved_cfg = checkpoint.restore_config(directory, good[-1])
    n = saved_cfg.pop("curve_points")
    saved_cfg.pop("checkpoint_format", None)
    if saved_cfg != cfg_json:
        diff = sorted(k for k in set(saved_cfg) | set(cfg_json) if saved_cfg.get(k) != cfg_json.get(k))
        raise ValueError(f"{directory} holds a state of another configuration (differs in {', '.join(diff)}); "
                         f"run with the same settings to resume it, or another --out")
    tree, _ = checkpoint.restore(directory, _tree(like, [(0, *like_point)] * n), good[-1])
    points = [(int(tree["points"][str(i)]["steps"]), tree["points"][str(i)]["normalizer"],
               tree["points"][str(i)]["policy"]) for i in range(n)]
    return tree["state"], points


def run(loop: Loop, directory: str, cfg_json: dict, fresh: Callable[[], Any], num_timesteps: int,
        thresholds: list[int], point_at_zero: bool, point, progress=None, timing: dict | None = None,
        checkpoint_every: int = 1):
    """Epochs from the newest checkpoint in `directory` (or from fresh()) until num_timesteps
    environment steps. point(steps, normalizer, policy) at 0 (point_at_zero) and after the first
    epoch that reaches each of `thresholds` (brax's next_eval_step: one point per epoch at
    most), replayed from the checkpoint for the points before it. A checkpoint at 0, at every
    point, every `checkpoint_every` epochs and at the end. progress(steps, metrics) after every
    epoch (brax's training/sps, training/walltime and the epoch's metrics); timing['epochs']
    gets the same. Returns the final state."""
    timing = {} if timing is None else timing
    like = jax.eval_shape(fresh)
    found = resume(directory, like, jax.eval_shape(loop.acting, like), cfg_json)
    state, points = found if found else (fresh(), [])
    for s, n, p in points:
        point(s, n, p)
    if not found:
        if point_at_zero:
            points.append((0, *loop.acting(state)))
            point(0, *points[-1][1:])
        save(directory, 0, state, points, cfg_json)
    evaluated = len(points) - point_at_zero     # thresholds already passed
    walltime, epochs = 0.0, 0
    while loop.steps(state) < num_timesteps:
        t = time.perf_counter()
        state, metrics = loop.epoch(state)
        metrics = jax.device_get(metrics)
        dt = time.perf_counter() - t
        walltime, epochs, steps = walltime + dt, epochs + 1, loop.steps(state)
        row = {"training/sps": loop.unit / dt, "training/walltime": walltime,
               **{f"training/{k}": float(v) for k, v in metrics.items()}}
        timing.setdefault("epochs", []).append({"env_steps": steps, "sps": row["training/sps"], "walltime": walltime})
        if progress is not None:
            progress(steps, row)
        due = evaluated < len(thresholds) and steps >= thresholds[evaluated]
        if due:
            evaluated += 1
            points.append((steps, *loop.acting(state)))
            point(steps, *points[-1][1:])
        if due or epochs % checkpoint_every == 0 or steps >= num_timesteps:
            save(directory, steps, state, points, cfg_json)
    return state
