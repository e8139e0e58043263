"""Checks that an output means what docs/DATA.md says, shared by the tests of each output:
`ttmjx eval --out` (summary.json, episodes.csv) and a run's metrics.jsonl."""
import csv
import json
import os

import numpy as np
import pytest

from ttmjx.world.config import Table
from ttmjx.world.goals import GOAL_REGIONS

GOAL_METRICS = {"within_30cm", "within_20cm", "hit_rate", "on_table_rate", "mean_dist", "mean_dist_landed", "goals"}
EPISODE_COLUMNS = ["goal_x", "goal_y", "hit", "landing_x", "landing_y", "on_opponent_half", "distance_m",
                   "success_30cm", "success_20cm"]


def check_eval_out(out: str, printed: dict, table: Table = Table()) -> list[dict]:
    """summary.json is the printed object with the documented keys, and episodes.csv's rows add up
    to it (DATA.md, "Evaluation output"); returns the rows."""
    assert sorted(os.listdir(out)) == ["episodes.csv", "summary.json", "tracks.npz"]
    assert json.load(open(os.path.join(out, "summary.json"))) == printed
    assert set(printed) == GOAL_METRICS | {"distribution", "trajectories", "step"} | (
        {"per_goal"} if "per_goal" in printed else set())
    rows = list(csv.DictReader(open(os.path.join(out, "episodes.csv"))))
    assert list(rows[0]) == EPISODE_COLUMNS and printed["goals"] == len(rows)
    col = lambda k: np.array([int(r[k]) for r in rows])  # noqa: E731
    for key, name in [("hit_rate", "hit"), ("on_table_rate", "on_opponent_half"),
                      ("within_30cm", "success_30cm"), ("within_20cm", "success_20cm")]:
        assert printed[key] == pytest.approx(col(name).mean()), key
    for r in rows:
        landed = r["landing_x"] != ""
        assert landed <= (r["hit"] == "1") and (r["distance_m"] != "") == landed
        if r["on_opponent_half"] == "1":      # a first bounce on the opponent's half: on its footprint
            x, y = float(r["landing_x"]), float(r["landing_y"])
            assert -0.02 <= x <= table.half_length + 0.02 and abs(y) <= table.half_width + 0.02, (x, y)
        else:
            assert r["success_30cm"] == r["success_20cm"] == "0"
        if landed:
            d = np.hypot(float(r["landing_x"]) - float(r["goal_x"]), float(r["landing_y"]) - float(r["goal_y"]))
            assert float(r["distance_m"]) == pytest.approx(d, abs=1e-6)
            assert r["success_30cm"] == str(int(r["on_opponent_half"] == "1" and d <= 0.30))
            assert r["success_20cm"] == str(int(r["on_opponent_half"] == "1" and d <= 0.20))
    on_table = np.array([float(r["distance_m"]) for r in rows if r["on_opponent_half"] == "1"])
    came_down = np.array([float(r["distance_m"]) for r in rows if r["distance_m"] != ""])
    assert printed["mean_dist"] == pytest.approx(on_table.mean())
    assert printed["mean_dist_landed"] == pytest.approx(came_down.mean())    # either half, or beside the table
    return rows


