"""The paper's extended comparison on one plot: the RL baselines' learning curves (strict metric,
200 uniform goals, from each cell's results/<method>-seed*.json) beside GoalsEye's held-out
evaluation during training (paper bootstrap, 5 seeds, from a Table I run's metrics.jsonl).

    python3 scripts/extended_curves.py docs/img/extended-curves.png docs/results/table1-120k-paper \
        docs/results/baselines/extended-h200 docs/results/baselines/table1-h100

Each RL directory is searched for results/<method>-seed*.json in it and one level below; every
(directory, method) pair found is one band.
"""
import glob
import json
import os
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
from table1_figures import band, runs_of, series  # noqa: E402

LABELS = {"ppo": "PPO (brax, no demonstrations)", "es": "ES (brax, no demonstrations)",
          "sac": "SAC (brax, no demonstrations)", "qtopt": "QT-Opt (ours, JAX, no demonstrations)"}


def rl_curves(root: str, method: str, key: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """(trajectories, % of `key`) of each seed of `method` under root/results/ or root/*/results/."""
    out = []
    paths = [p for d in ("", "*") for p in glob.glob(os.path.join(root, d, "results", f"{method}-seed*.json"))]
    for p in sorted(paths):
        curve = json.load(open(p))["curve"]
        out.append((np.array([c["trajectories"] for c in curve], float),
                    np.array([c[key] for c in curve], float) * 100))
    return out


def main(out: str, table_root: str, *rl_roots: str) -> None:
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    runs = runs_of(table_root, "goalseye")
    for ax, key, what in zip(axes, ("within_30cm", "hit_rate"), ("within 30 cm", "balls hit")):
        band(ax, [series(r, f"eval_{key}", "trajectories") for r in runs],
             label=f"GoalsEye (paper bootstrap, 3,600 demonstrations), {len(runs)} seeds")
        for rl_root in rl_roots:
            for method, label in LABELS.items():
                curves = rl_curves(rl_root, method, key)
                if curves:
                    top = max(int(x[-1]) for x, _ in curves)
                    band(ax, curves, marker="o", ms=3,
                         label=f"{label}, {len(curves)} seed{'s' * (len(curves) > 1)} to {top // 1000}k")
        ax.set(xlabel="trajectories", ylabel=f"% {what} (strict metric, 200 goals)",
               title=f"{what} (mean, band: min-max of seeds)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].axhline(21, color="gray", ls=":", lw=1, label="paper: GoalsEye at 120k (21%)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(out)


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit("usage: extended_curves.py OUT.png TABLE_I_DIR RL_DIR [RL_DIR ...]")
    main(*sys.argv[1:])
