"""Figures of a Table I run from its runs' metrics.jsonl (and, printed, the mean +- 95% interval
over seeds of each arm on the edges-and-net goal set, from ROOT/edges/*.json): the held-out evaluation during training
(mean and the band of seeds) and the paper's "good trajectories per 100 seen" (practice episodes
that were hits landing within 30 cm of their own goal on the opponent's half, per 100 played).

    python3 scripts/table1_figures.py docs/results/table1-120k-paper docs/img/table1-paper.png
"""
import glob
import json
import os
import re
import sys

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ARMS = {"goalseye": "GoalsEye (3,600 demonstrations)", "r0.2": "GoalsEye, 0.2 updates per practice trajectory",
        "d1000": "1,000 demonstrations", "d100": "100 demonstrations", "d10": "10 demonstrations",
        "lfp-equal-updates": "LFP (3,600, no practice)", "lfp-equal-data": "LFP (120,000, no practice)",
        "lfp-r0.2-updates": "LFP (3,600, 25,400 updates, no practice)"}
# The "New Results" setting (frame stack, 10 members; ablations noise and ensembles): two figures of
# their own, OUT with "-new" (noise) and "-ensembles" before the extension. The ensembles' n10 cells
# are copies of noise's "off" and are drawn from "off".
NOISE_ARMS = {"off": "frame stack, 10 members, no noise", "paper-b0.05": "the paper's noise a + z, b = 0.05",
              "paper-b0.1": "the paper's noise, b = 0.1", "paper-b0.2": "the paper's noise, b = 0.2",
              "b0.05": "our offset noise, b = 0.05", "b0.1": "our offset noise, b = 0.1",
              "b0.2": "our offset noise, b = 0.2"}
ENSEMBLE_ARMS = {"n1": "frame stack, 1 member", "n3": "frame stack, 3 members", "n5": "frame stack, 5 members",
                 "off": "frame stack, 10 members"}
NEW_ARMS = {**NOISE_ARMS, **ENSEMBLE_ARMS}


def runs_of(root: str, arm: str) -> list[list[dict]]:
    paths = sorted(glob.glob(os.path.join(root, "*", "runs", f"{arm}-seed*", "metrics.jsonl")))
    return [[json.loads(line) for line in open(p) if line.strip()] for p in paths]


def series(rows: list[dict], key: str, x: str) -> tuple[np.ndarray, np.ndarray]:
    pts = [(r[x], r[key]) for r in rows if key in r]
    return np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float) * 100


def band(ax, curves: list[tuple[np.ndarray, np.ndarray]], xs: np.ndarray | None = None, **kw):
    """Mean over seeds as a line, min-max as a band, over the points every seed has; its line."""
    n = min(len(c[0]) for c in curves)
    ys = np.stack([c[1][:n] for c in curves])
    if n == 1:   # evaluated once, at the end (LFP at equal data): a point with the seeds' range
        x, m = curves[0][0][:1], ys.mean(0)
        bars = ax.errorbar(x, m, yerr=[m - ys.min(0), ys.max(0) - m], fmt="o", capsize=4, **kw)
        return bars.lines[0]
    xs = curves[0][0][:n] if xs is None else xs[:n]
    line, = ax.plot(xs, ys.mean(0), **kw)
    ax.fill_between(xs, ys.min(0), ys.max(0), color=line.get_color(), alpha=0.2)
    return line


# LFP's data is fixed: its evaluations are drawn at the trajectories of the GoalsEye arm that
# trains the same updates (LFP at equal data is evaluated once, at its own x).
LFP_TWIN = {"lfp-equal-updates": "goalseye", "lfp-r0.2-updates": "r0.2"}


def twin_x(root: str, arm: str) -> np.ndarray | None:
    """Trajectories of the evaluations of `arm`'s GoalsEye twin (its first seed), or None."""
    twin = runs_of(root, LFP_TWIN[arm]) if arm in LFP_TWIN else []
    return series(twin[0], "eval_within_30cm", "trajectories")[0] if twin else None


def main(root: str, out: str, arms: dict = ARMS) -> None:
    fig, (ax_eval, ax_good) = plt.subplots(1, 2, figsize=(12, 4.5))
    lfp = any(arm in LFP_TWIN for arm in arms)
    for arm, label in arms.items():
        runs = runs_of(root, arm)
        if not runs:
            continue
        xs = twin_x(root, arm)
        line = band(ax_eval, [series(r, "eval_within_30cm", "trajectories") for r in runs], xs,
                    label=f"{label}, {len(runs)} seeds")
        good = [series(r, "practice_within_30cm", "trajectories") for r in runs]
        if len(good[0][0]):
            band(ax_good, good, color=line.get_color(), label=label)
    ax_eval.set(xlabel="trajectories" + (" (LFP: at its GoalsEye's update count)" if lfp else ""), ylabel="% within 30 cm (held-out goals)",
                title="evaluation during training (mean, band: min-max of seeds)")
    ax_good.set(xlabel="trajectories", ylabel="good trajectories per 100 seen",
                title="practice: hits landing within 30 cm of their goal")
    for ax in (ax_eval, ax_good):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    print(out)


def edges_rows(root: str, arm: str) -> list[dict]:
    """The edges-and-net evaluations of one arm's seeds: ROOT/edges/ABLATION-ARM-seedK.json, the
    ablation one word, so that arm "b0.05" does not take "paper-b0.05"'s files."""
    paths = glob.glob(os.path.join(root, "edges", f"*-{arm}-seed*.json"))
    return [json.load(open(p)) for p in sorted(paths)
            if re.fullmatch(rf"[a-z]+-{re.escape(arm)}-seed\d+\.json", os.path.basename(p))]


def edges_table(root: str) -> None:
    """Print each arm's mean +- 95% interval (Student's t) over seeds on the edges-and-net goals."""
    from eval.tables import interval
    for arm in {**ARMS, **NEW_ARMS}:
        rows = edges_rows(root, arm)
        if rows:
            stats = {k: interval([r[k] for r in rows]) for k in ("within_30cm", "within_20cm", "hit_rate")}
            cells = [f"{k} {100 * v['mean']:.1f} +- {100 * (v['half'] or 0):.1f}" for k, v in stats.items()]
            print(f"edges_net {arm} ({len(rows)} seeds): " + ", ".join(cells))


if __name__ == "__main__":
    main(*sys.argv[1:3])
    stem, ext = os.path.splitext(sys.argv[2])
    main(sys.argv[1], f"{stem}-new{ext}", NOISE_ARMS)
    main(sys.argv[1], f"{stem}-ensembles{ext}", ENSEMBLE_ARMS)
    edges_table(sys.argv[1])
