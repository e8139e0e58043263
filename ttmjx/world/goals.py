"""Goals and how reaching them is scored: the one uniform goal sampler, the five-goal protocol
and the one goal-metrics function, used by practice, evaluation and the robot runner alike.

Success is strict: the ball was hit, its first bounce after the hit was on the
opponent's half, and that bounce is within 30 (20) cm of the goal (`scored_distance`).

Goals and landings are (x, y) on the table top in the table frame (ttmjx.world.config): the
opponent's half is 0 <= x <= half_length, |y| <= half_width. Numpy only (the robot side uses it);
functions that must run under jit take xp=jax.numpy, and the draw from a JAX key is
ttmjx.world.env.uniform_goals.
"""
from __future__ import annotations

import math

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


# Goal regions of the diagnostics (ttmjx report, the run's metrics): thirds of the half's depth
# from the net, and the band within EDGE_BAND of its side and end lines (the paper: goals "less
# than 20cm from the edges"). The thirds partition the half; the edges overlap them.
GOAL_REGIONS = ("near", "middle", "far", "edges")
EDGE_BAND = 0.2


def goal_regions(goal, table: Table, xp=np):
    """[4, B] bool: which of GOAL_REGIONS each goal [B, 2] lies in (a goal off the half, by the
    practice goals' margin, falls in the third of its depth and in the edges)."""
    x, y = goal[:, 0], goal[:, 1]
    third = table.half_length / 3
    edges = (xp.abs(y) > table.half_width - EDGE_BAND) | (x > table.half_length - EDGE_BAND)
    return xp.stack([x < third, (x >= third) & (x < 2 * third), x >= 2 * third, edges])


def region_success(landing, goal, hit, on_opponent, table: Table, xp=np, counted=None):
    """[4] within-30-cm success over the attempts whose goal lies in each of GOAL_REGIONS (NaN
    for a region without attempts); counted [B] bool as goal_stats."""
    ok = scored_distance(landing, goal, hit, on_opponent, xp) <= RADII[0]
    return success_within(ok, goal_regions(goal, table, xp), xp, counted)


def success_within(ok, masks, xp=np, counted=None):
    """[K] share of successes ok [B] among the counted attempts of each group masks [K, B]
    (NaN for an empty group): the per-region and per-member success."""
    w = xp.ones(ok.shape, bool) if counted is None else counted
    masks = masks & w[None]
    n = masks.sum(-1)
    return xp.where(n > 0, (masks & ok[None]).sum(-1) / xp.maximum(n, 1), xp.nan)