def check_metrics_rows(rows: list[dict], cfg) -> None:
    """Every key of a run's metrics.jsonl rows is one DATA.md names ("Run directories") and means it."""
    regions = {f"{g}_30cm" for g in GOAL_REGIONS}
    members = {f"member{i}_30cm" for i in range(cfg.train.members)} if cfg.train.members > 1 else set()
    base = {"iteration", "phase", "trajectories", "updates", "cache_size", "loss", "seconds", "seeds_in_program"}
    practice = {f"practice_{k}" for k in {"hit_rate", "on_table_rate", "within_30cm", "within_20cm", "kept"}
                | regions | members}
    evaluation = {f"eval_{k}" for k in GOAL_METRICS | regions | members}
    # the loss on held-out demonstrations (ttmjx train logs it; a run with demonstrations only)
    heldout = {"eval_heldout_loss"} | ({f"eval_member{i}_heldout_loss" for i in range(cfg.train.members)}
                                       if cfg.train.members > 1 else set())
    assert [r["iteration"] for r in rows] == list(range(len(rows)))
    seen = 0
    for r in rows:
        keys = set(r)
        assert base <= keys and keys <= base | practice | evaluation | heldout, keys - base - practice - evaluation
        assert keys & heldout in (set(), heldout) and (not keys & heldout or "eval_goals" in keys)
        for k in keys & heldout:
            assert np.isfinite(r[k]) and r[k] >= 0, k
        assert r["phase"] in ("pretrain", "practice", "lfp")
        assert (practice <= keys) == (r["phase"] == "practice") and (keys & practice in (set(), practice))
        assert keys & evaluation in (set(), evaluation)
        assert r["trajectories"] >= seen and r["cache_size"] <= cfg.train.capacity and r["seconds"] > 0
        if r["phase"] == "practice":
            assert r["trajectories"] - seen <= cfg.episodes_per_ssp
            assert 0 <= r["practice_kept"] <= r["trajectories"] - seen
            for k in practice - {"practice_kept"}:
                assert r[k] is None or 0 <= r[k] <= 1, k
            assert r["practice_within_20cm"] <= r["practice_within_30cm"] <= r["practice_on_table_rate"] <= r["practice_hit_rate"]
        if "eval_goals" in r:
            assert r["eval_goals"] == cfg.eval_goals
            assert r["eval_within_20cm"] <= r["eval_within_30cm"] <= r["eval_on_table_rate"] <= r["eval_hit_rate"]
        seen = r["trajectories"]
    assert rows[-1]["trajectories"] == cfg.total_trajectories
    assert any("eval_goals" in r for r in rows) and any(r["phase"] == "practice" for r in rows)


SWEEP_KEYS = {"policy", "profile", "base_timing", "trained_ranges", "goals", "seed", "series", "plan", "points",
              "sessions_played"}
SWEEP_POINT_KEYS = GOAL_METRICS | {"series", "added_ms", "added_jitter_ms", "episodes", "played_within_30cm",
                                   "on_opponent", "mode", "faults", "within_trained", "outside"}


def check_sweep(out_dir: str, returned: dict, policy_dir: str, goals, seed: int, added_ms, jitter_ms) -> dict:
    """`ttmjx robot sweep`'s sweep.json holds the keys DATA.md ("Timing sweeps") names and they mean
    it: the plan, the base timing (the contract's centre), the points series by series, rates over
    every goal, `within_trained`/`outside` as the timing check judges each point's timing, and
    `sessions_played` the distinct timings. Returns sweep.json."""
    import dataclasses

    from deploy.robot.timing_check import outside_trained, trained_timing
    from deploy.robot.exported import read_contract
    from deploy.robot.modes import Mode
    from ttmjx.world import files
    from ttmjx.world.config import Timing, from_dict, to_dict
    saved = json.load(open(os.path.join(out_dir, "sweep.json")))
    assert saved == json.loads(json.dumps(files.json_safe(returned)))
    assert set(saved) == SWEEP_KEYS, set(saved) ^ SWEEP_KEYS
    doc = read_contract(policy_dir)
    record = trained_timing(doc, policy_dir)
    assert saved["policy"] == policy_dir and saved["profile"] == "export" and saved["seed"] == seed
    assert saved["base_timing"] == json.loads(json.dumps(to_dict(record["timing"].centre())))
    assert saved["base_timing"] == doc["timing"]["centre"] and saved["trained_ranges"] == doc["timing"]["ranges"]
    goals = np.asarray(goals, np.float64)
    assert saved["goals"] == len(goals)
    assert set(saved["plan"]) == {"export", "goals", "added_ms", "jitter_ms"}
    assert saved["plan"]["export"] == files.sha256_file(os.path.join(policy_dir, "manifest.json"))
    assert np.allclose(saved["plan"]["goals"], goals, atol=1e-6)
    assert saved["plan"]["added_ms"] == list(added_ms) and saved["plan"]["jitter_ms"] == list(jitter_ms)
    base = from_dict(Timing, saved["base_timing"])
    added = {"ball": ("tracker_latency_s",), "action": ("action_delay_s",), "jitter": ("jitter_s",),
             "all": ("tracker_latency_s", "action_delay_s", "jitter_s")}

    def timing_at(s, a, j):                       # DATA.md: each series' ms added to its Timing fields
        return dataclasses.replace(base, ideal_timing=False, **{
            f: getattr(base, f) + (j if f == "jitter_s" else a) / 1000.0 for f in added[s]})
    want = [(s, j if s == "jitter" else a, j if s in ("jitter", "all") else 0.0)
            for s in saved["series"] for a, j in zip(added_ms, jitter_ms)]
    assert [(p["series"], p["added_ms"], p["added_jitter_ms"]) for p in saved["points"]] == want
    timings = set()
    for p, (s, a, j) in zip(saved["points"], want):
        assert set(p) == SWEEP_POINT_KEYS, set(p) ^ SWEEP_POINT_KEYS
        tm = timing_at(s, a, j)
        timings.add(tuple(sorted(to_dict(tm).items())))
        assert p["outside"] == outside_trained(record, tm) and p["within_trained"] == (not p["outside"])
        n = p["episodes"]
        assert 0 < n <= len(goals) and p["goals"] == n
        assert 0 <= p["hit_rate"] <= n / len(goals)
        assert p["within_30cm"] == pytest.approx(p["played_within_30cm"] * n / len(goals))
        assert p["within_20cm"] <= p["within_30cm"] <= p["hit_rate"]
        assert p["on_opponent"] == pytest.approx(p["on_table_rate"])
        assert p["mode"] in {m.value for m in Mode} and (p["mode"] == "idle") <= (n == len(goals))
        assert all(isinstance(v, int) and v >= 0 for v in p["faults"].values())
    assert saved["sessions_played"] == len(timings)
    return saved


