"""Profile one practice round and one pretraining chunk of a preset with jax.profiler (issue 45:
where a round's time goes), and summarize the trace: for each device and host thread group its
busy time, event count, and the events that take most of it.

    python scripts/dev/profile_round.py paper-sim OUT_DIR [--demos 256]

Writes OUT_DIR/profile_summary.json (and the perfetto trace, trace.json.gz, if it is under 15 MB).
The round and chunk are each run once to compile, then timed, then traced; the trace covers a
practice round followed by a pretraining chunk of the preset's updates, each blocked until ready.
"""
import argparse
import collections
import dataclasses
import glob
import gzip
import json
import os
import shutil
import sys
import tempfile
import time

import jax

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
from training.runconfig import preset  # noqa: E402
from training.schedule import pretrain_iterations  # noqa: E402
from training.trainer import Run  # noqa: E402


def timed_step(run, ck, it):
    t0 = time.perf_counter()
    ck, rows = run.step(ck, it)
    jax.block_until_ready(ck)
    return ck, time.perf_counter() - t0


def summarize(trace_path: str, top: int = 25) -> dict:
    """Busy time (sum of complete events, microseconds -> seconds), event count and the top events
    by total time, per process of the perfetto trace (one per device stream group and host)."""
    with gzip.open(trace_path, "rt") as f:
        events = json.load(f)["traceEvents"]
    names = {e["pid"]: e["args"]["name"] for e in events if e.get("ph") == "M" and e.get("name") == "process_name"}
    by_pid = collections.defaultdict(lambda: {"busy_s": 0.0, "events": 0, "by_name": collections.Counter(),
                                              "count": collections.Counter(), "first": None, "last": None})
    for e in events:
        if e.get("ph") != "X" or "dur" not in e:
            continue
        p = by_pid[e["pid"]]
        d = float(e["dur"]) / 1e6
        p["busy_s"] += d
        p["events"] += 1
        p["by_name"][e["name"]] += d
        p["count"][e["name"]] += 1
        ts = float(e["ts"]) / 1e6
        p["first"] = ts if p["first"] is None else min(p["first"], ts)
        p["last"] = ts + d if p["last"] is None else max(p["last"], ts + d)
    out = {}
    for pid, p in by_pid.items():
        out[names.get(pid, str(pid))] = {
            "busy_s": round(p["busy_s"], 4), "events": p["events"],
            "span_s": round((p["last"] or 0) - (p["first"] or 0), 4),
            "top": [{"name": n[:120], "total_s": round(t, 4), "count": p["count"][n]}
                    for n, t in p["by_name"].most_common(top)]}
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("preset")
    ap.add_argument("out")
    ap.add_argument("--demos", type=int, default=256)
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    scratch = tempfile.mkdtemp(prefix="ttmjx-profile-")
    cfg = preset(a.preset)
    cfg = dataclasses.replace(cfg, demos=min(cfg.demos, a.demos), run_dir=os.path.join(scratch, "run"))
    t0 = time.perf_counter()
    run = Run(cfg, None, progress=False)
    ck = run.start()
    jax.block_until_ready(ck)
    res = {"preset": a.preset, "device": str(jax.devices()[0]), "setup_s": time.perf_counter() - t0,
           "episodes_per_round": cfg.episodes_per_ssp, "updates_per_round": cfg.steps_between_ssp}
    it_p = pretrain_iterations(cfg)             # the first practice round
    _, res["round_first_s"] = timed_step(run, ck, it_p)
    _, res["round_s"] = timed_step(run, ck, it_p)
    _, res["chunk_first_s"] = timed_step(run, ck, 0)
    _, res["chunk_s"] = timed_step(run, ck, 0)
    print(json.dumps(res), flush=True)
    tdir = os.path.join(scratch, "trace")
    opts = jax.profiler.ProfileOptions()
    opts.python_tracer_level = 0        # XLA's host and device events only: the Python tracer doubles the round
    with jax.profiler.trace(tdir, create_perfetto_trace=True, profiler_options=opts):
        _, res["traced_round_s"] = timed_step(run, ck, it_p)
        _, res["traced_chunk_s"] = timed_step(run, ck, 0)
    trace = glob.glob(os.path.join(tdir, "**", "perfetto_trace.json.gz"), recursive=True)
    res["trace_files"] = trace
    if trace:
        res["summary"] = summarize(trace[0])
        if os.path.getsize(trace[0]) < 15 * 2 ** 20:
            shutil.copy(trace[0], os.path.join(a.out, "trace.json.gz"))
    with open(os.path.join(a.out, "profile_summary.json"), "w") as f:
        json.dump(res, f, indent=1)
    print(json.dumps({k: v for k, v in res.items() if k != "summary"}), flush=True)
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
