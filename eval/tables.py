"""The outputs of an experiment table, built from its cell results (eval/table_cells.py) alone: a
markdown table (mean +- 95% interval over seeds), learning curves with seed bands, a landing
map per variant and a JSON summary. Rebuilt whole every time, so it always shows every result
present, and never needs a run directory or a checkpoint.
"""
from __future__ import annotations

import math
import os

import numpy as np

from ttmjx.world import files
from ttmjx.world.config import Table
from ttmjx.world.goals import RADII, landed_mean_distance, scored_distance

# Two-sided 95% quantiles of Student's t (t_{0.975, df}); beyond the table the next lower
# df is used, which widens the interval slightly (conservative).
T975 = {1: 12.7062, 2: 4.3027, 3: 3.1824, 4: 2.7764, 5: 2.5706, 6: 2.4469, 7: 2.3646, 8: 2.3060,
        9: 2.2622, 10: 2.2281, 11: 2.2010, 12: 2.1788, 13: 2.1604, 14: 2.1448, 15: 2.1314, 16: 2.1199,
        17: 2.1098, 18: 2.1009, 19: 2.0930, 20: 2.0860, 25: 2.0595, 30: 2.0423, 40: 2.0211, 60: 2.0003,
        120: 1.9799}

# (metric key, column title, scale for display, digits): percentages for rates, metres for distance.
COLUMNS = (("mean_dist", "mean distance (m)", 1.0, 2),
           ("mean_dist_landed", "distance, every landing (m)", 1.0, 2), ("within_30cm", "<= 30 cm (%)", 100.0, 1),
           ("within_20cm", "<= 20 cm (%)", 100.0, 1), ("hit_rate", "hit rate (%)", 100.0, 1),
           ("on_table_rate", "on table (%)", 100.0, 1))


def t975(df: int) -> float:
    return T975[max(k for k in T975 if k <= df)]


