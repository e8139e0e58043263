"""`ttmjx robot sweep`: strict success of an exported policy against added latency and jitter.

The export is verified and its policy built once (deploy.sim.station.load_for_station); every point
then plays the same goals and throws (one seed) on a fresh simulated station. The station's
base timing is the one the policy was trained under (its centre; or a named profile), and each
series adds to it:

  ball    ms of ball-tracker latency (the delivery of each ball sample)
  action  ms of command delay (the start of each command's ramp)
  jitter  ms of extra per-sample delivery jitter (uniform in [0, jitter], both sensors)
  all     the three together: point i adds the ball and action series' i-th value and the
          jitter series' i-th value at once

The runner's staleness limit is raised with the latency (stale_s = 0.1 s + added latency +
jitter), so the sweep measures the policy, not the runner's hold. Points outside the timing
the policy was trained under are played (a sweep exists to look there) and marked
(`within_trained` False, `outside` the reasons); a point whose timing equals an earlier one
(the +0 point of every series) is played once. Success rates count every goal: an episode the
runner did not play (a session that ended in HOLD) is a miss (`episodes` says how many played,
`faults` and `mode` why).
"""
from __future__ import annotations

import json
import os

import numpy as np

from deploy.robot.runner import RunnerConfig
from deploy.robot.timing_check import station_timing, with_added
from deploy.sim.station import load_for_station, play_session
from ttmjx.world import files
from ttmjx.world.config import to_dict

SERIES = ("ball", "action", "jitter", "all")


def parse_series(spec: str) -> tuple[str, ...]:
    """'ball,action' -> ('ball', 'action'); ValueError naming an unknown one."""
    names = tuple(s.strip() for s in spec.split(",") if s.strip())
    bad = [s for s in names if s not in SERIES]
    if bad or not names:
        raise ValueError(f"--series {spec!r}: expected a comma-separated subset of {', '.join(SERIES)}")
    return names


def added_for(series: str, latency_ms: float, jitter_ms: float) -> dict:
    """Seconds added to each Timing field at one point of `series`."""
    lat, jit = latency_ms / 1000.0, jitter_ms / 1000.0
    return {"ball": {"tracker_latency_s": lat}, "action": {"action_delay_s": lat},
            "jitter": {"jitter_s": jit},
            "all": {"tracker_latency_s": lat, "action_delay_s": lat, "jitter_s": jit}}[series]


def latency_sweep(policy_dir: str, goals: np.ndarray, out_dir: str, added_ms, seed: int = 0,
                  profile: str | None = None, series=("ball", "action", "jitter", "all"),
                  jitter_ms=None, progress: bool = True) -> dict:
    """Every series over its points (added_ms [P] of latency; jitter_ms [P] of jitter, default
    added_ms / 5); writes out_dir/sweep.json after every point (an interrupted sweep keeps what
    it measured, and the same call on out_dir measures only the points it lacks) and sweep.png.
    Returns the sweep.json object."""
    series = tuple(series)
    for s in series:
        if s not in SERIES:
            raise ValueError(f"unknown sweep series {s!r}; expected one of {SERIES}")
    added_ms = [float(x) for x in added_ms]
    jitter_ms = [x / 5.0 for x in added_ms] if jitter_ms is None else [float(x) for x in jitter_ms]
    if len(jitter_ms) != len(added_ms):
        raise ValueError(f"{len(jitter_ms)} jitter points for {len(added_ms)} latency points")
    loaded = load_for_station(policy_dir)                 # verified and built once for every point
    base, source = station_timing(loaded.timing, profile)
    base = base.centre()                 # each point adds to a fixed timing: no per-throw drift
    out = {"policy": policy_dir, "profile": source, "base_timing": to_dict(base),
           "trained_ranges": loaded.timing["ranges"], "goals": int(len(goals)), "seed": seed,
           "series": list(series), "points": [],
           "plan": {"export": files.sha256_file(os.path.join(policy_dir, "manifest.json")),
                    "goals": np.asarray(goals, np.float64).round(6).tolist(), "added_ms": added_ms,
                    "jitter_ms": jitter_ms}}
    earlier = measured_earlier(out_dir, out)
    os.makedirs(out_dir, exist_ok=True)
    played: dict = {}
    for s in series:
        for lat, jit in zip(added_ms, jitter_ms):
            add = added_for(s, lat, jit)
            tm = with_added(base, **add)
            key = tuple(sorted(to_dict(tm).items()))
            done = earlier.get((s, jit if s == "jitter" else lat, jit if s in ("jitter", "all") else 0.0))
            if key not in played and done is not None:     # measured before an interruption: the same
                played[key] = {k: v for k, v in done.items() if k not in ("series", "added_ms", "added_jitter_ms")}
            if key not in played:
                extra = sum(add.values()) if s != "action" else add.get("jitter_s", 0.0)
                config = RunnerConfig(stale_s=0.1 + extra)
                label = f"{source} + " + ", ".join(f"{k} {1e3 * v:g} ms" for k, v in add.items())
                session = play_session(loaded, goals, None, seed=seed, charge_compute=False, config=config,
                                       timing=tm, allow_untrained=True, timing_source=label)
                m, n = session["metrics"], len(goals)
                # over every goal: an episode the runner did not play (it ended in HOLD) is a miss
                played[key] = {"episodes": session["episodes"], **m,
                               "within_30cm": m["within_30cm"] * session["episodes"] / n,
                               "within_20cm": m["within_20cm"] * session["episodes"] / n,
                               "hit_rate": m["hit_rate"] * session["episodes"] / n,
                               "played_within_30cm": m["within_30cm"], "mode": session["mode"],
                               "faults": session["faults"],
                               "within_trained": session["timing"]["within_trained"],
                               "outside": session["timing"]["outside"]}
            point = {"series": s, "added_ms": jit if s == "jitter" else lat, "added_jitter_ms":
                     jit if s in ("jitter", "all") else 0.0, **played[key]}
            out["points"].append(point)
            if progress:
                print(f"sweep: {s} +{point['added_ms']:g} ms: within 30 cm {point['within_30cm']:.1%}"
                      f"{'' if point['within_trained'] else ' (outside the trained timing)'}", flush=True)
            files.write_json(os.path.join(out_dir, "sweep.json"), files.json_safe(out), indent=1)
    out["sessions_played"] = len(played)
    files.write_json(os.path.join(out_dir, "sweep.json"), files.json_safe(out), indent=1)
    plot_sweep(out, os.path.join(out_dir, "sweep.png"))
    return out


