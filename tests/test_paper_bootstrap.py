"""The paper's bootstrap procedure (training/bootstrap_paper.py) and its demonstrator
(ttmjx/tools/bootstrap.py, source `paper`): the tools-layer forward is the models-layer policy,
the weights file is pickle-free and checked, practice goals follow the stage's box, the stages
run through the trainer end to end, the shipped result spreads its landings over the half far
beyond the narrow ES policy's, and bad sizes are refused before anything is written."""
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models.config import PolicyConfig
from models.normalizer import Normalizer
from models.policy import init_ensemble, make_policy, member
from training import bootstrap_paper as bp
from ttmjx.tools import bootstrap, demos
from ttmjx.world import env, observation, record
from ttmjx.world.config import World

PCFG = PolicyConfig(kind="framestack", hidden=16, layers=2, obs_size=13, frame_stack=8)
META = {"layers": 2, "hidden": 16, "frame_stack": 8, "obs_size": 13}


def random_ensemble(members=3):
    k = jax.random.split(jax.random.PRNGKey(0), 5)
    norm = Normalizer(jax.random.normal(k[0], (13,)), 0.5 + jax.random.uniform(k[1], (13,)),
                      jax.random.normal(k[2], (8,)), 0.5 + jax.random.uniform(k[3], (8,)))
    return init_ensemble(k[4], PCFG, norm, members)


def test_the_tools_forward_is_the_models_policy_averaged_over_members(tmp_path):
    params = random_ensemble()
    bootstrap.save_weights(str(tmp_path), bp.tensors_of(params), META)
    with open(tmp_path / bootstrap.WEIGHTS_NAME, "rb") as f:
        assert f.read(8) and not f.read().startswith(b"\x80")          # safetensors, not a pickle
    policy, p = bootstrap.load_policy(World().with_throws("narrow"), str(tmp_path))
    frames = jax.random.normal(jax.random.PRNGKey(1), (8, 13))
    obs = env.Obs(frame=frames[-1], ball_vel=jnp.array([-5.0, 1.0, 0.5]), frames=frames, t=jnp.int32(9))
    goal = jnp.array([0.9, -0.3])
    carry, action = jax.jit(policy.apply)(p, goal, obs, jax.random.PRNGKey(2))
    with_goal = obs._replace(frames=observation.with_goal(frames, goal, xp=jnp))
    want = np.mean([make_policy(PCFG).apply(member(params, i), (), with_goal, None)[1] for i in range(3)], 0)
    np.testing.assert_allclose(action, want, rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(carry, goal)
    # The goal it plays for is its own: the observation's goal columns change nothing.
    other = obs._replace(frames=observation.with_goal(frames, jnp.array([5.0, 5.0]), xp=jnp))
    np.testing.assert_array_equal(policy.apply(p, goal, other, None)[1], policy.apply(p, goal, obs, None)[1])
    # Its goals per episode lie on the opponent's half.
    table = World().table
    g = np.asarray(jax.vmap(lambda k: policy.init(p, k))(jax.random.split(jax.random.PRNGKey(3), 500)))
    assert g[:, 0].min() >= 0 and g[:, 0].max() <= table.half_length and np.abs(g[:, 1]).max() <= table.half_width
    assert g[:, 0].std() > 0.3 and g[:, 1].std() > 0.35


def test_the_weights_file_is_checked(tmp_path):
    params = random_ensemble(1)
    bootstrap.save_weights(str(tmp_path), bp.tensors_of(params), META)
    tensors, meta = bootstrap.load_weights(str(tmp_path))
    assert meta["format_version"] == bootstrap.FORMAT_VERSION and tensors["dense0/kernel"].shape == (1, 8 * 13, 16)
    path = tmp_path / bootstrap.WEIGHTS_NAME
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ValueError, match="corrupt"):
        bootstrap.load_weights(str(tmp_path))
    with pytest.raises(ValueError, match="missing"):
        bootstrap.load_weights(str(tmp_path / "nowhere"))
    bad = dict(bp.tensors_of(params))
    bad["head/bias"] = np.zeros((1, 7), np.float32)
    with pytest.raises(ValueError, match="head"):
        bootstrap.save_weights(str(tmp_path / "b"), bad, META)


