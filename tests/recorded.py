"""Numbers recorded from runs, the configuration they were recorded with, and how a run on this
machine is compared with them.

XLA:CPU compiles float arithmetic differently on different x86-64 processors (vector widths,
fused multiply-adds), so a run's float32 numbers agree with a recording to the last bits only on
a processor that rounds alike; through contact physics (a landing moves with the hit's timing)
even the first evaluation's mean distance differs by percents between processors. So:

* on the processor a recording was made on (its `cpu` below: model, vector extensions, cores), the
  run must reproduce that recording to float rounding (SAME_REL), every number;
* on any processor, a run that reproduces a recording to float rounding passes (it rounds alike);
* on any other processor the run is compared with the recordings within what was measured
  across processors (ACROSS_CPUS): the schedule and the fields exactly, the pretraining losses
  (fixed demonstrations, no physics in the loop) within CROSS_CPU_LOSS_REL. What goes through
  contact physics (evaluations, practice rounds) is compared only on a recording's processor.
Determinism itself (two runs on one machine are equal bit for bit) is tested by the resumes in
tests/test_trainer.py, on whatever machine runs them.
"""
import dataclasses
import json
import os

import pytest

DATA = os.path.join(os.path.dirname(__file__), "data")
# name -> rows of tiny's metrics.jsonl (tiny_recorded below), newest last
RECORDINGS = {
    "before_renovation.json (the developers' CPU, before the One-way house renovation)":
        json.load(open(os.path.join(DATA, "before_renovation.json")))["tiny_metrics"],
    "recorded_x86_20261125.json (a 2-core x86-64 CPU, 2026-11-25)":
        json.load(open(os.path.join(DATA, "recorded_x86_20261125.json")))["tiny_metrics"],
}
# name -> the processor it was recorded on (cpu_identity()), where known
RECORDED_ON = {
    "recorded_x86_20261125.json (a 2-core x86-64 CPU, 2026-11-25)":
        json.load(open(os.path.join(DATA, "recorded_x86_20261125.json"))).get("cpu"),
}
SAME_REL, SAME_ABS = 1e-5, 1e-9     # float rounding of one computation
# Across processors, measured between the two recordings above (two x86-64 CPUs, the same
# code): the pretraining losses 7.4e-6 and 4.2e-5 relative apart; the schedule, the fields and
# the pretraining pool (cache_size) equal. From the first evaluation on the physics moves
# landings: iteration 1's eval_mean_dist 6.9% apart, iteration 3's 68%, the pool one episode
# apart at iteration 3. The bound is ~25x the largest loss difference measured.
CROSS_CPU_LOSS_REL = 1e-3
# Fields the runs write that the recordings predate (the paper's distance to goal over every
# landing, ttmjx.world.goals.landed_mean_distance): a run's rows are compared on the others.
# Since then too: success by goal region and by ensemble member (the diagnostics of `ttmjx
# report`), summaries of the same episodes that change no other number; and the loss on
# held-out demonstrations (eval.heldout), a diagnostic that changes no other number either; and
# the lane count of the program that trained the run (one seed is a batch of one since then).
ADDED_SINCE_THE_RECORDINGS = ("eval_mean_dist_landed", "seeds_in_program",
                              *(f"{phase}_{part}_30cm" for phase in ("eval", "practice")
                                for part in ("near", "middle", "far", "edges", "member0", "member1")),
                              "eval_heldout_loss", "eval_member0_heldout_loss", "eval_member1_heldout_loss")
ACROSS_CPUS = ("iteration", "phase", "trajectories", "updates", "eval_goals")
VECTOR_FLAGS = ("sse4_1", "sse4_2", "avx", "avx2", "fma", "avx512f", "avx512dq", "avx512bw", "avx512vl",
                "avx512_bf16", "avx512_fp16", "avx_vnni", "amx_bf16", "amx_tile", "asimd", "sve")

# Practice as tests/data/before_renovation.json was recorded: goals on the table, only hits
# landing near the opponent's half kept and the integrating action noise (today's defaults
# aim 0.2 m beyond the edges, keep every hit and hide the noise from the policy, which
# would change the run's numbers).
RECORDED_PRACTICE = {"practice_goal_margin": 0.0, "practice_keep": "near_half", "action_noise_form": "integrating"}


