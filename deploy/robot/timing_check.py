"""The timing an export was trained under, and the check of a station's timing against it.

deploy/sim/export.py writes the contract's `timing` section (`timing_record`): the training world's
timing model (ttmjx.world.config.Timing, its per-episode randomization included), the ranges it
drew from (`Timing.trained_ranges`: the sensor rates, [lowest, highest] of each latency and of
the command delay, the largest jitter and drop probability) and the SHA-256 of both, so the
record is hashed like the rest of the contract (and, with contract.json, by the manifest).

`trained_timing(doc)` reads it back; an export without it (an export older than the record) is an
ExportError: its timing is unknown, export the checkpoint again. `station_timing(record, name)`
is the timing a station plays: by default the trained model itself (a simulated station draws
each throw's delays within its ranges), `centre` without its randomization, or a named profile
(ttmjx.world.config.TIMING_PROFILES). `outside_trained(record, t)`
lists every way a station's timing falls outside what the policy saw; `ttmjx robot run`,
`robot serve` and `robot sweep` refuse such a station unless told to play it anyway, and then
every summary says so (`timing_summary`).

numpy only (no JAX, no MuJoCo): the robot's side imports it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math

from ttmjx.world.config import TIMING_PROFILES, Timing, from_dict, to_dict

TIMING_SECTION = "timing"
TOL_S = 1e-6               # seconds of slack in a range check (float round-off of ms sums)
RANGED = ("tracker_latency_s", "joint_latency_s", "action_delay_s", "jitter_s", "drop_prob")


class TimingError(ValueError):
    """A missing or damaged timing record, an unknown profile, or a station outside the trained
    timing (the message is one line)."""


def _canonical(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def record_hash(model: dict, ranges: dict) -> str:
    """SHA-256 of the record's model and ranges (canonical JSON)."""
    return hashlib.sha256(_canonical({"model": model, "ranges": ranges})).hexdigest()


def timing_record(timing: Timing) -> dict:
    """The contract's `timing` section for a policy trained under `timing`."""
    model, ranges = to_dict(timing), timing.trained_ranges()
    return {"model": model, "ranges": ranges, "ideal": bool(timing.ideal),
            "randomized_per_episode": max(timing.spreads()) > 0,
            "centre": to_dict(timing.centre()),
            "meaning": ("the policy was trained under `model` (ttmjx.world.config.Timing), each episode "
                        "drawing its latencies and command delay within `ranges` (s; rates in Hz, "
                        "null: every physics step); a station outside them is refused by default"),
            "sha256": record_hash(model, ranges)}


def trained_timing(doc: dict, directory: str = "") -> dict:
    """The checked `timing` section of an export's contract (TimingError if absent or damaged)."""
    where = f"{directory}: " if directory else ""
    rec = doc.get(TIMING_SECTION) if isinstance(doc, dict) else None
    if not isinstance(rec, dict):
        raise TimingError(f"{where}the export has no timing record (exported before the contract recorded "
                          f"the timing it was trained under), so no station timing can be checked against "
                          f"it; export the checkpoint again with `ttmjx export`")
    try:
        model = from_dict(Timing, rec["model"])
        ranges = rec["ranges"]
        digest = rec["sha256"]
    except (KeyError, TypeError, ValueError) as e:
        raise TimingError(f"{where}the contract's timing record is invalid ({e})") from None
    if digest != record_hash(rec["model"], ranges):
        raise TimingError(f"{where}the contract's timing record does not match its sha256; refusing it")
    if _canonical(model.trained_ranges()) != _canonical(ranges):
        raise TimingError(f"{where}the contract's timing ranges differ from its timing model's; refusing it")
    return {**rec, "timing": model}