def _record(landing, on):
    n = len(landing)
    z = lambda *s, d=np.float32: np.zeros((n, *s), d)  # noqa: E731
    return record.Trajectories(obs=z(4, 13), ball_vel=z(4, 3), actions=z(4, 8), valid=np.ones((n, 4), bool),
                               goal=z(2), hit=np.ones(n, bool), hit_step=np.zeros(n, np.int32),
                               landing=np.asarray(landing, np.float32), on_opponent=np.asarray(on, bool),
                               bounce_own=z(d=bool), net=z(d=bool), launch_pos=z(3), launch_vel=z(3),
                               launch_spin=z(3), aim=z(2))


def test_shift_goals_lie_up_the_table_from_the_narrow_landings():
    world = World().with_throws("narrow")
    rng = np.random.default_rng(0)
    land = np.stack([rng.uniform(0.1, 0.5, 200), rng.uniform(0.2, 0.5, 200)], 1)
    (x0, x1), (y0, y1) = bp.shift_box(_record(land, np.ones(200, bool)), world)
    assert np.median(land[:, 0]) == pytest.approx(x0) and x1 == pytest.approx(world.table.half_length - 0.05)
    assert 0.0 < y0 < 0.2 and 0.5 < y1 < 0.7
    assert bp.whole_half(world) == ((0.0, world.table.half_length), (-world.table.half_width, world.table.half_width))


def test_practice_goals_follow_the_box(tmp_path):
    from ttmjx.world.backends import Backend
    world = World().with_throws("narrow")
    cfg = bp.stage_config(world, bp.Procedure(), "unused", str(tmp_path), 2000)
    box = ((0.8, 1.2), (-0.1, 0.3))
    prac = bp.GoalBoxPractice(world, cfg.policy, cfg.train, Backend(world, "c"), 400, 0, box=box)
    g = np.asarray(prac._pure_parts(None).goals(jax.random.PRNGKey(0)))
    assert g.shape == (400, 2)
    assert g[:, 0].min() >= 0.8 and g[:, 0].max() <= 1.2 and g[:, 1].min() >= -0.1 and g[:, 1].max() <= 0.3
    assert g[:, 0].std() == pytest.approx(0.4 / np.sqrt(12), rel=0.15)


def test_bad_sizes_are_refused_with_their_numbers():
    with pytest.raises(ValueError, match=r"ES return phase: 5 generations x 48 x 8 throws = 1920 episodes"):
        bp.Procedure(es_generations=(130, 5)).check(rebuild_es=True)
    bp.Procedure(es_generations=(130, 5)).check(rebuild_es=False)      # the shipped ES: not trained
    with pytest.raises(ValueError, match=r"narrow=100 ES episodes"):
        bp.Procedure(narrow=100).check(False)
    with pytest.raises(ValueError, match=r"final=10: the final stage's 10 episodes are less than one practice round "
                                         r"of the procedure \(100\)"):
        bp.Procedure(final=10).check(False)


@pytest.mark.slow
def test_the_stages_run_through_the_trainer(tmp_path):
    """The whole procedure at toy sizes from the shipped ES weights (no ES is trained here): the
    shift and expand stages are one trainer run resumed, each with practice rounds; the exported
    weights play as the `paper` source; the record and figure are written; a second call finds
    everything done."""
    proc = bp.Procedure(narrow=340, shift=50, expand=50, final=50, pretrain_steps=20, steps_per_round=10,
                        episodes_per_round=50)
    out = str(tmp_path / "b")
    rep = bp.build(out, World().with_throws("narrow"), proc, progress=False, log=lambda m: None)
    rows = [json.loads(x) for x in open(os.path.join(out, "run", "metrics.jsonl"))]
    practice = [r for r in rows if r["phase"] == "practice"]
    assert [r["trajectories"] for r in practice] == [390, 440]
    assert rep["shift"]["rounds"] == rep["expand"]["rounds"] == 1
    assert rows[-1]["updates"] == 20 + 2 * 10
    final, meta = record.load(os.path.join(out, "final"))
    assert final.size == 50 and meta["source"] == "paper" and np.all(np.asarray(final.goal) == 0.0)
    (x0, _), _ = rep["shift_box"]
    assert x0 == pytest.approx(float(np.median(np.asarray(record.load(os.path.join(out, "narrow"))[0].landing)[
        np.asarray(record.load(os.path.join(out, "narrow"))[0].on_opponent)][:, 0])))
    assert os.path.exists(os.path.join(out, "bootstrap.png")) and os.path.exists(os.path.join(out, "procedure.json"))
    again = bp.build(out, World().with_throws("narrow"), proc, progress=False, log=lambda m: None)
    assert again["final"] == rep["final"]


