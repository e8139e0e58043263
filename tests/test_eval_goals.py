"""Strict success (ttmjx.world.goals), practice goals beyond the table, user goal files and what
`ttmjx eval RUN --goals FILE --out DIR` writes (ttmjx.world.goalfile, eval.report)."""
import contextlib
import csv
import io
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from documented import check_eval_out
from ttmjx import cli
from ttmjx.world.config import Table, World
from ttmjx.world.env import uniform_goals
from ttmjx.world.goalfile import read_goal_file as load_goal_file
from ttmjx.world.goals import goal_metrics, goal_stats

DATA = os.path.join(os.path.dirname(__file__), "data")
RUN = os.path.join(DATA, "tiny_run_v0")
TABLE = Table()
NAN = np.nan


def strict_case():
    """Six attempts, each a different way to land near the goal (which a lenient metric counts)."""
    goal = np.array([[0.7, 0.0], [0.7, 0.0], [1.30, 0.0], [0.10, 0.0], [0.7, 0.0], [0.7, 0.0]])
    landing = np.array([[0.7, 0.0],      # hit, first bounce on the opponent's half, on the goal
                        [NAN, NAN],      # not hit
                        [1.45, 0.0],     # hit, lands 15 cm from the goal but beyond the end line
                        [-0.10, 0.0],    # hit, lands 20 cm from the goal but on the robot's half
                        [NAN, NAN],      # hit, never came down
                        [0.7, 0.25]])    # hit, on the half, 25 cm away
    hit = np.array([1, 0, 1, 1, 1, 1], bool)
    on_opponent = np.array([1, 0, 0, 0, 0, 1], bool)
    return landing, goal, hit, on_opponent


def test_a_success_is_a_first_bounce_on_the_opponents_half_near_the_goal():
    m = goal_metrics(*strict_case())
    assert m["within_30cm"] == pytest.approx(2 / 6) and m["within_20cm"] == pytest.approx(1 / 6)
    assert m["hit_rate"] == pytest.approx(5 / 6) and m["on_table_rate"] == pytest.approx(2 / 6)
    assert m["mean_dist"] == pytest.approx(0.125)      # over the two on-table landings only
    # the paper's distance to goal: every hit ball that came down, on the table or beside it
    # (0, 0.15 beyond the end line, 0.20 on the robot's half, 0.25); the unhit and the
    # never-landed count in neither distance
    assert m["mean_dist_landed"] == pytest.approx((0 + 0.15 + 0.20 + 0.25) / 4)
    assert m["goals"] == 6
    jm = goal_stats(*(jnp.asarray(x) for x in strict_case()), xp=jnp)   # the jitted practice path
    assert {k: float(v) for k, v in jm.items()} == pytest.approx(
        {k: v for k, v in m.items() if k not in ("goals", "mean_dist_landed")})


def test_final_metrics_of_an_older_result_recompute_the_landed_distance_from_its_landings():
    from eval import tables
    landing, goal, hit, on_opponent = strict_case()
    m = goal_metrics(landing, goal, hit, on_opponent)
    old = {k: v for k, v in m.items() if k != "mean_dist_landed"}     # a result written before the metric
    lands = {"goal": goal.tolist(), "landing": [[None if np.isnan(v) else v for v in p] for p in landing.tolist()],
             "hit": hit.tolist(), "on_opponent": on_opponent.tolist()}
    got = tables.final_metrics({"final": old, "landings": lands})
    assert got == pytest.approx(m, nan_ok=True)
    assert tables.final_metrics({"final": m, "landings": None}) is m


def test_no_on_table_landing_gives_zero_success_and_no_mean_distance():
    landing, goal, hit, _ = strict_case()
    m = goal_metrics(landing, goal, hit, np.zeros(6, bool))
    assert m["within_30cm"] == 0 and m["on_table_rate"] == 0 and np.isnan(m["mean_dist"])
    with pytest.raises(ValueError, match=r"on_opponent has shape \(5,\), expected \(6,\)"):
        goal_metrics(landing, goal, hit, np.zeros(5, bool))