def station_timing(record: dict, name: str | None = None) -> tuple[Timing, str]:
    """(the station's Timing, where it came from): name None or 'export' is the trained model
    itself, so a simulated station drifts per throw within the trained ranges (SimStation draws
    each throw's delays, as a real cell's drift with load); 'centre' is the trained model without
    its per-episode randomization; otherwise a TIMING_PROFILES name (TimingError if unknown)."""
    if name is None or name == "export":
        return record["timing"], "export"
    if name == "centre":
        return record["timing"].centre(), "centre"
    if name not in TIMING_PROFILES:
        raise TimingError(f"unknown station timing profile {name!r}; expected 'export' (the timing the "
                          f"policy was trained under, drawn per throw: the default), 'centre' (its centre, "
                          f"fixed) or one of {', '.join(TIMING_PROFILES)}")
    return TIMING_PROFILES[name], name


def profile_timing(name: str | None) -> Timing:
    """A station's Timing when no export says what it was trained under: a TIMING_PROFILES name
    (None: 'nominal'); TimingError naming the choices if unknown."""
    name = name or "nominal"
    if name not in TIMING_PROFILES:
        raise TimingError(f"unknown station timing profile {name!r}; expected one of {', '.join(TIMING_PROFILES)}")
    return TIMING_PROFILES[name]


def _fmt(v) -> str:
    if v is None:
        return "every physics step"
    return f"{1e3 * v:.3g} ms" if isinstance(v, float) and v < 1 else f"{v:g}"


def outside_trained(record: dict, timing: Timing) -> list[str]:
    """Every way `timing` (a station's) falls outside the record's trained ranges (empty: inside)."""
    ranges, out = record["ranges"], []
    for name in ("tracker_hz", "joint_hz"):
        want, got = ranges[name], getattr(timing, name)
        if (want is None) != (got is None) or (want is not None and not math.isclose(want, got, rel_tol=1e-9)):
            out.append(f"{name} {_fmt(got)} (trained {_fmt(want)})")
    for name in RANGED:
        lo, hi = ranges[name]
        got = getattr(timing, name)
        spread = dict(zip(("tracker_latency_s", "joint_latency_s", "action_delay_s"), timing.spreads())).get(name, 0.0)
        if spread:
            got_lo, got_hi = max(0.0, got - spread), got + spread
        else:
            got_lo = got_hi = got
        if got_lo < lo - TOL_S or got_hi > hi + TOL_S:
            unit = (lambda x: f"{x:g}") if name == "drop_prob" else (lambda x: f"{1e3 * x:.3g} ms")
            shown = unit(got) if got_lo == got_hi else f"{unit(got_lo)}..{unit(got_hi)}"
            out.append(f"{name} {shown} (trained {unit(lo)}..{unit(hi)})")
    return out


def check_station(record: dict, timing: Timing, source: str, allow_untrained: bool = False) -> dict:
    """The summary's `timing` object for a station playing `timing`; TimingError (one line) if it
    is outside the trained ranges and allow_untrained is False."""
    outside = outside_trained(record, timing)
    if outside and not allow_untrained:
        raise TimingError(f"the station's timing ({source}) is outside what the policy was trained under: "
                          f"{'; '.join(outside)}; nothing played (play it anyway with "
                          f"--allow-untrained-timing, or export a policy trained for this timing)")
    return timing_summary(record, timing, source, outside, allow_untrained)


def timing_summary(record: dict, timing: Timing, source: str, outside: list[str], allow_untrained: bool) -> dict:
    """What every session summary says about its timing."""
    return {"station": to_dict(timing), "source": source, "trained": record["model"],
            "trained_ranges": record["ranges"], "trained_sha256": record["sha256"],
            "within_trained": not outside, "outside": outside,
            "override": bool(outside and allow_untrained)}


def timing_line(summary: dict) -> str:
    """One line for a text summary ('' inside the trained range)."""
    if summary.get("within_trained", True):
        return ""
    return "TIMING OUTSIDE THE TRAINED RANGE (played by --allow-untrained-timing): " + "; ".join(summary["outside"])


def with_added(timing: Timing, **added_s) -> Timing:
    """`timing` with seconds added to named fields (tracker_latency_s=0.025, ...)."""
    # An ideal timing resets every field it is given (Timing.ideal_timing): the added delays
    # must leave it, or the sweep would play the ideal station at every point.
    return dataclasses.replace(timing, ideal_timing=False, **{k: getattr(timing, k) + v for k, v in added_s.items()})
