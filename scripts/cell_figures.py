"""The drivers' figures (docs/BENCHMARKS.md, docs/RESULTS.md): one exported policy played over
`ttmjx robot serve` on loopback sockets in real time (the cell drivers), with optional faults,
and the same goals and throws on the in-process station; prints one JSON object.

    python scripts/cell_figures.py EXPORT --goals 40 --seed 0 [--faults SPEC] [--inprocess]

Tick timing from the episode logs: jitter = wake - deadline of executed ticks (p50/p99, ms),
missed deadlines (skipped ticks) and overruns per 1,000 ticks.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from deploy.drivers import config as cellconfig   # noqa: E402


def free_port(kind) -> int:
    s = socket.socket(socket.AF_INET, kind)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def tick_timing(out_dir: str, n: int) -> dict:
    from deploy.episode_log import load_episode
    late, ticks, skipped, overruns = [], 0, 0, 0
    for i in range(n):
        try:
            ep = load_episode(out_dir, f"episode_{i:04d}")
        except (OSError, ValueError):
            continue
        x = ep.extras
        ran = x["executed"].astype(bool)
        late.append((x["t_wake"] - x["t_grid"])[ran])
        ticks += int(ep.meta["ticks"])
        skipped += int(ep.meta["faults"].get("skipped", 0))
        overruns += int(ep.meta["faults"].get("overrun", 0))
    late = np.concatenate(late) * 1e3 if late else np.zeros(0)
    return {"ticks": ticks, "jitter_p50_ms": float(np.percentile(late, 50)) if late.size else None,
            "jitter_p99_ms": float(np.percentile(late, 99)) if late.size else None,
            "missed_per_1000": 1000.0 * skipped / max(ticks, 1),
            "overruns_per_1000": 1000.0 * overruns / max(ticks, 1)}


def over_sockets(policy: str, goals, seed: int, faults: str, egm_hz: float) -> dict:
    from deploy.drivers.cell import run_cell
    tmp = tempfile.mkdtemp(prefix="cell_figures_")
    cfg = cellconfig.CellConfig(
        egm=cellconfig.EgmConfig(port=free_port(socket.SOCK_DGRAM)),
        gantry=cellconfig.GantryConfig(port=free_port(socket.SOCK_STREAM)),
        tracker=cellconfig.TrackerConfig(port=free_port(socket.SOCK_DGRAM)),
        launcher=cellconfig.LauncherConfig(port=free_port(socket.SOCK_STREAM)))
    path = os.path.join(tmp, "cell.toml")
    with open(path, "w") as f:
        f.write(cellconfig.to_toml(cfg))
    env = {**os.environ, "PYTHONPATH": ROOT}
    proc = subprocess.Popen([sys.executable, "-m", "ttmjx.cli", "robot", "serve", "--config", path,
                             "--policy", policy, "--seed", str(seed), "--faults", faults,
                             "--egm-hz", str(egm_hz), "--json"], stdout=subprocess.PIPE, env=env, text=True)
    out = os.path.join(tmp, "episodes")
    try:
        assert '"ready": true' in proc.stdout.readline()
        summary = run_cell(policy, goals, path, out)
        from deploy.drivers.cell import Launcher
        launcher = Launcher(cfg.launcher)
        summary["server"] = launcher.call("stats")
        launcher.close()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    summary["timing"] = tick_timing(out, len(goals))
    return summary


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("policy")
    p.add_argument("--goals", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--faults", default="")
    p.add_argument("--egm-hz", type=float, default=250.0)
    p.add_argument("--inprocess", action="store_true", help="the in-process station instead")
    a = p.parse_args()
    from deploy.goals import session_goals
    goals = session_goals("uniform", a.goals, a.seed)
    if a.inprocess:
        from deploy.station import run_sim
        out = run_sim(a.policy, goals, seed=a.seed)
    else:
        out = over_sockets(a.policy, goals, a.seed, a.faults, a.egm_hz)
    keep = ("episodes", "goals", "metrics", "faults", "driver_faults", "timing", "overruns", "skipped",
            "mode", "latency_ms", "realtime_factor")
    print(json.dumps({k: out.get(k) for k in keep} | {"faults_injected": a.faults, "seed": a.seed,
                                                     "server": (out.get("server") or {}).get("counts")},
                     default=float))


if __name__ == "__main__":
    main()