def test_practice_goals_reach_beyond_the_edges_and_evaluation_goals_stay_on_the_table():
    key = jax.random.PRNGKey(0)
    on = np.asarray(uniform_goals(key, 4000, TABLE))
    np.testing.assert_array_equal(on, np.asarray(uniform_goals(key, 4000, TABLE, 0.0)))
    assert on[:, 0].min() >= 0 and on[:, 0].max() <= TABLE.half_length and np.abs(on[:, 1]).max() <= TABLE.half_width
    g = np.asarray(uniform_goals(key, 4000, TABLE, 0.2))
    assert g[:, 0].min() >= 0, "never over the net"
    assert g[:, 0].max() <= TABLE.half_length + 0.2 and np.abs(g[:, 1]).max() <= TABLE.half_width + 0.2
    off = (g[:, 0] > TABLE.half_length) | (np.abs(g[:, 1]) > TABLE.half_width)
    # Uniform over the extended area: the fraction off the table is 1 - table area / extended area.
    expect = 1 - TABLE.half_length * TABLE.half_width / ((TABLE.half_length + 0.2) * (TABLE.half_width + 0.2))
    assert off.mean() == pytest.approx(expect, abs=0.03)


def write_goals(tmp_path, goals) -> tuple[str, str]:
    csv_path, npy_path = str(tmp_path / "g.csv"), str(tmp_path / "g.npy")
    with open(csv_path, "w") as f:
        f.write("x,y\n" + "".join(f"{x!r},{y!r}\n" for x, y in goals.tolist()))
    np.save(npy_path, goals)
    return csv_path, npy_path


def test_goal_files_csv_and_npy_read_the_same_goals(tmp_path):
    goals = np.array([[0.7, 0.0], [0.35, 0.45], [1.05, -0.45]], np.float32)
    csv_path, npy_path = write_goals(tmp_path, goals)
    np.testing.assert_array_equal(load_goal_file(csv_path, TABLE), goals)
    np.testing.assert_array_equal(load_goal_file(npy_path, TABLE), goals)
    (tmp_path / "swapped.csv").write_text("y, x ,note\n0.45,0.35,a\n")
    np.testing.assert_array_equal(load_goal_file(str(tmp_path / "swapped.csv"), TABLE), np.float32([[0.35, 0.45]]))
    for name, text, match in [("noheader.csv", "0.7,0.0\n", "header row naming columns x and y"),
                              ("nan.csv", "x,y\n0.7,nan\n", r"goal 0 = \(0.7, nan\) is not finite"),
                              ("beyond.csv", "x,y\n0.7,0\n1.5,0\n", r"goal 1 = \(1.5, 0.0\) is off the opponent's half"),
                              ("own.csv", "x,y\n-0.2,0\n", "off the opponent's half"),
                              ("text.csv", "x,y\n0.7,abc\n", "row 2"), ("empty.csv", "x,y\n", r"shape \(0, 2\)")]:
        (tmp_path / name).write_text(text)
        with pytest.raises(ValueError, match=match):
            load_goal_file(str(tmp_path / name), TABLE)
    np.save(tmp_path / "wide.npy", np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"shape \(3, 3\); expected \[N, 2\]"):
        load_goal_file(str(tmp_path / "wide.npy"), TABLE)
    np.save(tmp_path / "obj.npy", np.array([[0.7, None]], object), allow_pickle=True)
    with pytest.raises(ValueError, match="not a plain numeric"):
        load_goal_file(str(tmp_path / "obj.npy"), TABLE)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_goal_file(str(tmp_path / "missing.npy"), TABLE)


def cli_json(*argv) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        cli.main(list(argv))
    return json.loads(out.getvalue().strip().splitlines()[-1])


