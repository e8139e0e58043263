"""Goal files and user goals, checked once for every reader: `ttmjx eval --goals FILE`, `ttmjx
robot run --goals FILE` and the ablations' held-out goal sets (numpy only: the robot side uses it).

One format, two encodings, neither needing pickle (docs/DATA.md, "Goal files"):

  .csv  a header row naming the columns `x` and `y` (any order; other columns, e.g. a goal's
        name, are ignored), then one goal per row, in metres in the table frame; blank rows
        are skipped
  .npy  a numeric array [N, 2] of (x, y)

Goals are (x, y) on the table top in the table frame (ttmjx.world.config): the opponent's half is
0 <= x <= half_length, |y| <= half_width. Evaluation and the robot's sessions aim only there;
practice may aim beyond the table and checks its goals with `check_goals` without a table.
"""
from __future__ import annotations

import csv
import os

import numpy as np

from ttmjx.world.config import Table
from ttmjx.world.goals import off_half

GOAL_FILE_TYPES = (".csv", ".npy")


def check_goals(goals, where: str = "goals", table: Table | None = None) -> np.ndarray:
    """[N, 2] float32 of `goals` (N >= 1, finite; with `table`, each on the opponent's half).
    ValueError names `where`, the first bad goal and what was expected."""
    try:
        g = np.asarray(goals, np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: not numbers of shape [N, 2] (x, y in metres): {e}") from None
    if g.ndim == 1 and g.shape == (2,):
        g = g[None]
    if g.ndim != 2 or g.shape[1] != 2 or g.shape[0] < 1:
        raise ValueError(f"{where}: goals of shape {g.shape}; expected [N, 2] (x, y in metres), N >= 1")
    bad = ~np.all(np.isfinite(g), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"{where}: goal {i} = ({g[i, 0]}, {g[i, 1]}) is not finite")
    if table is not None:
        out = off_half(g, table)
        if out.any():
            i = int(np.argmax(out))
            raise ValueError(f"{where}: goal {i} = ({g[i, 0]}, {g[i, 1]}) is off the opponent's half; expected "
                             f"0 <= x <= {table.half_length:g} and |y| <= {table.half_width:g}")
    return g.astype(np.float32)


def is_goal_file(spec: str) -> bool:
    """`spec` (a --goals value) names a goal file (by its extension, a path separator, or because
    it exists), not 'five', 'uniform' or a number of goals."""
    if spec in ("five", "uniform") or spec.strip().lstrip("+-").isdigit():
        return False
    return spec.lower().endswith(GOAL_FILE_TYPES) or os.sep in spec or os.path.isfile(spec)


def read_goal_file(path: str, table: Table = Table()) -> np.ndarray:
    """[N, 2] float32 goals from `path` (.csv or .npy), each on the opponent's half of `table`.
    FileNotFoundError or ValueError naming the file and the problem."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in GOAL_FILE_TYPES:
        raise ValueError(f"goal file {path!r}: extension {ext!r}; expected .csv (header x,y) or .npy ([N, 2])")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"goal file {path!r} does not exist")
    goals = _read_csv(path) if ext == ".csv" else _read_npy(path)
    return check_goals(goals, f"goal file {path!r}", table)


def _read_npy(path: str) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:     # object arrays need pickle: refused
        raise ValueError(f"goal file {path!r} is not a plain numeric .npy array ({e})") from None
    if not isinstance(a, np.ndarray) or not (np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"goal file {path!r} holds {getattr(a, 'dtype', type(a))}; expected numbers [N, 2]")
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"goal file {path!r} holds an array of shape {a.shape}; expected [N, 2] (x, y)")
    return a


def _read_csv(path: str) -> np.ndarray:
    try:
        with open(path, newline="") as f:
            rows = [r for r in csv.reader(f) if any(c.strip() for c in r)]
    except UnicodeDecodeError as e:
        raise ValueError(f"goal file {path!r} is not text ({e.reason})") from None
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