def tiny_recorded(demo_dir, run_dir, **kw):
    """The tiny run as the recordings were made: the oracle's demonstrations (conftest.py
    oracle_demos), practice as RECORDED_PRACTICE, every checkpoint kept (keep_checkpoints=10:
    tests/test_sharding.py compares weights at an early one; a resume may change it)."""
    from training import runconfig
    base = runconfig.tiny()
    kw.setdefault("train", dataclasses.replace(base.train, **RECORDED_PRACTICE))
    kw.setdefault("keep_checkpoints", 10)
    return dataclasses.replace(base, demo_dir=demo_dir, demo_source="oracle", run_dir=str(run_dir), **kw)


def cpu_identity() -> dict | None:
    """{"model", "vector_flags", "cores"} of this machine (Linux: its first processor, and the
    cores this process may use), else None. The cores count because XLA:CPU splits reductions
    by thread: an Intel Xeon host of the same model and vector flags as the 2-core recording's,
    with 48 cores, computed the first pretraining loss 7e-5 relative apart."""
    try:
        info = open("/proc/cpuinfo").read()
    except OSError:
        return None
    fields = dict(line.split(":", 1) for line in info.split("\n\n")[0].splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set((fields.get("flags") or fields.get("Features") or "").split())
    model = fields.get("model name") or fields.get("CPU part")
    return {"model": model, "vector_flags": sorted(flags & set(VECTOR_FLAGS)), "cores": len(os.sched_getaffinity(0))}


def on_a_recording_processor() -> bool:
    """Whether this machine's processor is one a recording was made on (RECORDED_ON)."""
    here = cpu_identity()
    return here is not None and any(cpu == here for cpu in RECORDED_ON.values())


# An evaluation's mean landing distance across processors: iteration 1's eval_mean_dist of the
# two recordings lie 6.9% apart (above); a bound 1.5x that.
CROSS_CPU_EVAL_DIST_REL = 0.1


def recorded_fields(row: dict) -> list[str]:
    """The fields of a metrics row that a recording holds: all but the wall time and the fields
    added since the recordings."""
    return sorted(set(row) - {"seconds", *ADDED_SINCE_THE_RECORDINGS})


def same_rows(got: list[dict], want: list[dict]) -> str | None:
    """None if the rows agree (counts exactly, floats to SAME_REL), else the first difference."""
    if [r["iteration"] for r in got] != [r["iteration"] for r in want]:
        return "iterations differ"
    for g, w in zip(got, want):
        if recorded_fields(g) != recorded_fields(w):
            return f"iteration {g['iteration']}: fields differ"
        for k, v in w.items():
            if k == "seconds":
                continue
            ok = g[k] == pytest.approx(v, rel=SAME_REL, abs=SAME_ABS) if isinstance(v, float) else g[k] == v
            if not ok:
                return f"iteration {g['iteration']}: {k} {g[k]!r} against {v!r}"
    return None


def within_cross_cpu_tolerance(got: list[dict], want: list[dict]) -> str | None:
    """None if the rows agree in what processors agree on (see above), else the first difference."""
    if [r["iteration"] for r in got] != [r["iteration"] for r in want]:
        return "iterations differ"
    for g, w in zip(got, want):
        if recorded_fields(g) != recorded_fields(w):
            return f"iteration {g['iteration']}: fields differ"
        for k in ACROSS_CPUS:
            if g.get(k) != w.get(k):
                return f"iteration {g['iteration']}: {k} {g.get(k)!r} against {w.get(k)!r}"
        if w["phase"] == "pretrain" and g["loss"] != pytest.approx(w["loss"], rel=CROSS_CPU_LOSS_REL):
            return f"iteration {g['iteration']}: pretraining loss {g['loss']!r} against {w['loss']!r}"
    return None


def assert_reproduces_a_recording(got: list[dict]) -> str:
    """Which recording `got` reproduces and how (see above); AssertionError naming the first
    difference from each recording otherwise."""
    here = cpu_identity()
    exact = {name: same_rows(got, rows) for name, rows in RECORDINGS.items()}
    for name, miss in exact.items():
        if miss is None:
            return name
    mine = [name for name, cpu in RECORDED_ON.items() if cpu is not None and cpu == here]
    assert not mine, f"this processor recorded {mine[0]}, which the run no longer reproduces: {exact[mine[0]]}"
    near = {name: within_cross_cpu_tolerance(got, rows) for name, rows in RECORDINGS.items()}
    for name, miss in near.items():
        if miss is None:
            print(f"within the cross-processor tolerance of {name} (no recording reproduced to float "
                  f"rounding: {exact}); to record this processor: {json.dumps({'cpu': here, 'tiny_metrics': got})}")
            return f"{name} (across processors)"
    raise AssertionError(f"not the recorded computation, even within the cross-processor tolerance: {near}; "
                         f"to float rounding: {exact}")
