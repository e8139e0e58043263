"""Numbers recorded from runs, and which recording a run on this machine should reproduce.

XLA:CPU compiles float arithmetic differently on different x86-64 processors (vector widths,
fused multiply-adds), so a run's float32 numbers agree with a recording to the last bits only on
a processor that rounds alike; through contact physics (a landing moves with the hit's timing)
even the first evaluation's mean distance differs by percents between processors. A test of
"the same numbers as recorded" therefore holds one recording per kind of processor met so far
and asks the run to reproduce one of them to float rounding. A run that reproduces none but
whose first chunk of updates agrees with them to 1e-3 ran on a processor not yet recorded:
the test is skipped, saying so and printing what to record. Anything further off fails.
"""
import json
import os

import pytest

DATA = os.path.join(os.path.dirname(__file__), "data")
# name -> rows of tiny's metrics.jsonl (tests/test_trainer.py RECORDED_PRACTICE), newest last
RECORDINGS = {
    "before_renovation.json (the developers' CPU, before the One-way house renovation)":
        json.load(open(os.path.join(DATA, "before_renovation.json")))["tiny_metrics"],
    "recorded_x86_20261125.json (a 2-core x86-64 CPU, 2026-11-25)":
        json.load(open(os.path.join(DATA, "recorded_x86_20261125.json")))["tiny_metrics"],
}
SAME_REL, SAME_ABS = 1e-5, 1e-9     # float rounding of one computation
FIRST_LOSS_REL = 1e-3               # the same program on another processor: the first 20 updates


def same_rows(got: list[dict], want: list[dict]) -> str | None:
    """None if the rows agree (counts exactly, floats to SAME_REL), else the first difference."""
    if [r["iteration"] for r in got] != [r["iteration"] for r in want]:
        return "iterations differ"
    for g, w in zip(got, want):
        if sorted(set(g) - {"seconds"}) != sorted(set(w) - {"seconds"}):
            return f"iteration {g['iteration']}: fields differ"
        for k, v in w.items():
            if k == "seconds":
                continue
            ok = g[k] == pytest.approx(v, rel=SAME_REL, abs=SAME_ABS) if isinstance(v, float) else g[k] == v
            if not ok:
                return f"iteration {g['iteration']}: {k} {g[k]!r} against {v!r}"
    return None


def assert_reproduces_a_recording(got: list[dict]) -> str:
    """The name of the recording `got` reproduces; skip on an unrecorded processor (see above);
    AssertionError if the run is not the recorded computation at all."""
    misses = {name: same_rows(got, rows) for name, rows in RECORDINGS.items()}
    for name, miss in misses.items():
        if miss is None:
            return name
    first = got[0]["loss"]
    if any(first == pytest.approx(rows[0]["loss"], rel=FIRST_LOSS_REL) for rows in RECORDINGS.values()):
        pytest.skip(f"this processor's float rounding matches no recording ({misses}); if the code is unchanged, "
                    f"record these rows as a new tests/data/recorded_*.json: {json.dumps(got)}")
    raise AssertionError(f"not the recorded computation: first loss {first} against "
                         f"{[rows[0]['loss'] for rows in RECORDINGS.values()]}; {misses}")