def measured_earlier(out_dir: str, out: dict) -> dict:
    """{(series, added_ms, added_jitter_ms): point} of the same sweep in out_dir/sweep.json (an
    interrupted or finished run of this command: every point is a fresh session of the same
    seed, so a point measured then is the point measured now); {} without one. ValueError naming
    the file if it holds another sweep (another export, goals, seed, timing or points)."""
    path = os.path.join(out_dir, "sweep.json")
    if not os.path.exists(path):
        return {}
    try:
        with open(path) as f:
            old = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable ({e}); delete it or choose a new --out") from None
    same = ("policy", "profile", "base_timing", "trained_ranges", "goals", "seed", "series", "plan")
    diff = [k for k in same if not isinstance(old, dict) or json.loads(json.dumps(files.json_safe(out[k]))) != old.get(k)]
    if diff:
        raise ValueError(f"{path} holds another sweep ({', '.join(diff)} differ); choose a new --out")
    return {(p["series"], p["added_ms"], p["added_jitter_ms"]): p for p in old["points"]}


def sweep_table(out: dict) -> str:
    """A markdown table of the sweep."""
    rows = ["| series | added (ms) | within 30 cm | within 20 cm | hit rate | trained timing |",
            "| --- | --- | --- | --- | --- | --- |"]
    for p in out["points"]:
        added = (f"{p['added_ms']:g} (+{p['added_jitter_ms']:g} jitter)" if p["series"] == "all"
                 else f"{p['added_ms']:g}")
        rows.append(f"| {p['series']} | {added} | {p['within_30cm']:.1%} | {p['within_20cm']:.1%} | "
                    f"{p['hit_rate']:.1%} | {'inside' if p['within_trained'] else 'OUTSIDE'} |")
    return "\n".join(rows)


def plot_sweep(out: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 4))
    styles = {"ball": "-o", "action": "-s", "jitter": "-^", "all": "-D"}
    for s in out["series"]:
        pts = [p for p in out["points"] if p["series"] == s]
        x = [p["added_ms"] for p in pts]
        label = {"jitter": "jitter", "all": "all together"}.get(s, f"{s} latency")
        ax.plot(x, [100 * p["within_30cm"] for p in pts], styles[s], label=f"{label}, within 30 cm")
        ax.plot(x, [100 * p["within_20cm"] for p in pts], styles[s], alpha=0.4, label=f"{label}, within 20 cm")
    ax.set_xlabel("added latency / jitter (ms)")
    ax.set_ylabel("success (%), strict")
    ax.set_title(f"{os.path.basename(out['policy'].rstrip('/'))}: {out['goals']} goals, base {out['profile']}")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6)
    fig.tight_layout()
    files.write_figure(path, fig, dpi=120)
    plt.close(fig)