@pytest.fixture(scope="module")
def eval_dir(tmp_path_factory):
    """`ttmjx eval tiny_run_v0 --goals g.csv --seed 3 --out DIR --json` on 24 uniform goals."""
    tmp = tmp_path_factory.mktemp("eval")
    u = np.random.default_rng(0).uniform(size=(24, 2))
    goals = np.stack([u[:, 0] * TABLE.half_length, (2 * u[:, 1] - 1) * TABLE.half_width], 1).round(3)
    csv_path, _ = write_goals(tmp, goals.astype(np.float32))
    out = str(tmp / "out")
    printed = cli_json("eval", RUN, "--goals", csv_path, "--seed", "3", "--out", out, "--json")
    return out, printed, goals.astype(np.float32)


def test_eval_out_writes_the_summary_it_prints_and_one_row_per_episode(eval_dir):
    out, printed, goals = eval_dir
    rows = check_eval_out(out, printed)                  # docs/DATA.md, "Evaluation output"
    assert printed["goals"] == len(goals) == 24
    np.testing.assert_array_equal(np.float32([[r["goal_x"], r["goal_y"]] for r in rows]), goals)  # exact text
    assert 0 < printed["on_table_rate"] < printed["hit_rate"], "the policy should put some hits on the table, not all"


def test_tracks_recompute_the_recorded_landings(eval_dir):
    """From tracks.npz alone: the ball's true centre at the last step before the episode ended, carried forward
    ballistically (gravity; drag moves it < 1 mm in one 10 ms step) to table height + radius,
    lands where the episode's landing was recorded, within the travel of two 1 ms physics steps
    (the events resolve a contact to one physics step) plus 2 mm of the ball's sink into the table."""
    out, _, _ = eval_dir
    with np.load(os.path.join(out, "tracks.npz"), allow_pickle=False) as f:
        t = {k: f[k] for k in f.files}
    # At ideal timing (tiny) the policy saw the truth; under the cell's: tests/test_true_tracks.py.
    np.testing.assert_array_equal(t["ball_observed"][t["valid"]], t["ball_pos"][t["valid"]])
    rows = list(csv.DictReader(open(os.path.join(out, "episodes.csv"))))
    n, steps = len(rows), World().horizon
    assert t["ball_pos"].shape == (n, steps, 3) and t["valid"].shape == (n, steps) and t["hit_step"].shape == (n,)
    dt, g = 1.0 / int(t["control_hz"]), 9.81
    height = float(t["table_top_z"] + t["ball_radius"])
    checked = 0
    for i, r in enumerate(rows):
        assert (t["hit_step"][i] >= 0) == (r["hit"] == "1")
        if r["landing_x"] == "":
            continue
        last = int(np.flatnonzero(t["valid"][i])[-1])
        assert last > t["hit_step"][i], "the landing comes after the hit"
        p0, p1 = t["ball_pos"][i, last - 1].astype(np.float64), t["ball_pos"][i, last].astype(np.float64)
        v = (p1 - p0) / dt - np.array([0, 0, -g * dt / 2])        # velocity at the last sample
        tau = (v[2] + np.sqrt(v[2] ** 2 + 2 * g * (p1[2] - height))) / g   # time to fall to table height
        landing = np.array([float(r["landing_x"]), float(r["landing_y"])])
        assert tau <= 1.05 * dt, (i, tau / dt)                    # it lands within the next control step
        speed = np.linalg.norm(v[:2])
        assert np.linalg.norm(p1[:2] + v[:2] * tau - landing) <= 2 * World().physics_dt * speed + 0.002, i
        checked += 1
    assert checked >= 4, checked