def data_md_row(first_cell: str) -> str:
    """The row of a table in docs/DATA.md whose first cell is `first_cell` (e.g. '`contract.json`')."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "DATA.md")
    rows = [line for line in open(path) if line.startswith(f"| {first_cell} |")]
    assert len(rows) == 1, (first_cell, len(rows))
    return rows[0]


def named_in(row: str, keys) -> None:
    """Every key is named in the DATA.md row, in backquotes."""
    missing = sorted(k for k in keys if f"`{k}`" not in row)
    assert not missing, f"not documented in docs/DATA.md: {missing}"


SESSION_KEYS = {"episodes", "goals", "mode", "overruns", "skipped", "faults", "ends", "policy_hash", "control_hz",
                "wall_s", "out"}
SIM_SESSION_KEYS = {"metrics", "violations", "violations_true_limits", "max_speed_fraction", "commands", "landings",
                    "latency_ms", "sim_s", "realtime_factor", "policy", "self_test_error", "distribution", "seed",
                    "timing", "throw_delays_s"}
SESSION_TIMING_KEYS = {"station", "source", "trained", "trained_ranges", "trained_sha256", "within_trained",
                       "outside", "override"}


def check_sim_session(out_dir: str, printed: dict, policy_dir: str, goals, seed: int) -> None:
    """`ttmjx robot run --station sim --out DIR`'s session.json is the summary printed, with the keys
    DATA.md ("The session's summary") names, and they mean it: recomputed from the episode logs
    (ends, metrics, landings, latencies), the export (hash, rate, timing record) and each other."""
    from deploy.robot.episode_log import load_episode
    from deploy.robot.exported import WEIGHTS_FILE, read_contract
    from deploy.robot.modes import Mode
    from ttmjx.world import files, record
    from ttmjx.world.goals import goal_metrics
    saved = json.load(open(os.path.join(out_dir, "session.json")))
    assert saved == json.loads(json.dumps(files.json_safe(printed)))
    assert set(saved) == SESSION_KEYS | SIM_SESSION_KEYS, set(saved) ^ (SESSION_KEYS | SIM_SESSION_KEYS)
    n = saved["episodes"]
    assert saved["goals"] == len(goals) and 0 < n <= len(goals) and saved["out"] == out_dir
    assert saved["mode"] in {m.value for m in Mode} and (saved["mode"] == "idle") <= (n == len(goals))
    assert saved["overruns"] >= 0 and saved["skipped"] >= 0 and saved["skipped"] <= saved["faults"].get("skipped", 0)
    assert all(isinstance(v, int) and v > 0 for v in saved["faults"].values())
    eps = [load_episode(out_dir, f"episode_{i:04d}") for i in range(n)]
    assert saved["ends"] == [e.meta["end"] for e in eps]
    assert all(e == "done" or e.startswith("hold: ") for e in saved["ends"])
    assert saved["policy_hash"] == "sha256:" + files.sha256_file(os.path.join(policy_dir, WEIGHTS_FILE))
    contract = read_contract(policy_dir)
    assert saved["control_hz"] == contract["runtime"]["control_hz"]
    tr = record.concat([e.traj for e in eps])
    want = goal_metrics(tr.landing, tr.goal, tr.hit, tr.on_opponent)
    assert set(saved["metrics"]) == GOAL_METRICS | {"on_opponent"}
    for k, v in want.items():                               # NaN (none landed) is written as null
        assert saved["metrics"][k] == (None if v != v else pytest.approx(v)), k
    assert saved["metrics"]["on_opponent"] == pytest.approx(float(np.mean(tr.on_opponent)))
    np.testing.assert_allclose(np.array(saved["landings"], np.float64), tr.landing, rtol=0, atol=1e-6)
    lat = np.concatenate([e.extras["t_sent"] - e.extras["t_grid"] for e in eps]) * 1e3
    lat = lat[np.isfinite(lat)]
    assert saved["latency_ms"] == pytest.approx({"p50": np.percentile(lat, 50), "p99": np.percentile(lat, 99),
                                                 "max": lat.max()})
    assert set(saved["violations"]) == set(saved["violations_true_limits"])
    assert all(v == 0 for v in saved["violations_true_limits"].values()) and 0 < saved["max_speed_fraction"] <= 1
    assert saved["commands"] >= sum(int(e.extras["executed"].sum()) for e in eps)
    assert saved["realtime_factor"] == pytest.approx(saved["sim_s"] / saved["wall_s"])
    assert saved["policy"] == policy_dir and saved["seed"] == seed and 0 <= saved["self_test_error"] <= 1e-5
    assert saved["distribution"] == contract["world"]["throws"]["name"]
    t = saved["timing"]
    assert set(t) == SESSION_TIMING_KEYS, set(t) ^ SESSION_TIMING_KEYS
    rec = contract["timing"]
    assert (t["trained"], t["trained_ranges"], t["trained_sha256"]) == (rec["model"], rec["ranges"], rec["sha256"])
    assert t["source"] == "export" and t["station"] == rec["model"]      # default: the trained model, drawn per throw
    assert t["within_trained"] == (not t["outside"]) and (not t["override"] or t["outside"])
    assert t["within_trained"] and not t["override"]                     # the trained timing is inside
    assert len(saved["throw_delays_s"]) == n
    names = ("tracker_latency_s", "joint_latency_s", "action_delay_s")
    for delays in saved["throw_delays_s"]:
        for name, d in zip(names, delays):
            lo, hi = rec["ranges"][name]
            assert lo - 1e-9 <= d <= hi + 1e-9, (name, d)


def data_md_section(heading: str) -> str:
    """The text of docs/DATA.md's section `heading` (e.g. '## Robot-runner episode logs') up to
    the next heading of its level or above."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "docs", "DATA.md")
    text = open(path).read()
    level = heading.split(" ")[0]
    start = text.index(heading + "\n")
    ends = [text.find("\n" + "#" * k + " ", start + 1) for k in range(1, len(level) + 1)]
    ends = [e for e in ends if e >= 0]
    return text[start:min(ends) if ends else len(text)]


