"""The `--goals` grammar of `ttmjx eval` and `ttmjx robot run`, defined once (numpy only: the
robot side reads it, and the layers put what both sides share in the world). A value is one of
GOAL_FORMS:

  N             that many goals uniform over the opponent's half (a positive whole number)
  uniform       uniform goals, as many as the command's count (`robot run --n`; `eval`: 200)
  five          goals A-E of the paper's five-goal protocol (ttmjx.world.goals.FIVE_GOALS)
  x,y;x,y;...   goals in metres in the table frame (docs/DESIGN.md), ';' between goals
  FILE          a goal file (ttmjx.world.goalfile: .csv with a header row x,y, or .npy [N, 2])

Explicit goals lie on the opponent's half. A bad value is one ValueError (FileNotFoundError for
a missing file) naming the value and the accepted forms (`goal_error`). What a command does with
the goals is its own: `ttmjx eval` (eval.evaluate) attempts each goal once (`five`: --per-goal
times) and draws uniform goals and throws with JAX from --seed, as the in-run evaluation does;
`ttmjx robot run` (deploy.robot.goals) attempts each goal --n times in a row (`uniform`: --n
goals once each) and draws uniform goals with numpy.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ttmjx.world.config import Table
from ttmjx.world.goalfile import check_goals, is_goal_file, read_goal_file

GOAL_FORMS = ("N (that many uniform goals), 'uniform' (the command's count of them), 'five' (goals A-E), "
              "'x,y;x,y;...' (goals in metres) or a goal file (.csv with a header row x,y, or .npy [N, 2])")
MAX_GOALS = 100_000     # goals one --goals value may name (eval: at most what fits in memory)


class GoalSpec(NamedTuple):
    """A parsed --goals value."""
    kind: str                        # 'uniform', 'five' or 'points'
    count: int | None = None         # 'uniform': how many; None: the command's count
    goals: np.ndarray | None = None  # 'points': [N, 2] float32 (x, y) in metres


def goal_error(value: str, why: str) -> str:
    """The one message of a bad --goals value: the value, what is wrong, the accepted forms."""
    return f"--goals {value!r}: {why}; --goals takes {GOAL_FORMS}"


def goal_spec(value: str, table: Table = Table(), most: int = MAX_GOALS) -> GoalSpec:
    """The GoalSpec of a --goals value (module docstring), explicit goals (inline, a file) checked
    to lie on `table`'s opponent's half; `most`: the largest count of goals accepted.
    ValueError / FileNotFoundError: `goal_error`'s line."""
    try:
        return _goal_spec(value, table, most)
    except FileNotFoundError as e:
        raise FileNotFoundError(goal_error(value, str(e))) from None
    except ValueError as e:
        raise ValueError(goal_error(value, str(e))) from None


def _goal_spec(value: str, table: Table, most: int) -> GoalSpec:
    if value in ("five", "uniform"):
        return GoalSpec(value)
    if is_goal_file(value):      # by its extension, a path separator, or because it exists
        goals = read_goal_file(value, table)
    elif value.strip().lstrip("+-").isdigit():
        n = int(value)
        if not 1 <= n <= most:
            raise ValueError(f"{n} uniform goals; expected between 1 and {most}")
        return GoalSpec("uniform", n)
    else:
        goals = check_goals(parse_goals(value), "goals", table)
    if len(goals) > most:
        raise ValueError(f"{len(goals)} goals; expected at most {most}")
    return GoalSpec("points", goals=goals)


def parse_goals(spec: str) -> np.ndarray:
    """'x,y' or 'x,y;x,y;...' (a space may stand for the comma) -> [N, 2] float32, finite."""
    rows = [r.strip() for r in spec.replace("\n", ";").split(";") if r.strip()]
    if not rows:
        raise ValueError("holds no goals ('x,y' or 'x,y;x,y;...')")
    goals = []
    for r in rows:
        try:
            x, y = (float(p) for p in r.replace(",", " ").split())    # one value or three: ValueError too
        except ValueError:
            raise ValueError(f"goal {r!r} is not two numbers x,y") from None
        goals.append([x, y])
    return check_goals(goals, "goals")
