"""Where on the half a Table I arm succeeds: the final evaluation's 200 goals split into thirds by
their distance from the net (x), success within 30 cm per third (mean +- 95% interval over seeds,
the strict metric: ttmjx.world.goals.scored_distance), and where the arm's on-half landings fall.
With --demos DIR (a `ttmjx demos` output), the share of its returned demonstrations per third.

    PYTHONPATH=. python3 scripts/table1_regions.py docs/results/table1-120k-paper \
        ratio/r0.2 practice/lfp-r0.2-updates practice/goalseye practice/lfp-equal-updates --demos /tmp/dp
"""
import argparse
import glob
import json
import os

import numpy as np

from eval.tables import interval, landing_arrays
from ttmjx.world.goals import RADII, scored_distance


def seed_landings(root: str, arm: str) -> list[dict]:
    """The final evaluation's landings of every seed of ABLATION/VARIANT under root."""
    ablation, variant = arm.split("/")
    paths = sorted(glob.glob(os.path.join(root, ablation, "results", f"{variant}-seed*.json")))
    if not paths:
        raise SystemExit(f"no results for {arm!r} under {root} (expected ABLATION/VARIANT, e.g. ratio/r0.2)")
    return [json.load(open(p))["landings"] for p in paths]


def thirds(x: np.ndarray) -> list[tuple[float, float]]:
    """Three (lo, hi] bins of x with a third of the values each."""
    q = np.quantile(x, [0, 1 / 3, 2 / 3, 1])
    return [(-np.inf, q[1]), (q[1], q[2]), (q[2], np.inf)], q


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("root")
    ap.add_argument("arms", nargs="+", help="ABLATION/VARIANT, e.g. ratio/r0.2")
    ap.add_argument("--demos", help="a `ttmjx demos` output directory (trajectories.npz)")
    a = ap.parse_args()
    goal0 = landing_arrays(seed_landings(a.root, a.arms[0])[0])[0]
    bins, q = thirds(goal0[:, 0])
    print("goal thirds by distance from the net (m): " + ", ".join(f"{lo:.2f}-{hi:.2f}" for lo, hi in zip(q, q[1:])))
    for arm in a.arms:
        per_seed, shares, near_err = [], [], []
        for d in seed_landings(a.root, arm):
            goal, land, hit, on = landing_arrays(d)
            if not np.allclose(goal, goal0):
                raise SystemExit(f"{arm}: its goals are not the first arm's; the thirds would not compare")
            win = scored_distance(land, goal, hit, on) <= RADII[0]
            per_seed.append([win[(goal[:, 0] > lo) & (goal[:, 0] <= hi)].mean() for lo, hi in bins])
            lx = land[on, 0]
            near = on & (goal[:, 0] <= bins[0][1])
            near_err.extend(land[near, 0] - goal[near, 0])
            shares.append([np.mean((lx > lo) & (lx <= hi)) for lo, hi in bins])
        cells = []
        for k in range(3):
            s = interval([p[k] for p in per_seed])
            cells.append(f"{100 * s['mean']:.1f} +- {100 * (s['half'] or 0):.1f}")
        share = " / ".join(f"{100 * v:.0f}%" for v in np.mean(shares, 0))
        print(f"{arm} ({len(per_seed)} seeds): within 30 cm near / middle / far: {', '.join(cells)}; "
              f"its on-half landings per third: {share}; near third, on-half landing x minus goal x: "
              f"median {np.median(near_err):+.2f} m")
    if a.demos:
        z = np.load(os.path.join(a.demos, "trajectories.npz"), allow_pickle=False)
        lx = z["landing"][z["hit"] & z["on_opponent"], 0]
        share = " / ".join(f"{100 * np.mean((lx > lo) & (lx <= hi)):.0f}%" for lo, hi in bins)
        print(f"demonstrations {a.demos}: {lx.size} of {z['hit'].size} returned; per third: {share}; "
              f"landing x 5th / 50th percentile {np.quantile(lx, 0.05):.2f} / {np.quantile(lx, 0.5):.2f} m")


if __name__ == "__main__":
    main()
