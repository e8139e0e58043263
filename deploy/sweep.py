"""`ttmjx robot sweep`: strict success of an exported policy against added latency.

Each point plays the same goals and throws (one seed) on the simulated station, with the
latency added either to the ball tracker's delivery or to the commands' start (the action
delay), on top of a timing profile. The runner's staleness limit is raised with the latency
(stale_s = 0.1 s + latency), so the sweep measures the policy, not the runner's hold.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np

from deploy.runner import RunnerConfig
from deploy.station import TIMING, run_sim
from ttmjx.world import files

SERIES = {"ball": "tracker_latency_s", "action": "action_delay_s"}


def sweep_point(policy_dir: str, goals: np.ndarray, seed: int, profile: str, series: str, added_ms: float) -> dict:
    """One point: the session's metrics with `added_ms` more latency on `series` (ball or action)."""
    base = TIMING[profile]
    field = SERIES[series]
    timing = dataclasses.replace(base, **{field: getattr(base, field) + added_ms / 1000.0})
    config = RunnerConfig(stale_s=0.1 + added_ms / 1000.0)
    out = run_sim(policy_dir, goals, None, seed=seed, charge_compute=False, config=config, timing=timing)
    return {"series": series, "added_ms": float(added_ms), "episodes": out["episodes"], **out["metrics"]}


def latency_sweep(policy_dir: str, goals: np.ndarray, out_dir: str, added_ms, seed: int = 0,
                  profile: str = "nominal") -> dict:
    """Both series over added_ms [P]; writes out_dir/sweep.json and sweep.png (after every point,
    so an interrupted sweep keeps what it measured). Returns the sweep.json object."""
    if profile not in TIMING:
        raise ValueError(f"unknown timing profile {profile!r}; expected one of {sorted(TIMING)}")
    os.makedirs(out_dir, exist_ok=True)
    out = {"policy": policy_dir, "profile": profile, "goals": int(len(goals)), "seed": seed, "points": []}
    for series in SERIES:
        for ms in added_ms:
            out["points"].append(sweep_point(policy_dir, goals, seed, profile, series, float(ms)))
            print(f"sweep: {series} +{ms:.0f} ms: within 30 cm {out['points'][-1]['within_30cm']:.1%}", flush=True)
            files.write_json(os.path.join(out_dir, "sweep.json"), files.json_safe(out), indent=1)
    plot_sweep(out, os.path.join(out_dir, "sweep.png"))
    return out


def sweep_table(out: dict) -> str:
    """A markdown table of the sweep."""
    rows = ["| added latency (ms) | on | within 30 cm | within 20 cm | hit rate |", "| --- | --- | --- | --- | --- |"]
    for p in out["points"]:
        rows.append(f"| {p['added_ms']:.0f} | {p['series']} | {p['within_30cm']:.1%} | {p['within_20cm']:.1%} | "
                    f"{p['hit_rate']:.1%} |")
    return "\n".join(rows)


def plot_sweep(out: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    for series, style in (("ball", "-o"), ("action", "-s")):
        pts = [p for p in out["points"] if p["series"] == series]
        x = [p["added_ms"] for p in pts]
        ax.plot(x, [100 * p["within_30cm"] for p in pts], style, label=f"{series} latency, within 30 cm")
        ax.plot(x, [100 * p["within_20cm"] for p in pts], style, alpha=0.5, label=f"{series} latency, within 20 cm")
    ax.set_xlabel("added latency (ms)")
    ax.set_ylabel("success (%), strict")
    ax.set_title(f"{os.path.basename(out['policy'].rstrip('/'))}: {out['goals']} goals, profile {out['profile']}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path + ".tmp.png", dpi=120)
    plt.close(fig)
    os.replace(path + ".tmp.png", path)
