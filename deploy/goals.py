"""Goals for the episodes of a session: from the command line, a file or a list, the five-goal
protocol or uniform over the opponent's half (`session_goals`).

A goal is (x, y) in metres on the opponent's half (docs/DESIGN.md frame). One goal per episode;
`episode_goals` repeats each goal (the paper's five-goal evaluation: 5 goals x 5 attempts). The
five goals and the uniform draw are ttmjx.world.goals', as practice and evaluation use them.
"""
from __future__ import annotations

import json
import os

import numpy as np

from ttmjx.world.config import Table, opponent_half
from ttmjx.world.goals import five_goals, goals_from_unit


def check_goals(goals) -> np.ndarray:
    """[N, 2] finite float32 goals (N >= 1); ValueError names the problem.

    (ttmjx.world.env.check_goals does the same but imports JAX; the runner stays numpy-only.)
    """
    try:
        g = np.asarray(goals, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"goals must be numbers of shape [N, 2] (x, y in metres): {e}") from None
    if g.ndim == 1 and g.shape == (2,):
        g = g[None]
    if g.ndim != 2 or g.shape[1] != 2 or g.shape[0] < 1:
        raise ValueError(f"goals must have shape [N, 2] (x, y in metres), got {g.shape}")
    if not np.all(np.isfinite(g)):
        bad = np.argwhere(~np.isfinite(g))[0]
        raise ValueError(f"goals[{bad[0]}, {bad[1]}] = {g[tuple(bad)]} is not finite")
    return g.astype(np.float32)


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
    return check_goals(goals)


GOAL_FILE_EXTENSIONS = (".json", ".npy", ".csv", ".txt")


def load_goals(path: str) -> np.ndarray:
    """[N, 2] goals from a .json ([[x, y], ...] or {"goals": [...]}), .npy, or .csv/.txt file
    (one 'x,y' per line, '#' comments, an optional header row 'x,y'). Every error names the file."""
    ext = os.path.splitext(path)[1].lower()
    if not os.path.isfile(path):
        raise FileNotFoundError(f"goal file {path!r} does not exist")
    if ext not in GOAL_FILE_EXTENSIONS:
        raise ValueError(f"goal file {path!r}: unknown extension {ext!r}; use .json, .npy, .csv or .txt")
    try:
        if ext == ".json":
            with open(path) as f:
                try:
                    data = json.load(f)
                except ValueError as e:
                    raise ValueError(f"not valid JSON ({e})") from None
            if isinstance(data, dict):
                if "goals" not in data:
                    raise ValueError(f"a JSON object needs a 'goals' key, got keys {sorted(data)}")
                data = data["goals"]
            return check_goals(data)
        if ext == ".npy":
            try:
                data = np.load(path, allow_pickle=False)
            except (ValueError, OSError, EOFError) as e:
                raise ValueError(f"not a plain numeric .npy array ({e})") from None
            return check_goals(data)
        with open(path, errors="replace") as f:
            lines = [ln.split("#")[0].strip() for ln in f]
        lines = [ln for ln in lines if ln]
        if lines and lines[0].replace(" ", "").lower() == "x,y":
            lines = lines[1:]           # the header row eval's goal files carry
        return parse_goals(";".join(lines))
    except UnicodeDecodeError as e:
        raise ValueError(f"goal file {path!r}: not text ({e.reason})") from None
    except ValueError as e:
        raise ValueError(f"goal file {path!r}: {e}") from None


def goals_from_arg(arg: str) -> np.ndarray:
    """A path to an existing goal file, or an inline spec 'x,y;x,y' (a spec that names a goal
    file, by its extension or a path separator, must be one: a missing file is said so)."""
    if os.path.isfile(arg) or os.path.splitext(arg)[1].lower() in GOAL_FILE_EXTENSIONS or os.sep in arg:
        return load_goals(arg)
    return parse_goals(arg)


def check_goal_region(goals, table: Table = Table()) -> np.ndarray:
    """[N, 2] goals, each on the opponent's half; ValueError names the first one outside."""
    g = check_goals(goals)
    (x0, x1), (y0, y1) = opponent_half(table)
    bad = (g[:, 0] < x0) | (g[:, 0] > x1) | (g[:, 1] < y0) | (g[:, 1] > y1)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise ValueError(f"goal {i} = ({g[i, 0]}, {g[i, 1]}) is off the opponent's half "
                         f"x in [{x0}, {x1}], y in [{y0:.4f}, {y1:.4f}]")
    return g


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
        g = episode_goals(goals_from_arg(spec), n)
        if os.path.isfile(spec):
            try:
                return check_goal_region(g, table)
            except ValueError as e:
                raise ValueError(f"goal file {spec!r}: {e}") from None
    return check_goal_region(g, table)
