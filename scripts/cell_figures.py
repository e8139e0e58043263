"""The drivers' figures (docs/BENCHMARKS.md, docs/RESULTS.md): one exported policy played over
`ttmjx robot serve` on loopback sockets in real time (the cell drivers), with optional faults,
and the same goals and throws on the in-process station; prints one JSON object.

    python scripts/cell_figures.py EXPORT --goals 40 --seed 0 [--timing zero] [--faults SPEC]
        [--runner-cpu 0 --server-cpu 1 [--no-lead]] [--out DIR]
        [--inprocess [--action-delay-ms MS] [--gantry-late-ms MS [--lead-ms MS]]]

Over sockets it also reports the command transport delay per part (the runner's send to the
target's arrival at the station, from serve's `arrivals`; the gantry's target as sent, after its
lead), and the gantry link's measured latency and the lead applied (`gantry`: drivers/lead.py;
`--no-lead` turns the lead off, for the comparison only: [gantry] compensate_latency = false).

In process, `--gantry-late-ms` sets the gantry's part of every command that much later than the
arm's (what a slow Modbus link does over sockets, here on the simulated clock: no machine load in
the figure), led by `--lead-ms` through the cell's GantryLead (deploy/robot/drivers/lead.py; the
lead the cell would apply for that link is the lateness minus its allowance, 2 ms).

Tick timing from the episode logs: jitter = wake - deadline of executed ticks (p50/p99, ms),
missed deadlines (skipped ticks) and overruns per 1,000 ticks.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from deploy.robot.drivers import config as cellconfig  # noqa: E402


def tick_timing(out_dir: str, n: int) -> dict:
    from deploy.robot.episode_log import load_episode
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


def transport_delays(out_dir: str, n: int, arrivals: list, tol=(1e-6, 2e-6)) -> dict:
    """Command transport delay per part (ms): from the runner's send (episode log t_sent) of a
    command whose part changed to the arrival of that target at the station (serve's
    `arrivals`); a target overtaken before it arrived (coalesced, lost) is not counted."""
    from deploy.robot.episode_log import load_episode
    parts = {"arm": (slice(2, 8), tol[0]), "gantry": (slice(0, 2), tol[1])}
    got = {p: [(t, np.asarray(q)) for t, part, q in arrivals if part == p] for p in parts}
    out = {}
    for part, (sl, atol) in parts.items():
        times = np.array([t for t, _ in got[part]])
        delays, missing = [], 0
        for i in range(n):
            try:
                ep = load_episode(out_dir, f"episode_{i:04d}")
            except (OSError, ValueError):
                continue
            ts, cmds = ep.extras["t_sent"], ep.extras["commands"][:, sl]
            if part == "gantry" and "gantry_sent" in ep.extras:
                cmds = ep.extras["gantry_sent"]     # the target as sent, after its lead
            prev = None
            for t, q in zip(ts, cmds):
                if not np.isfinite(t):
                    continue
                if prev is not None and np.allclose(q, prev, rtol=0, atol=atol):
                    continue
                prev = q
                j = np.searchsorted(times, t)
                hit = next((k for k in range(j, min(j + 8, len(times)))
                            if np.allclose(got[part][k][1], q, rtol=0, atol=atol)), None)
                if hit is None:
                    missing += 1
                else:
                    delays.append(times[hit] - t)
        d = np.asarray(delays) * 1e3
        out[part] = {"n": int(d.size), "not_arrived": missing,
                     **({"p50_ms": float(np.percentile(d, 50)), "p99_ms": float(np.percentile(d, 99)),
                         "mean_ms": float(d.mean())} if d.size else {})}
    return out


def over_sockets(policy: str, goals, seed: int, faults: str, egm_hz: float, timing: str,
                 tmp: str, server_cpu: int | None = None, lead: bool = True) -> dict:
    import dataclasses

    from deploy.robot.drivers.cell import Launcher, run_cell
    from deploy.sim.serve import serving
    cfg = cellconfig.loopback_config()
    cfg = dataclasses.replace(cfg, gantry=dataclasses.replace(cfg.gantry, compensate_latency=lead))
    path = os.path.join(tmp, "cell.toml")
    with open(path, "w") as f:
        f.write(cellconfig.to_toml(cfg))
    out = os.path.join(tmp, "episodes")
    with serving(path, "--policy", policy, "--seed", str(seed), "--faults", faults, "--egm-hz", str(egm_hz),
                 "--timing", timing, "--allow-untrained-timing", cpu=server_cpu):
        summary = run_cell(policy, goals, path, out)
        launcher = Launcher(cfg.launcher)
        summary["server"] = launcher.call("stats")
        arrivals = launcher.call("arrivals")["arrivals"]
        launcher.close()
    summary["timing"] = tick_timing(out, len(goals))
    summary["transport"] = transport_delays(out, len(goals), arrivals)
    return summary


@contextlib.contextmanager
def late_gantry(late_s: float, lead_s: float):
    """While open, deploy.sim.station's SimStation sets the gantry's part of every whole command
    late_s (s) after the arm's, the gantry's target first led by lead_s (s) through the cell's
    GantryLead (the contract's limits): the in-process image of a slow gantry link."""
    from deploy.robot.drivers.lead import GantryLead
    from deploy.robot.safety import limits_from_contract, part_limits
    from deploy.sim import station as st
    base = st.SimStation

    class LateGantry(base):
        def __init__(self, cfg, contract=None, *args, **kw):
            super().__init__(cfg, contract, *args, **kw)
            self.lead = GantryLead(part_limits(limits_from_contract(contract), slice(0, 2)))

        def set_target(self, q, now, part=None):
            if part is not None:
                return super().set_target(q, now, part)
            q = np.asarray(q, np.float64)
            super().set_target(q[2:8], now, "arm")
            super().set_target(self.lead.target(q[0:2], now, lead_s), now + late_s, "gantry")

    st.SimStation = LateGantry      # run_sim builds its station by this name
    try:
        yield
    finally:
        st.SimStation = base


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("policy")
    p.add_argument("--goals", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--faults", default="")
    p.add_argument("--egm-hz", type=float, default=250.0)
    p.add_argument("--timing", default="nominal", help="the station's timing profile (both sides)")
    p.add_argument("--out", default=None, help="keep the episode logs here (default: a temp dir)")
    p.add_argument("--inprocess", action="store_true", help="the in-process station instead")
    p.add_argument("--realtime", action="store_true", help="in-process: on the real clock")
    p.add_argument("--action-delay-ms", type=float, default=None,
                   help="in-process: this action delay instead of the profile's (e.g. the measured transport)")
    p.add_argument("--gantry-late-ms", type=float, default=None,
                   help="in-process: the gantry's part of each command this much later than the arm's")
    p.add_argument("--lead-ms", type=float, default=0.0,
                   help="in-process, with --gantry-late-ms: the gantry's targets led by this much")
    p.add_argument("--runner-cpu", type=int, default=None, help="pin the runner (this process) to this core")
    p.add_argument("--server-cpu", type=int, default=None, help="pin `serve` to this core")
    p.add_argument("--no-lead", action="store_true",
                   help="over sockets: the gantry's targets without the latency lead (comparisons only)")
    a = p.parse_args()
    if a.runner_cpu is not None:
        os.sched_setaffinity(0, {a.runner_cpu})
    from deploy.robot.goals import session_goals
    goals = session_goals("uniform", a.goals, a.seed)
    tmp = a.out or tempfile.mkdtemp(prefix="cell_figures_")
    os.makedirs(tmp, exist_ok=True)
    if a.inprocess:
        import dataclasses

        from deploy.sim.station import TIMING, run_sim
        timing = TIMING[a.timing]
        if a.action_delay_ms is not None:
            timing = dataclasses.replace(timing, action_delay_s=a.action_delay_ms / 1000.0)
        # a measurement at the named profile: played even outside the trained timing (reported)
        late = (late_gantry(a.gantry_late_ms / 1000.0, a.lead_ms / 1000.0) if a.gantry_late_ms is not None
                else contextlib.nullcontext())
        with late:
            out = run_sim(a.policy, goals, os.path.join(tmp, "episodes"), seed=a.seed, timing=timing,
                          realtime=a.realtime, allow_untrained=True)
        out["trained_timing"] = {k: out["timing"][k] for k in ("within_trained", "outside")}
        out["timing"] = tick_timing(os.path.join(tmp, "episodes"), len(goals))
    else:
        out = over_sockets(a.policy, goals, a.seed, a.faults, a.egm_hz, a.timing, tmp, a.server_cpu, not a.no_lead)
    keep = ("episodes", "goals", "metrics", "faults", "driver_faults", "timing", "trained_timing", "transport", "overruns", "skipped",
            "mode", "latency_ms", "realtime_factor", "gantry")
    print(json.dumps({k: out.get(k) for k in keep} | {"faults_injected": a.faults, "seed": a.seed, "timing_profile": a.timing, "action_delay_ms": a.action_delay_ms, "out": tmp,
                                                     "lead": (not a.no_lead) if not a.inprocess else (
                                                         None if a.gantry_late_ms is None else {"gantry_late_ms": a.gantry_late_ms, "lead_ms": a.lead_ms}),
                                                     "server": (out.get("server") or {}).get("counts")},
                     default=float))


if __name__ == "__main__":
    main()
