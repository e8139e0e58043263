"""Goal-reaching metrics as in the paper: % of balls within 30 cm and 20 cm of the goal, mean
distance to the goal over hit balls, hit rate; 200 uniform goals or the fixed five-goal
protocol."""
from __future__ import annotations

import numpy as np

from ttmjx.world import env
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


def uniform_goals(key, n: int, table: Table) -> np.ndarray:
    """[n, 2] goals uniform over the opponent's half (the same draw practice uses), as numpy."""
    return np.asarray(env.uniform_goals(key, n, table), np.float32)


def five_goals(per_goal: int) -> tuple[np.ndarray, list[str]]:
    """[5 * per_goal, 2] goals A..E repeated per_goal times each, and their names."""
    names = [n for n in FIVE_GOALS for _ in range(per_goal)]
    return np.array([FIVE_GOALS[n] for n in names], np.float32), names


def goal_metrics(landing, goal, hit) -> dict:
    """Metrics of B attempts. landing [B, 2] (NaN where nothing was hit), goal [B, 2], hit [B].

    A ball that was not hit counts as a miss for the within-X metrics; mean_dist is over hit
    balls only and NaN when nothing was hit (as in the paper's table)."""
    landing, goal, hit = np.asarray(landing, np.float64), np.asarray(goal, np.float64), np.asarray(hit, bool)
    if landing.shape != goal.shape or landing.ndim != 2 or landing.shape[1] != 2:
        raise ValueError(f"landing {landing.shape} and goal {goal.shape} must both be [B, 2]")
    dist = np.linalg.norm(landing - goal, axis=1)
    ok = hit & np.isfinite(dist)
    d = np.where(ok, dist, np.inf)
    return {"within_30cm": float(np.mean(d <= 0.30)), "within_20cm": float(np.mean(d <= 0.20)),
            "mean_dist": float(dist[ok].mean()) if ok.any() else float("nan"),
            "hit_rate": float(hit.mean()), "goals": int(len(goal))}


def per_goal_metrics(landing, goal, hit, names: list[str]) -> dict:
    """goal_metrics for each named goal."""
    names = np.asarray(names)
    return {n: goal_metrics(np.asarray(landing)[names == n], np.asarray(goal)[names == n],
                            np.asarray(hit)[names == n]) for n in dict.fromkeys(names.tolist())}