def member_success(landing, goal, hit, on_opponent, members: int, xp=np, counted=None):
    """[members] within-30-cm success of each ensemble member over its own block of attempts: an
    ensemble plays B attempts in `members` contiguous blocks of ceil(B / members) (the last may be
    short), one per member (ttmjx.world.backends.batched_policy); counted [B] bool as goal_stats.
    NaN for a member without attempts."""
    ok = scored_distance(landing, goal, hit, on_opponent, xp) <= RADII[0]
    b = ok.shape[0]
    block = -(-b // members)
    return success_within(ok, xp.arange(b)[None] // block == xp.arange(members)[:, None], xp, counted)


def goals_from_unit(u, table: Table, xp=np, margin: float = 0.0):
    """[n, 2] uniform numbers in [0, 1) -> [n, 2] goals uniform over the opponent's half, extended
    `margin` metres beyond its end line and both side lines (never over the net): x in
    [0, half_length + margin], |y| <= half_width + margin. margin=0: the half itself."""
    hl, hw = table.half_length + margin, table.half_width + margin
    return xp.stack([u[:, 0] * hl, (2 * u[:, 1] - 1) * hw], 1)


def off_half(goals, table: Table) -> np.ndarray:
    """[B] bool: goal [B, 2] lies outside the opponent's half (NaN counts as outside)."""
    g = np.asarray(goals, np.float64)
    inside = (g[:, 0] >= 0) & (g[:, 0] <= table.half_length) & (np.abs(g[:, 1]) <= table.half_width)
    return ~inside


def five_goals(per_goal: int) -> tuple[np.ndarray, list[str]]:
    """[5 * per_goal, 2] goals A..E, each repeated per_goal times in a row, and their names."""
    names = [n for n in FIVE_GOALS for _ in range(per_goal)]
    return np.array([FIVE_GOALS[n] for n in names], np.float32), names


def scored_distance(landing, goal, hit, on_opponent, xp=np):
    """[B] distance (m) from the goal [B, 2] of each strict landing, inf for the others: a landing
    [B, 2] counts when the ball was hit (hit [B]) and its first bounce after the hit was on the
    opponent's half (on_opponent [B], the events' `on_opponent`). A ball landing near a goal but
    off the table, or on the robot's own half, is a miss. `d <= radius` is a success."""
    ok = xp.asarray(hit, bool) & xp.asarray(on_opponent, bool)
    dist = xp.linalg.norm(landing - goal, axis=-1)
    return xp.where(ok & xp.isfinite(dist), dist, xp.inf)


def goal_stats(landing, goal, hit, on_opponent, xp=np, counted=None) -> dict:
    """Goal-reaching statistics of B attempts as arrays: landing [B, 2] (NaN where nothing
    landed), goal [B, 2], hit [B] bool, on_opponent [B] bool (scored_distance: strict success);
    counted [B] bool (None: all) marks the attempts the statistics are over.

    within_30cm / within_20cm: fraction of all attempts that succeed; hit_rate: fraction hit;
    on_table_rate: fraction whose first bounce after the hit was on the opponent's half;
    mean_dist: mean distance to the goal over those on-table landings (NaN if none)."""
    d = scored_distance(landing, goal, hit, on_opponent, xp)
    w = xp.ones(d.shape, bool) if counted is None else counted
    n = xp.maximum(xp.sum(w), 1)
    ok = xp.isfinite(d) & w
    n_ok = xp.sum(ok)
    mean_dist = xp.where(n_ok > 0, xp.sum(xp.where(ok, d, 0.0)) / xp.maximum(n_ok, 1), xp.nan)
    share = lambda x: xp.sum(x & w) / n  # noqa: E731
    return {"within_30cm": share(d <= RADII[0]), "within_20cm": share(d <= RADII[1]),
            "mean_dist": mean_dist, "hit_rate": share(xp.asarray(hit, bool)), "on_table_rate": share(ok)}


def landed_mean_distance(landing, goal, hit) -> float:
    """Mean distance (m) from the goal [B, 2] over every hit ball that came down, wherever its
    landing [B, 2] is (either half, or where it fell through table height beside the table):
    the paper's "distance to goal", which also counts the balls that miss the table. NaN if no
    hit ball came down."""
    d = np.linalg.norm(np.asarray(landing, np.float64) - np.asarray(goal, np.float64), axis=-1)
    ok = np.asarray(hit, bool) & np.isfinite(d)
    return float(d[ok].mean()) if ok.any() else math.nan


def goal_metrics(landing, goal, hit, on_opponent) -> dict:
    """goal_stats of B attempts as Python floats (float64 arithmetic), plus mean_dist_landed
    (landed_mean_distance) and the goal count."""
    landing, goal = np.asarray(landing, np.float64), np.asarray(goal, np.float64)
    hit, on_opponent = np.asarray(hit, bool), np.asarray(on_opponent, bool)
    if landing.shape != goal.shape or landing.ndim != 2 or landing.shape[1] != 2:
        raise ValueError(f"landing {landing.shape} and goal {goal.shape} must both be [B, 2]")
    for name, x in (("hit", hit), ("on_opponent", on_opponent)):
        if x.shape != (len(goal),):
            raise ValueError(f"{name} has shape {x.shape}, expected ({len(goal)},)")
    stats = goal_stats(landing, goal, hit, on_opponent)
    return {**{k: float(v) for k, v in stats.items()},
            "mean_dist_landed": landed_mean_distance(landing, goal, hit), "goals": int(len(goal))}


def per_goal_metrics(landing, goal, hit, on_opponent, names: list[str]) -> dict:
    """goal_metrics for each named goal, in order of first appearance."""
    names = np.asarray(names)
    arrays = [np.asarray(x) for x in (landing, goal, hit, on_opponent)]
    return {n: goal_metrics(*(x[names == n] for x in arrays)) for n in dict.fromkeys(names.tolist())}