def test_the_landing_map_colours_a_ball_off_the_half_red_however_near_its_goal():
    """The map's green is the strict success: a ball 10 cm beyond the side line from a goal at
    the edge is a miss (red), as in the tables; one on the half within 30 cm is green."""
    from eval.tables import _landings
    from ttmjx.world.config import Table
    hw = Table().half_width
    d = {"goal": [[0.5, hw - 0.05], [0.5, 0.0], [0.5, 0.0]],
         "landing": [[0.5, hw + 0.05], [0.6, 0.1], None],
         "hit": [True, True, False], "on_opponent": [False, True, False]}
    _, _, landed, colour = _landings(d)
    assert list(colour) == ["tab:red", "tab:green", "tab:red"] and list(landed) == [True, True, False]


def test_an_ensemble_that_does_not_divide_the_goals_plays_each_goal_and_throw_once():
    """Three members on 4 goals: the ensemble's equal blocks need 6 episodes, and the 2 repeats
    are dropped; the throws are the ones every member count gets, so a 3-member cell is scored on
    the same goals and throws as a 1- or 10-member cell (a 3-member final evaluation once counted
    goal 0 twice, over 201 throws)."""
    from eval.evaluate import rollout_goals_one, uniform_runs
    from models.config import PolicyConfig
    from models.normalizer import identity_normalizer
    from models.policy import init_ensemble, member
    from ttmjx.world.backends import Backend, lane_of_one
    world = World()
    pcfg = PolicyConfig(kind="framestack", hidden=16, layers=2, obs_size=13, frame_stack=8)
    ens = init_ensemble(jax.random.PRNGKey(0), pcfg, identity_normalizer(13), 3)
    backend = Backend(world, "c")
    goals = np.asarray(uniform_goals(jax.random.PRNGKey(1), 4, TABLE), np.float32)
    three = rollout_goals_one(world, pcfg, ens, backend, jax.random.PRNGKey(2), goals, members=3)
    one = rollout_goals_one(world, pcfg, member(ens, 0), backend, jax.random.PRNGKey(2), goals)
    assert three.landing.shape == (4, 2) and three.hit.shape == (4,)
    np.testing.assert_array_equal(three.goal, goals)
    np.testing.assert_array_equal(three.launch_pos, one.launch_pos)
    np.testing.assert_array_equal(three.launch_vel, one.launch_vel)
    metrics, tr = uniform_runs(world, pcfg, lane_of_one(ens), backend, lane_of_one(jax.random.PRNGKey(3)), 4,
                               members=3)
    assert metrics[0]["goals"] == 4 and tr.goal.shape == (1, 4, 2)


# -- one --goals grammar for `ttmjx eval` and `ttmjx robot run` (ttmjx.world.goalspec) -----------
INLINE = "0.7,0.3;0.4,-0.5"


def test_the_grammar_reads_every_form_once_for_both_commands(tmp_path):
    from ttmjx.world.goalspec import goal_spec
    csv_path, npy_path = write_goals(tmp_path, np.float32([[0.7, 0.3], [0.4, -0.5]]))
    assert goal_spec("12") == ("uniform", 12, None) and goal_spec("uniform") == ("uniform", None, None)
    assert goal_spec("five") == ("five", None, None)
    for value in (INLINE, "0.7 0.3; 0.4 -0.5", csv_path, npy_path):
        spec = goal_spec(value)
        assert spec.kind == "points", value
        np.testing.assert_array_equal(spec.goals, np.float32([[0.7, 0.3], [0.4, -0.5]]))


def robot_goals(tmp_path, value, n) -> np.ndarray:
    """The goals `ttmjx robot run --station fake --goals VALUE --n N --out DIR` played, from its logs."""
    from deploy.robot.episode_log import load_episode
    out = tmp_path / f"robot{len(os.listdir(tmp_path))}"
    printed = cli_json("robot", "run", "--station", "fake", "--goals", value, "--n", str(n), "--out", str(out), "--json")
    names = sorted(f[:-len(".meta.json")] for f in os.listdir(out) if f.startswith("episode_") and f.endswith(".meta.json"))
    assert printed["episodes"] == len(names)
    return np.float32([load_episode(str(out), name).meta["goal"] for name in names])


