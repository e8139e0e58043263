"""Why a run learns or not (`ttmjx report RUN`): per practice round, where the pool's landings
lie (demonstrations and practice apart), success and "good per 100" by goal region, each
ensemble member against the ensemble, the training loss and the loss on held-out
demonstrations (eval.heldout, where the run logged it); a JSON record and one figure.

Everything is read from what the run wrote: metrics.jsonl (the practice statistics and
evaluations by region and member, training.practice.stats_row and eval.evaluate.with_regions)
and the pool inside its newest checkpoint, whose rows were appended in order (demonstrations
first, then each round's kept episodes), so the round of every row follows from the logged
`practice_kept` counts.
"""
from __future__ import annotations

import json
import os
from typing import NamedTuple

import numpy as np

from ttmjx.world import files
from ttmjx.world.config import Table
from ttmjx.world.goals import GOAL_REGIONS, goal_regions, off_half

REPORT_FILES = ("report.json", "report.png")
POOL_REGIONS = (*GOAL_REGIONS, "off_half")   # where a pool episode's relabelled goal lies


class RunRecord(NamedTuple):
    """What a report is made from."""
    run_dir: str
    config: dict
    rows: list            # metrics.jsonl rows up to the checkpoint the pool comes from
    goal: np.ndarray      # [P, 2] the pool's relabelled goals (landings), oldest first
    demo: np.ndarray      # [P] bool the row is a demonstration
    round_of: np.ndarray  # [P] int32 practice round that added the row (-1: the starting pool)
    iteration: int        # the checkpoint's iteration


def read_run(run_dir: str) -> RunRecord:
    """The run's configuration, metrics and pool; ValueError naming the path and what is missing
    when `run_dir` is not a training run or has no practice round yet."""
    from training.rundir import SEEDS_FILE
    if not os.path.isdir(run_dir):
        raise ValueError(f"{run_dir}: not a directory; expected a training run (ttmjx train --run-dir)")
    if os.path.exists(os.path.join(run_dir, SEEDS_FILE)):
        raise ValueError(f"{run_dir} holds a batch of seeds ({SEEDS_FILE}); report one of its runs, "
                         f"e.g. {os.path.join(run_dir, 'seed0')}")
    for name in ("config.json", "metrics.jsonl"):
        if not os.path.isfile(os.path.join(run_dir, name)):
            raise ValueError(f"{run_dir}: not a training run (no {name}); expected a directory written by ttmjx train")
    with open(os.path.join(run_dir, "config.json")) as f:
        config = json.load(f)
    from training.checkpoint import load_checkpoint
    try:
        loaded = load_checkpoint(run_dir, warn=lambda m: None)
    except FileNotFoundError:
        raise ValueError(f"{run_dir}: no checkpoint (checkpoints/ is empty or missing); the report reads the "
                         f"pool from the newest one") from None
    iteration = int(loaded.ck.counters.iteration)
    rows = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl")) if line.strip()]
    rows = [r for r in rows if r["iteration"] < iteration]
    practice = [r for r in rows if r.get("phase") == "practice"]
    if not practice:
        raise ValueError(f"{run_dir}: no practice round yet ({len(rows)} rows in metrics.jsonl up to checkpoint "
                         f"{iteration}, none of phase 'practice'); the report needs at least one")
    cache = loaded.ck.cache
    size, count, cap = int(cache.size), int(cache.count), cache.capacity
    kept = [int(r["practice_kept"]) for r in practice]
    # Row labels in writing order: the starting pool, then each round's kept episodes.
    labels = np.concatenate([np.full(count - sum(kept), -1), *(np.full(k, i) for i, k in enumerate(kept))])
    written = np.arange(count)[-size:] if size else np.arange(0)          # the episodes still in the pool
    order = written % cap
    goal = np.asarray(cache.goal)[order]
    demo = np.asarray(cache.demo)[order]
    return RunRecord(run_dir, config, rows, goal, demo, labels[written].astype(np.int32), iteration)


def region_shares(goal: np.ndarray, table: Table) -> dict:
    """{region: share of the goals [P, 2]} over POOL_REGIONS (the thirds and off_half partition the
    goals; edges overlaps the thirds); NaN without goals."""
    if len(goal) == 0:
        return {r: float("nan") for r in POOL_REGIONS}
    off = off_half(goal, table)
    masks = goal_regions(goal, table) & ~off[None]
    return {**{r: float(m.mean()) for r, m in zip(GOAL_REGIONS, masks)}, "off_half": float(off.mean())}


def _table_of(config: dict) -> Table:
    from ttmjx.world.config import World, from_dict
    return from_dict(World, config["world"]).table