def interval(values) -> dict:
    """{mean, half (the 95% half-width, None for n < 2), n} of the finite values (None/NaN dropped)."""
    v = np.array([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if len(v) == 0:
        return {"mean": None, "half": None, "n": 0}
    half = t975(len(v) - 1) * float(np.std(v, ddof=1)) / math.sqrt(len(v)) if len(v) > 1 else None
    return {"mean": float(np.mean(v)), "half": half, "n": int(len(v))}


def final_metrics(result: dict) -> dict:
    """A cell's final metrics; mean_dist_landed recomputed from its landings where the result
    predates that metric."""
    final, lands = result["final"], result.get("landings")
    if "mean_dist_landed" in final or not lands:
        return final
    landing = np.array([[np.nan if v is None else v for v in p] for p in lands["landing"]], np.float64)
    return {**final, "mean_dist_landed": landed_mean_distance(landing, lands["goal"], lands["hit"])}


def summarize(results: list[dict], variants: list[str], header: dict) -> dict:
    """The JSON summary: per variant (in `variants` order, then any others found) its seeds and,
    per metric, the interval over seeds."""
    names = list(variants) + sorted({r["variant"] for r in results} - set(variants))
    out = []
    for v in names:
        mine = sorted((r for r in results if r["variant"] == v), key=lambda r: r["seed"])
        finals = [final_metrics(r) for r in mine]
        keys = [k for k, *_ in COLUMNS if any(k in f for f in finals)]
        out.append({"variant": v, "seeds": [r["seed"] for r in mine],
                    "metrics": {k: {**interval([f.get(k) for f in finals]),
                                    "values": [f.get(k) for f in finals]} for k in keys},
                    "wall_s": [r["wall_s"] for r in mine]})
    return {**header, "variants": out}


def cell_text(stat: dict | None, scale: float, digits: int) -> str:
    if not stat or stat["mean"] is None:
        return "-"
    text = f"{stat['mean'] * scale:.{digits}f}"
    return text if stat["half"] is None else f"{text} +- {stat['half'] * scale:.{digits}f}"


def markdown(summary: dict) -> str:
    """The table: one row per variant, mean +- 95% interval over seeds (n = 1: the value alone)."""
    cols = [c for c in COLUMNS if any(c[0] in v["metrics"] for v in summary["variants"])] or list(COLUMNS[:4])
    lines = [f"### {summary['title']}", "", summary["subtitle"], "",
             "| variant | seeds | " + " | ".join(c[1] for c in cols) + " |",
             "| --- | --- |" + " --- |" * len(cols)]
    for v in summary["variants"]:
        row = [cell_text(v["metrics"].get(k), s, d) for k, _, s, d in cols]
        lines.append(f"| {v['variant']} | {len(v['seeds'])} | " + " | ".join(row) + " |")
    lines += ["", "Mean over seeds +- the 95% interval (Student's t, n - 1 degrees of freedom); no "
              "interval with one seed. '-': no finished cell (or no ball landed). The table is each cell's final "
              "evaluation; curves.png shows the runs' own evaluations during training (other goals)."]
    return "\n".join(lines) + "\n"


# -- plots -------------------------------------------------------------------------------------
def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def save_png(fig, png: str) -> str:
    """The figure written atomically (a crash leaves the old picture or the new one)."""
    files.write_figure(png, fig, dpi=110)
    _pyplot().close(fig)
    return png


def seed_curves(results: list[dict], key: str, x: str) -> tuple[np.ndarray, np.ndarray]:
    """(x [P], values [S, P]) at the evaluation points every seed has."""
    common = sorted(set.intersection(*({p[x] for p in r["curve"] if p.get(key) is not None} for r in results)))
    table = [{p[x]: p[key] for p in r["curve"]} for r in results]
    return np.array(common, np.float64), np.array([[t[c] for c in common] for t in table], np.float64)


def plot_curves(results: list[dict], variants: list[str], png: str, x: str = "trajectories",
                title: str = "") -> str:
    """Success vs `x`, one line per variant (the mean over seeds) with a band from the lowest to
    the highest seed; a third panel shows the training examples (cache size), as the paper's
    demonstrations ablation does."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    for i, v in enumerate(variants):
        mine = [r for r in results if r["variant"] == v and r["curve"]]
        if not mine:
            continue
        for ax, key, scale in zip(axes, ("within_30cm", "within_20cm", "cache_size"), (100, 100, 1)):
            xs, ys = seed_curves(mine, key, x)
            if len(xs) == 0:
                continue
            ax.plot(xs, scale * ys.mean(0), "o-", ms=3, color=f"C{i}", label=f"{v} (n={len(mine)})")
            if len(mine) > 1 and len(xs) > 1:
                ax.fill_between(xs, scale * ys.min(0), scale * ys.max(0), color=f"C{i}", alpha=0.2)
            elif len(mine) > 1:   # one evaluation (an LFP run): the band is an error bar
                mean = scale * ys.mean(0)
                ax.errorbar(xs, mean, [mean - scale * ys.min(0), scale * ys.max(0) - mean], color=f"C{i}", capsize=4)
    label = "total trajectories (demonstrations + practice)" if x == "trajectories" else "gradient updates"
    for ax, ylabel in zip(axes, ("% of goals within 30 cm", "% of goals within 20 cm", "training examples in the pool")):
        ax.set_xlabel(label), ax.set_ylabel(ylabel), ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title}: mean over seeds, band from lowest to highest seed")
    fig.tight_layout()
    return save_png(fig, png)


def plot_landing_map(results: list[dict], png: str, title: str, table: Table = Table()) -> str:
    """The table seen from above, the opponent's half shaded: each final-evaluation goal (a ring)
    joined to where its ball first landed (green within 30 cm, orange elsewhere on the opponent's
    half, red off it), all seeds overlaid; goals whose ball was never hit or never came down
    are grey crosses."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.6))
    hl, hw = table.half_length, table.half_width
    ax.add_patch(plt.Rectangle((-hl, -hw), hl, 2 * hw, fc="none", ec="k", lw=0.8))            # the robot's half
    ax.add_patch(plt.Rectangle((0, -hw), hl, 2 * hw, fc="#2f6f4f", alpha=0.15, ec="k"))      # the opponent's
    ax.axvline(0, color="k", lw=2)    # the net
    for r in results:
        goal, land, ok, colour = _landings(r["landings"])
        for g, l, c in zip(goal[ok], land[ok], colour[ok]):
            ax.plot([g[0], l[0]], [g[1], l[1]], "-", color=c, lw=0.6, alpha=0.5)
        ax.scatter(goal[ok, 0], goal[ok, 1], s=10, facecolors="none", edgecolors="k", lw=0.5, zorder=3)
        ax.scatter(land[ok, 0], land[ok, 1], s=7, c=list(colour[ok]), zorder=4)
        ax.scatter(goal[~ok, 0], goal[~ok, 1], s=14, marker="x", c="gray", lw=0.8, zorder=3)
    for label, style in (("goal", dict(marker="o", mfc="none", mec="k", ls="")),
                         ("landing <= 30 cm", dict(marker="o", color="tab:green", ls="-")),
                         ("on the half, farther", dict(marker="o", color="tab:orange", ls="-")),
                         ("off the half", dict(marker="o", color="tab:red", ls="-")),
                         ("not hit / never landed", dict(marker="x", color="gray", ls=""))):
        ax.plot([], [], ms=4, label=label, **style)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1))
    ax.set_xlim(-hl - 0.4, hl + 0.6), ax.set_ylim(-hw - 0.4, hw + 0.4), ax.set_aspect("equal")
    ax.set_xlabel("x (m; net at 0, robot at negative x)"), ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    return save_png(fig, png)