def test_cli_refuses_a_rebuild_too_small_for_es(tmp_path):
    import subprocess
    import sys
    out = tmp_path / "d"
    r = subprocess.run([sys.executable, "-m", "ttmjx", "demos", "--source", "paper", "--rebuild", "all",
                        "--es-generations", "130", "5", "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "5 generations x 48 x 8 throws = 1920 episodes" in r.stderr and not out.exists()
    r = subprocess.run([sys.executable, "-m", "ttmjx", "demos", "--source", "es", "--rebuild", "stages",
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "--rebuild stages builds the paper procedure" in r.stderr and not out.exists()
    r = subprocess.run([sys.executable, "-m", "ttmjx", "demos", "--rebuild", "stages", "--distribution", "varied",
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 2 and "trained on narrow throws, not varied: use --rebuild all" in r.stderr
    assert not out.exists()


@pytest.mark.slow
def test_a_rebuild_resumes_in_its_out_directory_and_nothing_else_is_overwritten(tmp_path):
    """`--rebuild` keeps what it built in OUT/bootstrap/ when it is cut short (docs/DATA.md): the
    same command accepts an OUT holding only that, and still refuses an OUT with anything else."""
    from ttmjx.cli import DemosArgs
    out = tmp_path / "d"
    (out / "bootstrap").mkdir(parents=True)
    DemosArgs(source="paper", rebuild="all", distribution="any", out=str(out))
    DemosArgs(source="paper", rebuild="stages", distribution="any", out=str(out))   # any-ball's own ES ships
    with pytest.raises(ValueError, match="already holds files"):
        DemosArgs(source="paper", rebuild="none", out=str(out))
    (out / "trajectories.npz").write_bytes(b"")
    with pytest.raises(ValueError, match="already holds files"):
        DemosArgs(source="paper", rebuild="all", distribution="any", out=str(out))


@pytest.fixture(scope="module")
def shipped():
    """The shipped `paper` source and the narrow ES policy it started from (unperturbed, as the
    paper's figure draws it), 128 narrow throws each in the world the bootstrap was built in."""
    world = bp.default_world()
    return (world, demos.collect(world, "paper", 128, seed=5),
            demos.collect(world, "es", 128, seed=5, pert=None))


def test_the_shipped_bootstrap_covers_the_half_beyond_the_narrow_policy(shipped):
    """The paper's claim for its procedure, on the shipped weights: the final demonstrations
    still hit and return most balls, and their landings spread over the half further than the
    narrow ES policy's, along the table and across it."""
    world, final, narrow = shipped
    f, n = demos.summary(final, world), demos.summary(narrow, world)
    assert f["hit_rate"] >= 0.85 and f["return_rate"] >= 0.4, f
    assert f["landing_std_y"] > 1.5 * n["landing_std_y"] and f["landing_std_x"] > n["landing_std_x"], (f, n)
    assert f["area_within_30cm"] > n["area_within_30cm"] and f["coverage"] > n["coverage"], (f, n)
    assert np.all(np.asarray(final.goal) == 0.0)                 # the zero placeholder: relabelled later


def test_each_throw_distribution_gets_its_own_shipped_build_and_no_other():
    """Narrow throws: ttmjx/tools/assets/; any-ball: assets/any/ (each built on its throws); a
    distribution without a build is refused, not served another's."""
    meta = bootstrap.read_meta()
    assert meta["world"]["throws"]["name"] == "narrow" and meta["procedure"]["final"] == 3600
    from ttmjx.tools import es
    any_dir = es.shipped_dir("any", bootstrap.WEIGHTS_NAME)
    assert es.shipped_dir("any") == any_dir and es.read_meta(any_dir)["distribution"] == "any"
    assert any_dir != bootstrap.ASSETS and bootstrap.read_meta(any_dir)["world"]["throws"]["name"] == "any"
    policy, params = bootstrap.load_policy(World().with_throws("any"))
    assert set(params) >= set(bootstrap.NORM_NAMES)
    with pytest.raises(ValueError, match="built on narrow throws, not varied"):
        bootstrap.load_policy(World().with_throws("varied"))


def test_cli_demos_paper_writes_the_two_maps(tmp_path, capsys):
    """`ttmjx demos` (source `paper`, the default) gathers with the shipped weights and reports
    the narrow ES policy's numbers beside the dataset's; the figure holds both maps. The command
    line runs in this process (ttmjx.cli.main; a failure raises SystemExit with its exit code),
    without a fresh process's imports and tracing of what this module's other tests traced."""
    from ttmjx.cli import main
    out = str(tmp_path / "d")
    capsys.readouterr()
    main(["demos", "--n", "16", "--out", out, "--json"])
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert res["n"] == 16 and res["narrow_n"] == 16 and 0 <= res["narrow_return_rate"] <= 1
    traj, meta = record.load(out)
    assert meta["source"] == "paper" and meta["source_version"] == demos.SOURCE_VERSION and traj.size == 16
    assert demos.dataset_source(meta) == "paper"
    from PIL import Image
    w, h = Image.open(os.path.join(out, "coverage.png")).size
    assert w > 1.2 * h                                              # two maps side by side


@pytest.mark.slow
def test_es_from_scratch_chains_the_contact_and_return_phases(tmp_path):
    """`--rebuild all`'s ES stage at toy sizes (below what Procedure.check accepts): the return
    phase starts from the contact phase's weights, both are written, and the result loads as
    the `es` source's weights."""
    from ttmjx.tools import es
    proc = bp.Procedure(es_generations=(1, 1), es_population=4, es_throws=2, es_pool=8, es_val=4)
    summary = bp.train_es(World().with_throws("narrow"), proc, str(tmp_path), progress=False, log=lambda m: None)
    assert set(summary) == {"contact", "return"} and all(s["generations"] == 1 for s in summary.values())
    contact = es.load_params(str(tmp_path / "es_contact.npz"))
    final = es.load_params(str(tmp_path / es.WEIGHTS_NAME))
    returned = es.load_params(str(tmp_path / "es_return.npz"))
    assert all(np.array_equal(final[k], returned[k]) for k in es.PARAM_NAMES)
    assert not np.array_equal(contact["W2"], np.zeros_like(contact["W2"]))   # it moved from the zero head
    assert es.read_meta(str(tmp_path))["phases"]["return"]["generations"] == 1


def test_the_hidden_perturbation_is_a_calibration_offset():
    """A policy that commands the joints it observes (hold) drifts by the offset every step when
    it sees the true joints, and commands exactly the true joints when the offset is hidden (it
    is shown them moved back, and the offset is added to what it sends): the executed stroke is
    its usual one moved by the offset, once."""
    from ttmjx.world import backends
    hold = backends.Policy(init=lambda p, k: jnp.zeros(()),
                           apply=lambda p, c, obs, k: (c, observation.joints(obs.frame)))
    pert = demos.Perturbation()
    frames = jnp.tile(jnp.concatenate([jnp.arange(8.0) / 10, jnp.array([-1.0, 0.0, 0.9, 0.0, 0.0])]), (8, 1))
    obs = env.Obs(frame=frames[-1], ball_vel=jnp.zeros(3), frames=frames, t=jnp.int32(0))
    for hidden, want_extra in ((True, 0.0), (False, 1.0)):
        policy = demos.perturbed(hold, pert, hidden=hidden)
        carry = policy.init(None, jax.random.PRNGKey(0))
        (_, offset), action = policy.apply(None, carry, obs, None)
        assert np.abs(offset).max() > 0
        np.testing.assert_allclose(action, observation.joints(obs.frame) + want_extra * offset, atol=1e-6)