def summarize(rec: RunRecord) -> dict:
    """The report's JSON: per practice round, the evaluations (with the loss on held-out
    demonstrations where the run logged it, `heldout` saying which or why not), and the pool."""
    table = _table_of(rec.config)
    practice = [r for r in rec.rows if r.get("phase") == "practice"]
    members = sorted({k for r in rec.rows for k in r if "member" in k})
    rounds = []
    for i, r in enumerate(practice):
        own = rec.goal[rec.round_of == i]
        pool = rec.goal[rec.round_of <= i]
        rounds.append({
            "iteration": r["iteration"], "trajectories": r["trajectories"], "updates": r["updates"],
            "loss": r["loss"], "good_per_100": 100 * r["practice_within_30cm"],
            "hit_rate": r["practice_hit_rate"], "on_table_rate": r["practice_on_table_rate"],
            **{f"{g}_30cm": r.get(f"practice_{g}_30cm") for g in GOAL_REGIONS},
            **{k[len("practice_"):]: r[k] for k in members if k.startswith("practice_") and k in r},
            "kept": r["practice_kept"],
            "kept_landings": region_shares(own, table), "pool_landings": region_shares(pool, table)})
    evaluations = [{"iteration": r["iteration"], "trajectories": r["trajectories"], "phase": r["phase"],
                    **{k[len("eval_"):]: v for k, v in r.items() if k.startswith("eval_")}}
                   for r in rec.rows if "eval_within_30cm" in r]
    demo_goals, prac_goals = rec.goal[rec.demo], rec.goal[~rec.demo]
    return {"run_dir": rec.run_dir, "checkpoint_iteration": rec.iteration,
            "regions": {"near": "x < 1/3 of the half's depth", "middle": "the middle third",
                        "far": "the far third", "edges": "within 0.2 m of a side or end line",
                        "off_half": "landings off the opponent's half (pool only)"},
            "pool": {"demonstrations": len(demo_goals), "practice": len(prac_goals),
                     "demonstration_landings": region_shares(demo_goals, table),
                     "practice_landings": region_shares(prac_goals, table)},
            "rounds": rounds, "evaluations": evaluations, "heldout": heldout_note(rec.config, evaluations)}


def heldout_note(config: dict, evaluations: list[dict]) -> dict:
    """Whether the evaluations carry the loss on held-out demonstrations (`heldout_loss`), and
    which demonstrations those are, or why there is none."""
    from eval.heldout import HELDOUT_DEMOS, HELDOUT_SEED_OFFSET
    if not config.get("demos"):
        return {"logged": False, "why": "the run has no demonstrations (demos = 0, as GCSL): none to hold out"}
    if not any(e.get("heldout_loss") is not None for e in evaluations):
        return {"logged": False, "why": "not in the run's metrics: its evaluation did not compute it "
                                        "(eval.evaluate.training_evaluation(cfg, heldout=True))"}
    return {"logged": True, "demonstrations": HELDOUT_DEMOS, "source": config.get("demo_source"),
            "seed": config["seed"] + HELDOUT_SEED_OFFSET,
            "what": "the update's loss (normalized MSE) on demonstrations of the run's source never in its pool"}


