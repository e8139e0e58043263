"""A user's evaluation goal set from a file (`ttmjx eval RUN --goals FILE`).

Two formats, neither needing pickle: a .csv with a header row naming the columns `x` and `y`
(metres, table frame; other columns are ignored), or a .npy holding a numeric [N, 2] array.
Evaluation goals must lie on the opponent's half (0 <= x <= half_length, |y| <= half_width):
practice may aim beyond the table, evaluation does not.
"""
from __future__ import annotations

import csv
import os

import numpy as np

from ttmjx.world.config import Table
from ttmjx.world.goals import off_half

GOAL_FILE_TYPES = (".csv", ".npy")


def is_goal_file(spec: str) -> bool:
    """`spec` (`ttmjx eval --goals`) names a goal file (by its extension or because it exists),
    not a number of uniform goals or 'five'."""
    if spec == "five" or spec.strip().lstrip("+-").isdigit():
        return False
    return spec.lower().endswith(GOAL_FILE_TYPES) or os.path.exists(spec)


def load_goal_file(path: str, table: Table) -> np.ndarray:
    """[N, 2] float32 goals from `path` (.csv or .npy), N >= 1, finite, on the opponent's half.
    FileNotFoundError or ValueError naming the file and the problem."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in GOAL_FILE_TYPES:
        raise ValueError(f"goal file {path!r}: extension {ext!r}; expected one of {GOAL_FILE_TYPES}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"goal file {path!r} does not exist")
    goals = _read_csv(path) if ext == ".csv" else _read_npy(path)
    return check_eval_goals(goals, table, f"goal file {path!r}")


def check_eval_goals(goals: np.ndarray, table: Table, where: str = "goals") -> np.ndarray:
    """[N, 2] float32 of goals [N, 2]; ValueError names the first bad row (NaN, off the half)."""
    g = np.asarray(goals, np.float64)
    if g.ndim != 2 or g.shape[1] != 2 or g.shape[0] < 1:
        raise ValueError(f"{where}: goals of shape {g.shape}; expected [N, 2] (x, y in metres), N >= 1")
    bad = ~np.all(np.isfinite(g), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{where}: goal {i} = ({g[i, 0]}, {g[i, 1]}) is not finite")
    out = off_half(g, table)
    if out.any():
        i = int(np.argmax(out))
        raise ValueError(f"{where}: goal {i} = ({g[i, 0]}, {g[i, 1]}) is off the opponent's half; expected "
                         f"0 <= x <= {table.half_length:g} and |y| <= {table.half_width:g} (evaluation "
                         f"goals lie on the table)")
    return g.astype(np.float32)


def _read_npy(path: str) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except ValueError as e:     # object arrays need pickle: refused
        raise ValueError(f"goal file {path!r} is not a plain numeric .npy array ({e})") from None
    if not isinstance(a, np.ndarray) or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"goal file {path!r} holds {getattr(a, 'dtype', type(a))}; expected numbers [N, 2]")
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"goal file {path!r} holds an array of shape {a.shape}; expected [N, 2] (x, y)")
    return a


def _read_csv(path: str) -> np.ndarray:
    with open(path, newline="") as f:
        rows = [r for r in csv.reader(f) if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"goal file {path!r} is empty; expected a header row x,y and one goal per row")
    header = [c.strip().lower() for c in rows[0]]
    if "x" not in header or "y" not in header:
        raise ValueError(f"goal file {path!r}: header {rows[0]}; expected a header row naming columns x and y")
    ix, iy = header.index("x"), header.index("y")
    goals = []
    for line, r in enumerate(rows[1:], start=2):
        try:
            goals.append([float(r[ix]), float(r[iy])])
        except (IndexError, ValueError):
            raise ValueError(f"goal file {path!r}, row {line}: {r} does not give numbers x and y") from None
    return np.array(goals, np.float64).reshape(-1, 2)
