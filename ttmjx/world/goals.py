"""Goals and how reaching them is scored: the one uniform goal sampler, the five-goal protocol
and the one goal-metrics function, used by practice, evaluation and the robot runner alike.

Goals and landings are (x, y) on the table top in the table frame (ttmjx.world.config): the
opponent's half is 0 <= x <= half_length, |y| <= half_width. Numpy-only at import; functions that
must run under jit take xp=jax.numpy.
"""
from __future__ import annotations

import numpy as np

from ttmjx.world.config import Table

# The five evaluation goals (the paper's Figure 1c shows five targets spread over the
# opponent's half; its exact coordinates are not published). Ours, in the table frame
# (x from the net toward the opponent's end line, y to the robot's left):
FIVE_GOALS = {
    "A": (0.35, 0.45),    # short, left
    "B": (0.35, -0.45),   # short, right
    "C": (0.70, 0.0),     # centre
    "D": (1.05, 0.45),    # deep, left
    "E": (1.05, -0.45),   # deep, right
}
RADII = (0.30, 0.20)      # the paper's success radii (m)


def goals_from_unit(u, table: Table, xp=np):
    """[n, 2] uniform numbers in [0, 1) -> [n, 2] goals uniform over the opponent's half."""
    return xp.stack([u[:, 0] * table.half_length, (2 * u[:, 1] - 1) * table.half_width], 1)


def uniform_goals(key, n: int, table: Table):
    """[n, 2] goals uniform over the opponent's half from a JAX key (jittable; n static). The
    draw practice, evaluation and `ttmjx robot run --goals uniform` share."""
    import jax
    import jax.numpy as jnp
    return goals_from_unit(jax.random.uniform(key, (n, 2)), table, jnp)


def five_goals(per_goal: int) -> tuple[np.ndarray, list[str]]:
    """[5 * per_goal, 2] goals A..E, each repeated per_goal times in a row, and their names."""
    names = [n for n in FIVE_GOALS for _ in range(per_goal)]
    return np.array([FIVE_GOALS[n] for n in names], np.float32), names


def goal_stats(landing, goal, hit, xp=np) -> dict:
    """Goal-reaching statistics of B attempts as arrays: landing [B, 2] (NaN where nothing
    landed), goal [B, 2], hit [B] bool.

    within_30cm / within_20cm: fraction of all B attempts that were hit and landed within the
    radius (a ball not hit is a miss); mean_dist: mean distance over hit balls that landed (NaN
    if none); hit_rate: fraction hit."""
    dist = xp.linalg.norm(landing - goal, axis=-1)
    ok = hit & xp.isfinite(dist)
    d = xp.where(ok, dist, xp.inf)
    n_ok = xp.sum(ok)
    mean_dist = xp.where(n_ok > 0, xp.sum(xp.where(ok, dist, 0.0)) / xp.maximum(n_ok, 1), xp.nan)
    return {"within_30cm": xp.mean(d <= RADII[0]), "within_20cm": xp.mean(d <= RADII[1]),
            "mean_dist": mean_dist, "hit_rate": xp.mean(hit)}


def goal_metrics(landing, goal, hit) -> dict:
    """goal_stats of B attempts as Python floats (float64 arithmetic), plus the goal count."""
    landing, goal, hit = np.asarray(landing, np.float64), np.asarray(goal, np.float64), np.asarray(hit, bool)
    if landing.shape != goal.shape or landing.ndim != 2 or landing.shape[1] != 2:
        raise ValueError(f"landing {landing.shape} and goal {goal.shape} must both be [B, 2]")
    if hit.shape != (len(goal),):
        raise ValueError(f"hit has shape {hit.shape}, expected ({len(goal)},)")
    return {**{k: float(v) for k, v in goal_stats(landing, goal, hit).items()}, "goals": int(len(goal))}


def per_goal_metrics(landing, goal, hit, names: list[str]) -> dict:
    """goal_metrics for each named goal, in order of first appearance."""
    names = np.asarray(names)
    return {n: goal_metrics(np.asarray(landing)[names == n], np.asarray(goal)[names == n],
                            np.asarray(hit)[names == n]) for n in dict.fromkeys(names.tolist())}
