"""Goals for the episodes of a session: from the command line, a file or a list, the five-goal
protocol or uniform over the opponent's half (`session_goals`).

A goal is (x, y) in metres on the opponent's half (docs/DESIGN.md frame). One goal per episode;
`episode_goals` repeats each goal (the paper's five-goal evaluation: 5 goals x 5 attempts). The
five goals and the uniform draw are ttmjx.world.goals', as practice and evaluation use them.
"""
from __future__ import annotations

import numpy as np

from ttmjx.world.config import Table
from ttmjx.world.goalfile import check_goals, is_goal_file, read_goal_file
from ttmjx.world.goals import five_goals, goals_from_unit


def parse_goals(spec: str) -> np.ndarray:
    """'x,y' or 'x,y;x,y;...' -> [N, 2]."""
    rows = [r.strip() for r in spec.replace("\n", ";").split(";") if r.strip()]
    if not rows:
        raise ValueError(f"goal spec {spec!r} holds no goals; expected 'x,y' or 'x,y;x,y;...'")
    goals = []
    for r in rows:
        parts = [p for p in r.replace(",", " ").split() if p]
        if len(parts) != 2:
            raise ValueError(f"goal {r!r} in {spec!r} must be two numbers 'x,y'")
        try:
            goals.append([float(p) for p in parts])
        except ValueError as e:
            raise ValueError(f"goal {r!r} in {spec!r} is not two numbers ({e})") from None
    return check_goals(goals, f"goal spec {spec!r}")


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
    """[N, 2] goals of a session, all on the opponent's half: 'five' (goals A..E of
    ttmjx.world.goals.FIVE_GOALS, n attempts each in a row), 'uniform' (n goals,
    uniform_session_goals), or an inline 'x,y;x,y' / goal file (each goal n times in a row)."""
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    if spec == "five":
        g = five_goals(n)[0]
    elif spec == "uniform":
        g = uniform_session_goals(n, seed, table)
    else:
        g = episode_goals(goals_from_arg(spec, table), n)     # a file's goals are checked as it is read
    return check_goal_region(g, table)
