"""Profile one practice round and one pretraining chunk of a preset with jax.profiler (issue 45:
where a round's time goes), and summarize the trace: for each device and host thread group its
busy time, event count, and the events that take most of it.

    python scripts/dev/profile_round.py paper-sim OUT_DIR [--demos 128] [--window 0.3]

Writes OUT_DIR/profile_summary.json (and each piece's perfetto trace, trace_<piece>.json.gz, if
small). The round and the chunk are each run once to compile, then timed, then sampled by the
profiler for --window seconds from their launch.
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
import numpy as np

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
    ap.add_argument("--demos", type=int, default=128)
    ap.add_argument("--window", type=float, default=0.3, help="seconds of each piece traced")
    ap.add_argument("--no-trace", action="store_true", help="time the pieces only (no jax.profiler trace)")
    ap.add_argument("--rounds", type=int, default=1, help="timed practice rounds after the compiling one")
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
    res["rounds_s"] = [timed_step(run, ck, it_p)[1] for _ in range(a.rounds)]
    res["round_s"] = float(np.median(res["rounds_s"]))
    _, res["chunk_first_s"] = timed_step(run, ck, 0)
    _, res["chunk_s"] = timed_step(run, ck, 0)
    res["world_contacts"] = dataclasses.asdict(cfg.world.contacts)
    print(json.dumps(res), flush=True)
    if a.no_trace:
        with open(os.path.join(a.out, "profile_summary.json"), "w") as f:
            json.dump(res, f, indent=1)
        shutil.rmtree(scratch, ignore_errors=True)
        return
    # A round is 1,600 sequential physics steps of hundreds of kernels each: a whole round's trace
    # overflows CUPTI's buffers and takes minutes to convert. So each piece is sampled: the trace
    # runs for WINDOW_S from the moment the piece is launched (the round's goals, then its rollout;
    # the chunk's first updates), and is summarized per device stream.
    base = np.asarray(ck.key)
    fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
    pr = run.practice
    throws = pr.round_throws(base, it_p)
    pieces = {"round": lambda: pr.iteration(ck.state, ck.cache, run.place(fold(base, it_p)), throws,
                                            np.array([cfg.episodes_per_ssp], np.int32), run.knobs),
              "chunk": lambda: pr.iteration(ck.state, ck.cache, run.place(fold(base, 0)), None, None, run.knobs)}
    opts = jax.profiler.ProfileOptions()
    opts.python_tracer_level = 0        # XLA's host and device events only
    res["window_s"] = a.window
    res["summary"] = {}
    for name, fn in pieces.items():
        tdir = os.path.join(scratch, "trace_" + name)
        jax.profiler.start_trace(tdir, create_perfetto_trace=True, profiler_options=opts)
        t0 = time.perf_counter()
        out = fn()
        time.sleep(max(0.0, a.window - (time.perf_counter() - t0)))
        jax.profiler.stop_trace()
        jax.block_until_ready(out)
        trace = glob.glob(os.path.join(tdir, "**", "perfetto_trace.json.gz"), recursive=True)
        if trace:
            res["summary"][name] = summarize(trace[0])
            if os.path.getsize(trace[0]) < 6 * 2 ** 20:
                shutil.copy(trace[0], os.path.join(a.out, f"trace_{name}.json.gz"))
        print(json.dumps({name: {k: {"busy_s": v["busy_s"], "events": v["events"], "span_s": v["span_s"]}
                                 for k, v in res["summary"].get(name, {}).items()}}), flush=True)
    with open(os.path.join(a.out, "profile_summary.json"), "w") as f:
        json.dump(res, f, indent=1)
    print(json.dumps({k: v for k, v in res.items() if k != "summary"}), flush=True)
    shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
