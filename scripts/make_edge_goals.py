"""Writes eval/goals/edges_net.csv: 200 evaluation goals along the hard parts of the opponent's
half (x from the net, metres, table frame), drawn once with a fixed seed:
60 within 20 cm of the net, 60 within 20 cm of the end line, 80 within 20 cm of a sideline.
Every goal is at least 2 cm inside the half. Rerunning rewrites the same file.
    python scripts/make_edge_goals.py"""
import os

import numpy as np

HALF_LENGTH, HALF_WIDTH, BAND, INSET = 1.37, 0.7625, 0.20, 0.02

rng = np.random.default_rng(2026)
y_all = lambda n: rng.uniform(-HALF_WIDTH + INSET, HALF_WIDTH - INSET, n)  # noqa: E731
near_net = np.stack([rng.uniform(INSET, BAND, 60), y_all(60)], 1)
near_end = np.stack([rng.uniform(HALF_LENGTH - BAND, HALF_LENGTH - INSET, 60), y_all(60)], 1)
side = rng.choice([-1.0, 1.0], 80) * rng.uniform(HALF_WIDTH - BAND, HALF_WIDTH - INSET, 80)
near_side = np.stack([rng.uniform(INSET, HALF_LENGTH - INSET, 80), side], 1)
goals = np.concatenate([near_net, near_end, near_side]).round(4)
path = os.path.join(os.path.dirname(__file__), "..", "eval", "goals", "edges_net.csv")
with open(path, "w") as f:
    f.write("x,y,region\n")
    for (x, y), r in zip(goals, ["net"] * 60 + ["end"] * 60 + ["side"] * 80):
        f.write(f"{x},{y},{r}\n")
print(f"{len(goals)} goals -> {os.path.normpath(path)}")