def landing_arrays(d: dict) -> tuple:
    """(goal [G, 2], landing [G, 2] with NaN where the ball never came down, hit [G] bool,
    on_opponent [G] bool) of a cell's stored final-evaluation landings."""
    land = np.array([[np.nan, np.nan] if p is None or None in p else p for p in d["landing"]], np.float64)
    return (np.array(d["goal"], np.float64), land, np.array(d["hit"], bool),
            np.array(d["on_opponent"], bool))


def _landings(d: dict) -> tuple:
    """(goal [G, 2], landing [G, 2], landed [G] bool, colour [G]) of a cell's final evaluation."""
    goal, land, hit, on = landing_arrays(d)
    ok = hit & np.isfinite(land).all(1)
    scored = scored_distance(land, goal, hit, on)   # a landing off the half is red
    colour = np.where(scored <= RADII[0], "tab:green",
                      np.where(np.array(d["on_opponent"], bool), "tab:orange", "tab:red"))
    return goal, land, ok, colour


def write_report(out_dir: str, results: list[dict], variants: list[str], header: dict,
                 x: str = "trajectories") -> dict:
    """table.md, curves.png, landings/<variant>.png and summary.json in out_dir; returns the summary
    with the paths it wrote."""
    summary = summarize(results, variants, header)
    names = [v["variant"] for v in summary["variants"] if v["seeds"]]
    os.makedirs(os.path.join(out_dir, "landings"), exist_ok=True)
    paths = {"table": os.path.join(out_dir, "table.md"), "curves": os.path.join(out_dir, "curves.png"),
             "landings": {v: os.path.join(out_dir, "landings", f"{v}.png") for v in names},
             "summary": os.path.join(out_dir, "summary.json")}
    files.write_bytes(paths["table"], markdown(summary).encode())
    plot_curves(results, names, paths["curves"], x, summary["title"])
    for v in names:
        mine = [r for r in results if r["variant"] == v]
        m = next(s for s in summary["variants"] if s["variant"] == v)["metrics"]
        plot_landing_map(mine, paths["landings"][v], f"{summary['title']}: {v}, {len(mine)} seed(s), "
                         f"<= 30 cm {cell_text(m.get('within_30cm'), 100, 1)}%")
    summary["outputs"] = paths
    files.write_json(paths["summary"], summary)
    return summary