EPISODE_META_KEYS = {"schema_version", "n", "horizon", "source", "policy_hash", "episode", "goal", "t0", "end",
                     "ticks", "executed", "faults", "max_latency_s", "events_detected", "contract", "runner",
                     "transitions"}
SIM_EPISODE_META_KEYS = {"station", "events"}
EVENT_KEYS = {"t_launch", "launch_pos", "launch_vel", "launch_spin", "aim", "hit", "t_hit", "bounce_own", "net",
              "landed", "landing", "t_land", "on_opponent", "fell", "done", "t_done"}


def check_episode_meta(out_dir: str, i: int, session: dict, goals, contract, runner_config,
                       station: str = "sim") -> dict:
    """Episode i's `episode_<i:04d>.meta.json` of a `ttmjx robot run --station sim|fake --out DIR`
    session holds the keys DATA.md ("Robot-runner episode logs") names, and each means it:
    recomputed from the episode's record and deploy arrays, the session's summary, the goals,
    the contract played and the runner's settings; the simulated station's events against the
    record they completed, the fake station's record left without outcomes. Returns the metadata."""
    import dataclasses

    from deploy.robot.contract import contract_to_dict
    from deploy.robot.episode_log import load_episode
    from deploy.robot.safety import FAULTS
    from ttmjx.world import record
    ep = load_episode(out_dir, f"episode_{i:04d}")
    meta, tr, x = ep.meta, ep.traj, ep.extras
    keys = EPISODE_META_KEYS | (SIM_EPISODE_META_KEYS if station == "sim" else set())
    assert set(meta) == keys, set(meta) ^ keys
    named_in(data_md_section("## Robot-runner episode logs"), keys | EVENT_KEYS)
    T, dt = contract.horizon, 1.0 / contract.control_hz
    assert meta["schema_version"] == record.SCHEMA_VERSION and meta["n"] == 1 == tr.size
    assert meta["horizon"] == T == tr.obs.shape[1]
    assert meta["source"] == "deploy.robot.runner" and meta["policy_hash"] == session["policy_hash"]
    assert meta["episode"] == i
    np.testing.assert_array_equal(np.float32(meta["goal"]), np.float32(goals[i]))
    np.testing.assert_array_equal(np.float32(meta["goal"]), tr.goal[0])
    valid = tr.valid[0]
    assert meta["ticks"] == int(valid.sum()) and meta["end"] == session["ends"][i]
    assert (meta["end"] == "done") <= (meta["ticks"] == T)
    np.testing.assert_allclose(x["t_grid"][valid], meta["t0"] + np.arange(T)[valid] * dt, rtol=0, atol=1e-9)
    assert meta["executed"] == int(x["executed"].sum()) and 0 < meta["executed"] <= meta["ticks"]
    assert set(meta["faults"]) == set(FAULTS)
    for name, bit in FAULTS.items():
        assert meta["faults"][name] == int(np.sum((x["faults"] & bit) != 0)), name
    lat = x["t_sent"] - x["t_grid"]
    assert meta["max_latency_s"] == pytest.approx(float(np.nanmax(lat)), abs=1e-12) and meta["max_latency_s"] >= 0
    assert meta["contract"] == json.loads(json.dumps(contract_to_dict(contract)))
    assert meta["runner"] == json.loads(json.dumps(dataclasses.asdict(runner_config)))
    tt = meta["transitions"]
    assert all(len(t) == 4 for t in tt) and [t[1:3] for t in tt][0] == ["armed", "running"]
    assert tt[-1][2] == ("idle" if meta["end"] == "done" else "hold") and all(a[2] == b[1] for a, b in zip(tt, tt[1:]))
    assert [t[0] for t in tt] == sorted(t[0] for t in tt) and tt[0][0] >= meta["t0"]
    if station == "fake":                 # no events: the outcome fields the runner cannot see
        assert meta["events_detected"] is False
        assert not tr.hit[0] and tr.hit_step[0] == -1 and np.isnan(tr.landing[0]).all()
        assert not (tr.on_opponent[0] or tr.bounce_own[0] or tr.net[0])
        assert np.isnan(tr.launch_spin[0]).all() and np.isnan(tr.aim[0]).all()
        return meta
    # the simulated station's events: they completed the record
    assert meta["station"] == "sim" and meta["events_detected"] is True
    ev = meta["events"]
    assert set(ev) == EVENT_KEYS, set(ev) ^ EVENT_KEYS
    for k in ("launch_pos", "launch_vel", "launch_spin", "aim"):
        np.testing.assert_allclose(np.array(ev[k], np.float64), getattr(tr, k)[0], rtol=0, atol=1e-6, err_msg=k)
    assert ev["t_launch"] <= meta["t0"] and ev["hit"] == bool(tr.hit[0]) and ev["net"] == bool(tr.net[0])
    assert ev["bounce_own"] == bool(tr.bounce_own[0])
    assert (ev["t_hit"] is not None) == ev["hit"]
    if ev["hit"]:
        assert tr.hit_step[0] == min(T - 1, int(np.floor((ev["t_hit"] - meta["t0"]) / dt + 1e-9)))
    else:
        assert tr.hit_step[0] == -1
    assert ev["done"] and (ev["t_done"] is not None) and ev["fell"] == (not ev["landed"])
    assert (ev["t_land"] is not None) == ev["landed"] and (not ev["landed"] or ev["t_land"] == ev["t_done"])
    if ev["hit"] and ev["landed"]:
        np.testing.assert_allclose(np.array(ev["landing"], np.float64), tr.landing[0], rtol=0, atol=1e-6)
        assert ev["t_hit"] < ev["t_land"]
    else:
        assert np.isnan(tr.landing[0]).all()
    assert bool(tr.on_opponent[0]) == (ev["hit"] and ev["landed"] and ev["on_opponent"])
    return meta