def plot_report(rec: RunRecord, summary: dict, png: str) -> str:
    """Six panels: evaluation success by goal region; practice good-per-100 by region; members
    alone against the ensemble; the pool's landing density, demonstrations and practice; the
    pool's landing shares by region over the rounds, with the training loss and the loss on
    held-out demonstrations (or why the run has none)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    table = _table_of(rec.config)
    fig, ax = plt.subplots(2, 3, figsize=(15, 8))
    colours = dict(zip(POOL_REGIONS, ("C0", "C1", "C2", "C3", "C7")))

    ev, rounds = summary["evaluations"], summary["rounds"]
    a = ax[0, 0]
    x = [e["trajectories"] for e in ev]
    a.plot(x, [100 * e["within_30cm"] for e in ev], "ko-", lw=2, label="all goals")
    for g in GOAL_REGIONS:
        a.plot(x, [100 * _num(e.get(f"{g}_30cm")) for e in ev], "o--", color=colours[g], ms=3, label=g)
    lfp = [e for e in ev if e["phase"] != "practice"]
    if lfp:
        a.axvline(lfp[-1]["trajectories"], color="gray", ls=":", lw=1)
    a.set_title("evaluation: within 30 cm by goal region", fontsize=9)
    a.set_ylabel("% of goals"), a.legend(fontsize=7), a.grid(alpha=0.3)

    a = ax[0, 1]
    x = [r["trajectories"] for r in rounds]
    a.plot(x, [r["good_per_100"] for r in rounds], "k-", lw=2, label="all goals")
    for g in GOAL_REGIONS:
        a.plot(x, [100 * _num(r.get(f"{g}_30cm")) for r in rounds], "-", color=colours[g], lw=1, label=g)
    a.set_title("practice: good attempts per 100 (within 30 cm) by goal region", fontsize=9)
    a.legend(fontsize=7), a.grid(alpha=0.3)

    a = ax[0, 2]
    ex = [e["trajectories"] for e in ev]
    a.plot(ex, [100 * e["within_30cm"] for e in ev], "ko-", lw=2, label="ensemble (evaluation)")
    n_members = len([k for k in (ev[-1] if ev else {}) if k.startswith("member") and k.endswith("_30cm")])
    for i in range(n_members):
        a.plot(ex, [100 * _num(e.get(f"member{i}_30cm")) for e in ev], "o--", ms=3, label=f"member {i} alone")
        a.plot(x, [100 * _num(r.get(f"member{i}_30cm")) for r in rounds], "-", lw=0.6, alpha=0.6,
               label=f"member {i} in practice")
    a.set_title("each member over the goals it played", fontsize=9)
    a.legend(fontsize=7), a.grid(alpha=0.3)

    for a, pick, title in ((ax[1, 0], rec.demo, "pool landings: demonstrations"),
                           (ax[1, 1], ~rec.demo, "pool landings: practice episodes")):
        g = rec.goal[pick]
        _table_axes(a, table)
        if len(g):
            a.hist2d(g[:, 0], g[:, 1], bins=[np.linspace(-0.2, table.half_length + 0.6, 33),
                                             np.linspace(-table.half_width - 0.5, table.half_width + 0.5, 33)],
                     cmap="viridis", cmin=1)
        a.set_title(f"{title} ({len(g)})", fontsize=9)

    a = ax[1, 2]
    for reg in POOL_REGIONS:
        a.plot(x, [100 * _num(r["pool_landings"][reg]) for r in rounds], "-", color=colours[reg], label=reg)
    a.set_title("pool: share of landings by region (after each round)", fontsize=9)
    a.set_xlabel("total trajectories"), a.set_ylabel("% of the pool"), a.grid(alpha=0.3)
    b = a.twinx()
    b.plot(x, [r["loss"] for r in rounds], "k:", lw=1, label="training loss")
    held = summary["heldout"]
    if held["logged"]:
        b.plot(ex, [_num(e.get("heldout_loss")) for e in ev], "ks--", ms=4, lw=1, label="held-out demonstrations")
    else:
        a.text(0.02, 0.02, f"no held-out loss: {held['why']}", transform=a.transAxes, fontsize=6, wrap=True)
    b.set_ylabel("loss (normalized MSE)")
    a.legend(fontsize=7, loc="upper left"), b.legend(fontsize=7, loc="upper right")
    for a in ax[0]:
        a.set_xlabel("total trajectories (demonstrations + practice)")
    fig.suptitle(f"{rec.run_dir}: why practice lifts or not (ttmjx report)", fontsize=10)
    fig.tight_layout()
    files.write_figure(png, fig, dpi=100)
    plt.close(fig)
    return png


def _num(v) -> float:
    return float("nan") if v is None else float(v)


def _table_axes(a, table: Table) -> None:
    """The opponent's half from above (net at x = 0)."""
    hl, hw = table.half_length, table.half_width
    a.plot([0, hl, hl, 0, 0], [-hw, -hw, hw, hw, -hw], "k-", lw=1)
    a.axvline(0, color="k", lw=2)
    third = hl / 3
    for t in (third, 2 * third):
        a.axvline(t, color="gray", lw=0.5, ls=":")
    a.set_xlim(-0.2, hl + 0.6), a.set_ylim(-hw - 0.5, hw + 0.5), a.set_aspect("equal")
    a.set_xlabel("x (m from the net)"), a.set_ylabel("y (m)")


def write_report(run_dir: str, out: str | None = None) -> dict:
    """report.json and report.png of `run_dir` into `out` (default RUN/report/), each written
    atomically -> {"json": path, "png": path, "summary": the JSON}."""
    rec = read_run(run_dir)
    out = out or os.path.join(run_dir, "report")
    if os.path.isfile(out):
        raise ValueError(f"--out {out!r} is a file; expected a directory for {', '.join(REPORT_FILES)}")
    os.makedirs(out, exist_ok=True)
    summary = summarize(rec)
    paths = {"json": os.path.join(out, REPORT_FILES[0]), "png": os.path.join(out, REPORT_FILES[1])}
    files.write_json(paths["json"], summary)
    plot_report(rec, summary, paths["png"])
    return {**paths, "summary": summary}
