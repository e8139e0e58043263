"""Goals for the episodes of a `ttmjx robot run` session (`session_goals`), from a --goals value
in the one grammar `ttmjx eval` reads too (ttmjx.world.goalspec): N uniform goals, 'uniform'
(--n of them), 'five', inline 'x,y;x,y' or a goal file.

A goal is (x, y) in metres on the opponent's half (docs/DESIGN.md frame). One goal per episode;
`episode_goals` repeats each goal (the paper's five-goal evaluation: 5 goals x 5 attempts). The
five goals and the uniform draw are ttmjx.world.goals', as practice and evaluation use them.
"""
from __future__ import annotations

import numpy as np

from ttmjx.world.config import Table
from ttmjx.world.goalfile import check_goals, is_goal_file, read_goal_file
from ttmjx.world.goals import five_goals, goals_from_unit
from ttmjx.world.goalspec import goal_spec, parse_goals  # noqa: F401  (parse_goals: deploy.robot's API)


def goals_from_arg(arg: str, table: Table = Table()) -> np.ndarray:
    """A goal file (ttmjx.world.goalfile: .csv with a header x,y, or .npy), or an inline spec
    'x,y;x,y' (a spec that names a file, by its extension or a path separator, must be one: a
    missing file is said so)."""
    return read_goal_file(arg, table) if is_goal_file(arg) else parse_goals(arg)


def check_goal_region(goals, table: Table = Table()) -> np.ndarray:
    """[N, 2] goals, each on the opponent's half; ValueError names the first one outside."""
    return check_goals(goals, "goals", table)


def episode_goals(goals, repeat: int = 1) -> np.ndarray:
    """[N * repeat, 2]: each goal `repeat` times in a row (A A A B B B ...)."""
    if repeat < 1:
        raise ValueError(f"repeat={repeat}, expected >= 1")
    return np.repeat(check_goals(goals), repeat, axis=0)


def uniform_session_goals(n: int, seed: int = 0, table: Table = Table()) -> np.ndarray:
    """[n, 2] float32 goals uniform over the opponent's half: ttmjx.world.goals.goals_from_unit
    of numpy's default_rng(seed) uniform numbers (the robot side draws without JAX)."""
    return goals_from_unit(np.random.default_rng(seed).uniform(size=(n, 2)), table).astype(np.float32)


def session_goals(spec: str, n: int, seed: int = 0, table: Table = Table()) -> np.ndarray:
    """[N, 2] goals of a `robot run` session, all on the opponent's half, from a --goals value
    (goal_spec): 'five' (goals A..E, n attempts each in a row), 'uniform' (n goals once each,
    uniform_session_goals), N (N uniform goals), inline goals or a goal file (each goal n times in
    a row)."""
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    g = goal_spec(spec, table)
    if g.kind == "five":
        return five_goals(n)[0]
    if g.kind == "uniform" and g.count is None:
        return uniform_session_goals(n, seed, table)
    points = uniform_session_goals(g.count, seed, table) if g.kind == "uniform" else g.goals
    return episode_goals(points, n)