def test_robot_run_plays_every_form(tmp_path):
    from deploy.robot.goals import uniform_session_goals
    from ttmjx.world.goals import five_goals
    csv_path, npy_path = write_goals(tmp_path, np.float32([[0.7, 0.3], [0.4, -0.5]]))
    twice = np.float32([[0.7, 0.3], [0.7, 0.3], [0.4, -0.5], [0.4, -0.5]])       # --n 2: each goal twice
    for value in (INLINE, csv_path, npy_path):
        np.testing.assert_allclose(robot_goals(tmp_path, value, 2), twice, atol=1e-6)
    np.testing.assert_allclose(robot_goals(tmp_path, "3", 2), np.repeat(uniform_session_goals(3), 2, 0), atol=1e-6)
    np.testing.assert_allclose(robot_goals(tmp_path, "uniform", 2), uniform_session_goals(2), atol=1e-6)
    np.testing.assert_allclose(robot_goals(tmp_path, "five", 1), five_goals(1)[0], atol=1e-6)


def test_eval_plays_every_form():
    """N and 'uniform' (200) are the same uniform draw: the same goals and rollout key, so the
    same rollout, which plays every goal; 'five' its goals A-E."""
    from eval.evaluate import EVAL_UNIFORM_GOALS, eval_plan
    from ttmjx.world.goalspec import goal_spec
    plans = [eval_plan(goal_spec(v), World(), jax.random.PRNGKey(2), 1) for v in ("uniform", "200")]
    raw = lambda x: jax.random.key_data(x) if jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key) else x  # noqa: E731
    (goals_u, names_u, key_u), (goals_n, names_n, key_n) = plans
    np.testing.assert_array_equal(goals_u, goals_n)
    np.testing.assert_array_equal(raw(key_u), raw(key_n))
    assert names_u is names_n is None
    uniform = cli_json("eval", RUN, "--goals", "uniform", "--seed", "2", "--json")
    assert uniform["goals"] == EVAL_UNIFORM_GOALS == 200 and 0.0 <= uniform["within_30cm"] <= 1.0
    five = cli_json("eval", RUN, "--goals", "five", "--per-goal", "1", "--json")
    assert five["goals"] == 5 and sorted(five["per_goal"]) == ["A", "B", "C", "D", "E"]


def test_eval_reads_inline_goals_as_it_reads_them_from_a_file(tmp_path):
    csv_path, npy_path = write_goals(tmp_path, np.float32([[0.7, 0.3], [0.4, -0.5]]))
    inline = cli_json("eval", RUN, "--goals", INLINE, "--seed", "3", "--json")
    assert inline["goals"] == 2
    for path in (csv_path, npy_path):
        assert cli_json("eval", RUN, "--goals", path, "--seed", "3", "--json") == inline, path


BAD_GOALS = ["abc", "0", "-3", "0.7", "nan,0", "5,5", "", "{tmp}/missing.csv", "{tmp}/goals.txt", "{tmp}/wide.npy"]


@pytest.mark.parametrize("command", ["eval " + RUN, "robot run --station fake"])
def test_a_bad_goals_value_is_one_line_naming_it_and_the_forms(command, tmp_path):
    (tmp_path / "goals.txt").write_text("x,y\n0.7,0.0\n")                   # neither .csv nor .npy
    np.save(tmp_path / "wide.npy", np.zeros((4, 3)))
    for value in BAD_GOALS:
        value = value.replace("{tmp}", str(tmp_path))
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()), \
                pytest.raises(SystemExit) as ex:
            cli.main(command.split() + ["--goals", value])
        msg = err.getvalue()
        assert ex.value.code == 2 and msg.count("\n") == 1, (value, msg)
        assert f"--goals {value!r}" in msg and "--goals takes N" in msg and "'five'" in msg, (value, msg)