TABLE_ENTRIES = ["curves.png", "landings", "results", "runs", "summary.json", "table.md"]
RESULT_KEYS = {"variant", "seed", "run_dir", "final", "curve", "landings", "wall_s", "attempts", "config"}
TABLE_METRICS = [("mean_dist", "mean distance (m)", 1.0, 2), ("mean_dist_landed", "distance, every landing (m)", 1.0, 2),
                 ("within_30cm", "<= 30 cm (%)", 100.0, 1), ("within_20cm", "<= 20 cm (%)", 100.0, 1),
                 ("hit_rate", "hit rate (%)", 100.0, 1), ("on_table_rate", "on table (%)", 100.0, 1)]
# Two-sided 95% quantiles of Student's t by degrees of freedom (any statistics table).
STUDENT_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571}


def check_table_result(out: str, path: str, table: Table = Table()) -> dict:
    """One `results/<variant>-seed<s>.json` of an experiment table holds the keys DATA.md
    ("Experiment tables") names and they mean it: the cell, its run, its configuration, the
    final metrics recomputed from its landings, a curve that ends at the budget. Returns it."""
    from ttmjx.world.goals import goal_metrics
    r = json.load(open(path))
    name = os.path.basename(path)[:-len(".json")]
    assert set(r) - {"seeds_in_program"} == RESULT_KEYS, set(r) ^ RESULT_KEYS
    assert name == f"{r['variant']}-seed{r['seed']}" and r["run_dir"] == os.path.join(out, "runs", name)
    assert os.path.isdir(r["run_dir"])
    assert json.load(open(os.path.join(r["run_dir"], "wall_time.json"))) == {"wall_s": r["wall_s"],
                                                                           "attempts": r["attempts"]}
    assert r["wall_s"] > 0 and r["attempts"] >= 1 and r.get("seeds_in_program", 2) >= 2
    rl = "method" in r["config"]
    run = r["config"]["run"] if rl else r["config"]
    assert run["seed"] == r["seed"] and run["run_dir"] == r["run_dir"]
    assert (r["config"]["method"] == r["variant"]) if rl else set(r["config"]) >= {"world", "policy", "train", "demos"}
    lands, g = r["landings"], run["eval_goals"]
    assert set(lands) == {"goal", "landing", "hit", "on_opponent"} and all(len(v) == g for v in lands.values())
    goal = np.array(lands["goal"], np.float64)
    landing = np.array([[np.nan if v is None else v for v in p] for p in lands["landing"]], np.float64)
    hit, on = np.array(lands["hit"], bool), np.array(lands["on_opponent"], bool)
    assert np.all(np.isnan(landing).all(1) | np.isfinite(landing).all(1)) and np.all(hit | np.isnan(landing).all(1))
    assert np.all((goal[:, 0] >= 0) & (goal[:, 0] <= table.half_length) & (np.abs(goal[:, 1]) <= table.half_width))
    assert np.all(hit[on] & np.isfinite(landing[on]).all(1))
    x, y = landing[on, 0], landing[on, 1]                       # a first bounce on the opponent's half
    assert np.all((x >= -0.02) & (x <= table.half_length + 0.02) & (np.abs(y) <= table.half_width + 0.02))
    assert set(r["final"]) == GOAL_METRICS and r["final"]["goals"] == g
    want = goal_metrics(landing, goal, hit, on)                  # from the rounded landings: 0.1 mm
    for k, v in want.items():
        assert (r["final"][k] is None) == (v != v), k
        if v == v:
            assert r["final"][k] == pytest.approx(v, abs=2e-4), k
    curve = r["curve"]
    assert curve and [p["trajectories"] for p in curve] == sorted(p["trajectories"] for p in curve)
    assert curve[-1]["trajectories"] == run["total_trajectories"]
    for p in curve:
        assert set(p) >= {"trajectories", "updates", "cache_size"} | GOAL_METRICS and p["goals"] == g
        assert p["within_20cm"] <= p["within_30cm"] <= p["on_table_rate"] <= p["hit_rate"] <= 1
        if rl:
            assert set(p) == {"trajectories", "updates", "cache_size", "env_steps"} | GOAL_METRICS, set(p)
            horizon = run["world"]["episode_s"] * run["world"]["control_hz"]
            assert p["env_steps"] == pytest.approx(p["trajectories"] * horizon)
            assert p["updates"] == p["cache_size"] == 0
        else:
            extra = set(p) - {"trajectories", "updates", "cache_size"} - GOAL_METRICS
            members = {f"member{i}_30cm" for i in range(run["train"]["members"])} if run["train"]["members"] > 1 else set()
            assert extra == {f"{k}_30cm" for k in GOAL_REGIONS} | members, extra
            assert 0 <= p["cache_size"] <= run["train"]["capacity"] and p["updates"] >= 0
    return r


def check_table_out(out: str, printed: dict, variants: list[str], scale: str, command: str) -> dict:
    """`ttmjx ablate NAME --out DIR --json` or `ttmjx baseline METHODS --out DIR --json`: the
    directory holds what DATA.md ("Experiment tables") lists; every result as check_table_result;
    summary.json is the printed object without its last keys, each key meaning what DATA.md says
    (the intervals recomputed from the results with a statistics table's t); table.md shows those
    numbers. variants: the ablation's variants or the baseline's methods, in order; command: the
    command line that wrote it ('' through the Python API). Returns summary.json."""
    import math
    assert sorted(n for n in os.listdir(out) if not n.startswith(".")) == TABLE_ENTRIES
    names = sorted(os.listdir(os.path.join(out, "results")))
    results = [check_table_result(out, os.path.join(out, "results", n)) for n in names]
    saved = json.load(open(os.path.join(out, "summary.json")))
    assert {k: v for k, v in printed.items() if k not in ("cells_run", "stopped_by_signal", "unfinished")} == saved
    assert printed["stopped_by_signal"] == 0 and "unfinished" not in printed
    baseline = saved["ablation"] == "baselines"
    header = {"ablation", "scale", "command", "title", "subtitle", "variants", "outputs"}
    assert set(saved) == header | (set() if baseline else {"bootstrap", "variants_overrides"}), set(saved)
    named_in(data_md_section("## Experiment tables (`ttmjx ablate NAME --out DIR`, `ttmjx baseline METHODS --out DIR`)"),
             set(saved) | set(printed) | RESULT_KEYS | {"seeds_in_program"} | {"mean", "half", "n", "values"})
    assert saved["scale"] == scale and saved["command"] == command
    configs = [r["config"].get("run", r["config"]) for r in results]
    budgets = sorted({c["total_trajectories"] for c in configs})
    assert f"{'/'.join(f'{t:,}' for t in budgets)} trajectories per cell" in saved["subtitle"]
    assert "seed 1234" in saved["subtitle"]
    if baseline:
        assert saved["title"] == f"baselines ({scale})"
    else:
        sources = sorted({c["demo_source"] for c in configs if c["demos"] > 0})
        none = any(c["demos"] == 0 for c in configs)
        want = ", ".join(sources) + (" (and none: GCSL)" if sources and none else "none (GCSL)" if none else "")
        assert saved["bootstrap"] == want and saved["title"] == f"ablate {saved['ablation']} ({scale}; bootstrap: {want})"
        assert set(saved["variants_overrides"]) == set(variants)
    order = list(variants) + sorted({r["variant"] for r in results} - set(variants))
    assert [v["variant"] for v in saved["variants"]] == order
    rows = []
    for v in saved["variants"]:
        mine = sorted((r for r in results if r["variant"] == v["variant"]), key=lambda r: r["seed"])
        assert set(v) == {"variant", "seeds", "metrics", "wall_s"}
        assert v["seeds"] == [r["seed"] for r in mine] and v["wall_s"] == [r["wall_s"] for r in mine]
        assert set(v["metrics"]) == {k for k, *_ in TABLE_METRICS if any(k in r["final"] for r in mine)}
        cells = {}
        for k, _, scale_, digits in TABLE_METRICS:
            if k not in v["metrics"]:
                continue
            m = v["metrics"][k]
            values = [r["final"][k] for r in mine]
            got = np.array([x for x in values if x is not None], np.float64)
            assert set(m) == {"mean", "half", "n", "values"} and m["values"] == values and m["n"] == len(got)
            assert m["mean"] == (pytest.approx(got.mean()) if len(got) else None)
            half = (STUDENT_T975[len(got) - 1] * got.std(ddof=1) / math.sqrt(len(got))) if len(got) > 1 else None
            assert m["half"] == (None if half is None else pytest.approx(half, rel=1e-3, abs=1e-12)), (k, m, half)
            cells[k] = ("-" if m["mean"] is None else f"{m['mean'] * scale_:.{digits}f}"
                        + ("" if m["half"] is None else f" +- {m['half'] * scale_:.{digits}f}"))
        rows.append((v["variant"], len(mine), cells))
    shown = [c for c in TABLE_METRICS if any(c[0] in v["metrics"] for v in saved["variants"])]
    lines = open(os.path.join(out, "table.md")).read().splitlines()
    assert lines[0] == f"### {saved['title']}" and lines[2] == saved["subtitle"]
    assert lines[4] == "| variant | seeds | " + " | ".join(c[1] for c in shown) + " |"
    assert lines[5] == "| --- | --- |" + " --- |" * len(shown) and lines[6 + len(rows)] == ""
    for (name, n, cells), line in zip(rows, lines[6:6 + len(rows)]):
        want = [cells.get(k, "-") for k, *_ in shown]
        assert line == f"| {name} | {n} | " + " | ".join(want) + " |", (line, want)
    outputs = saved["outputs"]
    finished = [v["variant"] for v in saved["variants"] if v["seeds"]]
    assert outputs == {"table": os.path.join(out, "table.md"), "curves": os.path.join(out, "curves.png"),
                       "landings": {v: os.path.join(out, "landings", f"{v}.png") for v in finished},
                       "summary": os.path.join(out, "summary.json")}
    assert sorted(os.listdir(os.path.join(out, "landings"))) == sorted(f"{v}.png" for v in finished)
    for png in [outputs["curves"], *outputs["landings"].values()]:
        with open(png, "rb") as f:
            assert f.read(8) == b"\x89PNG\r\n\x1a\n", png
    seed_major = sorted(results, key=lambda r: (r["seed"], order.index(r["variant"])))
    assert printed["cells_run"] == [f"{r['variant']}-seed{r['seed']}" for r in seed_major]
    return saved
