"""Export (safetensors + contract + golden self-test), numpy inference equal to the JAX policies,
and every refusal of a tampered or mismatched export."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from deploy.robot import ROBOT_MODEL_ID, Contract, ExportError, load_export, read_contract
from deploy.robot.exported import CONTRACT_FILE, GOLDEN_FILE, MANIFEST_FILE, ONNX_FILE, WEIGHTS_FILE, sha256_bytes
from deploy.robot.numpy_policy import ExportedPolicy, PolicySpec, tensor_shapes
from deploy.robot.policy_bench import benchmark
from deploy.sim.export import export, export_checkpoint
from models import Normalizer, PolicyConfig, PolicyParams, init_ensemble, init_params, make_policy, member
from ttmjx.world import env, observation
from ttmjx.world.config import World

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
try:
    import onnx  # noqa: F401  (the optional extra: exports hold policy.onnx only with it)
    HAVE_ONNX = True
except ImportError:
    HAVE_ONNX = False
LSTM = PolicyConfig(kind="lstm", hidden=32, layers=2)
MLP = PolicyConfig(kind="framestack", hidden=32, layers=2, frame_stack=4)


def random_norm(key, obs_size=13) -> Normalizer:
    k = jax.random.split(key, 4)
    return Normalizer(jax.random.normal(k[0], (obs_size,)), jnp.exp(0.3 * jax.random.normal(k[1], (obs_size,))),
                      jax.random.normal(k[2], (8,)), jnp.exp(0.3 * jax.random.normal(k[3], (8,))))


def random_params(pcfg, seed=0, members=None) -> PolicyParams:
    """Initialized params with every leaf (biases too) perturbed, and a random normalizer."""
    key = jax.random.key(seed)
    norm = random_norm(jax.random.fold_in(key, 1), pcfg.obs_size)
    p = (init_params(key, pcfg, norm) if members is None
         else init_ensemble(key, pcfg, norm, members))
    leaves, tree = jax.tree.flatten(p.net)
    keys = jax.random.split(jax.random.fold_in(key, 2), len(leaves))
    leaves = [x + 0.2 * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)]
    return p._replace(net=jax.tree.unflatten(tree, leaves))


def observations(steps, k, seed=0):
    """[L, 13] frames of plausible scale and their [L, k, 13] stacks (the runner's padding)."""
    rng = np.random.default_rng(seed)
    normal = lambda scale, mean=0.0: rng.standard_normal((steps, len(scale))) * scale + mean  # noqa: E731
    frames = observation.make_frame(normal([0.2] * 2 + [1.0] * 6), normal([1.0, 0.4, 0.2], [0.0, 0.0, 0.9]),
                                    normal([0.5] * 2, [0.7, 0.0])).astype(np.float32)
    return frames, observation.frame_stack(frames[None], k)[0]


def jax_actions(pcfg, params, frames, stacks):
    """[L, 8] from models.make_policy (one member), from a zero state."""
    pol = make_policy(pcfg)

    @jax.jit
    def run(p, f, s):
        obs = lambda frame, stack: env.Obs(frame, jnp.zeros(3), stack, jnp.int32(0))  # noqa: E731
        body = lambda c, xs: pol.apply(p, c, obs(*xs), None)  # noqa: E731
        return jax.lax.scan(body, pol.init(p, None), (f, s))[1]
    return np.asarray(run(params, jnp.asarray(frames), jnp.asarray(stacks)))


def numpy_policy(pcfg, params) -> ExportedPolicy:
    from deploy.sim.export import policy_tensors, select_members
    tensors, is_ens = policy_tensors(params)
    tensors, _ = select_members(tensors, is_ens, None, is_ens)
    from deploy.sim.export import _spec
    return ExportedPolicy(_spec(pcfg), tensors)


# --------------------------------------------------------------------------- numpy == JAX
MIXTURE = PolicyConfig(kind="lstm", hidden=32, layers=2, head="mixture", components=4)


@pytest.mark.parametrize("pcfg,steps", [(LSTM, 300), (MLP, 100), (MIXTURE, 100)], ids=["lstm", "framestack", "mixture"])
def test_numpy_policy_equals_jax_over_many_steps(pcfg, steps):
    params = random_params(pcfg, seed=3)
    frames, stacks = observations(steps, pcfg.frame_stack, seed=4)
    want = jax_actions(pcfg, params, frames, stacks)
    pol = numpy_policy(pcfg, params)
    state, got = pol.reset(), []
    for t in range(steps):
        before = None if state is None else state.copy()
        state, a = pol.step(state, frames[t], stacks[t])
        if before is not None:
            assert not np.shares_memory(before, state)
        got.append(a)
    got = np.asarray(got)
    assert got.shape == (steps, 8) and got.dtype == np.float32
    assert np.abs(want).max() > 0.5            # a non-trivial output, not all zeros
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-5)
    # A reset restarts the episode: the same first action again.
    _, a0 = pol.step(pol.reset(), frames[0], stacks[0])
    np.testing.assert_allclose(a0, want[0], rtol=0, atol=1e-5)


def test_prepare_between_ticks_gives_bit_identical_steps():
    """prepare(state) moves the recurrent products off the critical path without changing a bit;
    a prepared result is used only for the very state it was computed from."""
    params = random_params(LSTM, seed=7, members=2)
    pol = numpy_policy(LSTM, params)
    frames, _ = observations(30, 1, seed=5)
    s_plain, s_prep = pol.reset(), pol.reset()
    for t in range(30):
        s_plain, a_plain = pol.step(s_plain, frames[t], None)
        pol.prepare(s_prep)
        s_prep, a_prep = pol.step(s_prep, frames[t], None)
        np.testing.assert_array_equal(a_plain, a_prep)
        np.testing.assert_array_equal(s_plain, s_prep)
    pol.prepare(pol.reset())                     # prepared for another state: ignored
    _, a = pol.step(s_plain, frames[0], None)
    _, want = pol.step(s_plain, frames[0], None)
    np.testing.assert_array_equal(a, want)


def test_numpy_policy_rejects_wrong_inputs():
    pol = numpy_policy(LSTM, random_params(LSTM))
    with pytest.raises(ValueError, match="frame has shape"):
        pol.step(pol.reset(), np.zeros(16), np.zeros((8, 16)))
    with pytest.raises(ValueError, match="state has shape"):
        pol.step(np.zeros((1, 2, 2, 31)), np.zeros(13), np.zeros((8, 13)))
    mlp = numpy_policy(MLP, random_params(MLP))
    assert mlp.reset() is None
    with pytest.raises(ValueError, match="frames has shape"):
        mlp.step(None, np.zeros(13), np.zeros((8, 13)))


# --------------------------------------------------------------------------- export round trip
@pytest.fixture(scope="module")
def ensemble_export(tmp_path_factory):
    """A 3-member LSTM ensemble exported at 20 Hz (made once for the module)."""
    params = random_params(LSTM, seed=5, members=3)
    out = str(tmp_path_factory.mktemp("exports") / "ens")
    export(params, LSTM, World(), out, ensemble=True, source="ckpt/run@7", control_hz=20)
    return out, params


def test_export_round_trip_and_golden_self_test(ensemble_export):
    out, params = ensemble_export
    listed = [CONTRACT_FILE, WEIGHTS_FILE, GOLDEN_FILE, MANIFEST_FILE]
    assert sorted(os.listdir(out)) == sorted(listed + ([ONNX_FILE] if HAVE_ONNX else []))
    pol, contract = load_export(out)
    assert isinstance(contract, Contract) and contract.control_hz == 20.0 and contract.horizon == 32
    assert pol.members == 3 and pol.state_shape == (3, 2, 2, 32)
    assert 0.0 <= pol.self_test_error <= 1e-5
    with open(os.path.join(out, WEIGHTS_FILE), "rb") as f:
        assert pol.policy_hash == "sha256:" + sha256_bytes(f.read())
    doc = read_contract(out)
    assert doc["robot"]["model_id"] == ROBOT_MODEL_ID
    assert doc["robot"]["joint_names"][:2] == ["gantry_x", "gantry_y"]
    assert doc["observation"]["frame"][8:] == ["ball_x", "ball_y", "ball_z", "goal_x", "goal_y"]
    assert doc["policy"]["state"]["shape"] == [3, 2, 2, 32] and "mean" in doc["policy"]["ensemble_rule"]
    assert doc["source"] == {**doc["source"], "checkpoint": "ckpt/run@7", "members": [0, 1, 2]}
    assert doc["goal"]["units"] == "m" and doc["runtime"]["control_hz"] == 20.0
    assert {k: tuple(v) for k, v in doc["weights"]["tensors"].items()} == tensor_shapes(pol.spec, 3)
    # The ensemble's action is the mean of the members' JAX actions, on fresh inputs too.
    frames, stacks = observations(40, 8, seed=9)
    want = np.mean([jax_actions(LSTM, member(params, i), frames, stacks) for i in range(3)], axis=0)
    np.testing.assert_allclose(pol.run(frames, stacks), want, rtol=0, atol=1e-5)


CONTRACT_KEYS = {"format", "version", "robot", "runtime", "observation", "action", "goal", "policy", "normalization",
                 "weights", "golden", "onnx", "source", "world", "timing"}
POLICY_KEYS = {"kind", "hidden", "layers", "obs_size", "frame_stack", "input_frames", "members", "ensemble_rule",
               "head", "components", "head_rule", "state", "cell", "trained_control_hz"}
TIMING_KEYS = {"model", "ranges", "ideal", "randomized_per_episode", "centre", "meaning", "sha256"}


@pytest.mark.parametrize("which", ["lstm", "framestack"])
def test_manifest_and_contract_hold_the_documented_keys_and_they_mean_it(which, ensemble_export, mlp_export):
    """docs/DATA.md ("Policy exports"): every key of manifest.json and contract.json (top level, the
    policy's and the timing's) is one the docs name, every one they name is there, and the cheap
    ones mean it: the hashes and sizes are the files', the rate, observation size and members are
    the export's, the timing record is the training World's."""
    from deploy.robot.contract import REAL_OBS_SIZE
    from deploy.robot.exported import EXPORT_FORMAT
    from deploy.robot.timing_check import record_hash
    from documented import data_md_row, named_in
    from ttmjx.world.config import to_dict
    out, members, kind = ((ensemble_export[0], 3, "lstm") if which == "lstm" else (mlp_export, 2, "framestack"))
    manifest = json.load(open(os.path.join(out, MANIFEST_FILE)))
    assert set(manifest) == {"format", "format_version", "files"}
    named_in(data_md_row("`manifest.json`"), manifest)
    assert manifest["format"] == EXPORT_FORMAT == "ttmjx-policy-export" and manifest["format_version"] == 2
    assert sorted(manifest["files"]) == sorted(set(os.listdir(out)) - {MANIFEST_FILE})
    blobs = {name: open(os.path.join(out, name), "rb").read() for name in manifest["files"]}
    for name, entry in manifest["files"].items():
        assert entry == {"sha256": sha256_bytes(blobs[name]), "bytes": len(blobs[name])}, name
    doc = json.loads(blobs[CONTRACT_FILE])
    row = data_md_row("`contract.json`")
    for keys, got in [(CONTRACT_KEYS, doc), (POLICY_KEYS, doc["policy"]), (TIMING_KEYS, doc["timing"])]:
        assert set(got) == keys, set(got) ^ keys
        named_in(row, keys)
    named_in(row, ["control_hz", "frame_stack", "obs_size", "frame_size", "frame"])
    assert (doc["format"], doc["version"]) == (manifest["format"], manifest["format_version"])
    for section, name in [("weights", WEIGHTS_FILE), ("golden", GOLDEN_FILE)]:
        assert doc[section]["file"] == name and doc[section]["sha256"] == manifest["files"][name]["sha256"]
    assert doc["weights"]["bytes"] == len(blobs[WEIGHTS_FILE])
    assert (doc["onnx"] is None) == (ONNX_FILE not in blobs)
    if doc["onnx"] is not None:
        assert doc["onnx"]["sha256"] == manifest["files"][ONNX_FILE]["sha256"] and doc["onnx"]["file"] == ONNX_FILE
    assert doc["runtime"]["control_hz"] == 20.0 and doc["policy"]["trained_control_hz"] == World().control_hz
    obs = REAL_OBS_SIZE                                   # the robot's 13: joints, ball, goal
    assert doc["runtime"]["obs_size"] == doc["policy"]["obs_size"] == doc["observation"]["frame_size"] == obs
    assert len(doc["observation"]["frame"]) == obs
    assert doc["policy"]["kind"] == kind and doc["policy"]["members"] == members
    assert all(shape[0] == members for shape in doc["weights"]["tensors"].values())
    assert doc["source"]["members"] == list(range(members))
    assert (doc["policy"]["state"] is None) == (kind == "framestack")
    assert doc["world"] == json.loads(json.dumps(to_dict(World())))
    t = doc["timing"]
    assert t["model"] == json.loads(json.dumps(to_dict(World().timing)))
    assert t["centre"] == json.loads(json.dumps(to_dict(World().timing.centre())))
    assert t["sha256"] == record_hash(t["model"], t["ranges"]) and t["ideal"] == World().timing.ideal
    assert t["randomized_per_episode"] == (max(World().timing.spreads()) > 0)


def test_export_one_member_and_framestack(tmp_path):
    params = random_params(LSTM, seed=5, members=3)
    export(params, LSTM, World(), str(tmp_path / "m1"), member=1, control_hz=60)
    pol, contract = load_export(str(tmp_path / "m1"))
    assert pol.members == 1 and contract.control_hz == 60.0
    frames, stacks = observations(20, 8, seed=2)
    np.testing.assert_allclose(pol.run(frames), jax_actions(LSTM, member(params, 1), frames, stacks),
                               rtol=0, atol=1e-5)
    mlp = random_params(MLP, seed=6)
    export(mlp, MLP, World(), str(tmp_path / "mlp"))
    pol, contract = load_export(str(tmp_path / "mlp"))
    assert contract.frame_stack == 4 and contract.control_hz == 100.0 and pol.reset() is None
    frames, stacks = observations(20, 4, seed=2)
    np.testing.assert_allclose(pol.run(frames, stacks), jax_actions(MLP, mlp, frames, stacks),
                               rtol=0, atol=1e-5)


def test_a_mixture_head_exports_and_plays_on_the_numpy_engine_without_a_graph(tmp_path):
    """The mixture head's export: its policy section names the head, the numpy engine plays it
    as the JAX policy does (the golden self-test passed on loading), and the ONNX graph, built for
    the mean head only, is left out on `auto` and refused when asked for."""
    params = random_params(MIXTURE, seed=7, members=2)
    export(params, MIXTURE, World(), str(tmp_path / "mix"), ensemble=True)
    pol, _ = load_export(str(tmp_path / "mix"))
    doc = read_contract(str(tmp_path / "mix"))
    assert (doc["policy"]["head"], doc["policy"]["components"], doc["onnx"]) == ("mixture", 4, None)
    frames, stacks = observations(20, 8, seed=2)
    want = np.mean([jax_actions(MIXTURE, member(params, i), frames, stacks) for i in range(2)], 0)
    np.testing.assert_allclose(pol.run(frames), want, rtol=0, atol=1e-5)
    with pytest.raises(ExportError, match="mean head only.*'mixture'"):
        export(params, MIXTURE, World(), str(tmp_path / "mix2"), ensemble=True, onnx=True)


def test_export_refuses_bad_requests(tmp_path, ensemble_export):
    ens = random_params(LSTM, seed=5, members=2)
    with pytest.raises(ExportError, match="ensemble of 2 members"):
        export(ens, LSTM, World(), str(tmp_path / "a"))
    with pytest.raises(ExportError, match="not both"):
        export(ens, LSTM, World(), str(tmp_path / "a"), member=0, ensemble=True)
    with pytest.raises(ExportError, match="out of range"):
        export(ens, LSTM, World(), str(tmp_path / "a"), member=2)
    with pytest.raises(ExportError, match="do not match the PolicyConfig"):
        export(ens, PolicyConfig(hidden=16, layers=2), World(), str(tmp_path / "a"), member=0)
    p16 = PolicyConfig(hidden=8, layers=1, obs_size=16)    # the tracker's velocity: exported, not refused
    with pytest.raises(ExportError, match="do not match the PolicyConfig"):
        export(random_params(p16), PolicyConfig(hidden=8, layers=1), World(), str(tmp_path / "a"))
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        export(ens, LSTM, World(), ensemble_export[0], ensemble=True)


# --------------------------------------------------------------------------- refusals
def _copy(src, tmp_path, name="x"):
    dst = str(tmp_path / name)
    shutil.copytree(src, dst)
    return dst


def _rehash_manifest(d):
    """Make manifest.json match the files as they are now (a tamperer who also fixes the
    manifest), so that only the deeper checks can catch a change."""
    path = os.path.join(d, MANIFEST_FILE)
    with open(path) as f:
        man = json.load(f)
    for name in man["files"]:
        if os.path.exists(os.path.join(d, name)):
            man["files"][name]["sha256"] = sha256_bytes(open(os.path.join(d, name), "rb").read())
    with open(path, "w") as f:
        json.dump(man, f)


def _edit_contract(d, fn):
    path = os.path.join(d, CONTRACT_FILE)
    with open(path) as f:
        doc = json.load(f)
    fn(doc)
    with open(path, "w") as f:
        json.dump(doc, f)
    _rehash_manifest(d)


def _rewrite_tensors(d, name, key, fn):
    """Change a .safetensors file and make the contract's hash (and tensor list) match it, so
    only the deeper checks can catch the change."""
    from safetensors.numpy import load, save
    path = os.path.join(d, name)
    with open(path, "rb") as f:
        tensors = dict(load(f.read()))
    fn(tensors)
    data = save(tensors)
    with open(path, "wb") as f:
        f.write(data)

    def fix(doc):
        doc[key]["sha256"] = sha256_bytes(data)
        if key == "weights":
            doc[key]["tensors"] = {k: list(v.shape) for k, v in tensors.items()}
    _edit_contract(d, fix)     # also rehashes the manifest


def test_tampered_or_mismatched_exports_are_refused(ensemble_export, tmp_path):
    src = ensemble_export[0]
    cases = []

    def case(name, match, mutate):
        cases.append((name, match, mutate))

    def flip_byte(d):
        path = os.path.join(d, WEIGHTS_FILE)
        data = bytearray(open(path, "rb").read())
        data[-5] ^= 0x01
        open(path, "wb").write(bytes(data))
        _rehash_manifest(d)
    case("weights byte flipped, manifest fixed", "does not match the contract", flip_byte)
    case("golden byte flipped, manifest fixed", "does not match the contract", lambda d: (
        open(os.path.join(d, GOLDEN_FILE), "ab").write(b"\0"), _rehash_manifest(d)))
    case("another robot", "for robot", lambda d: _edit_contract(
        d, lambda c: c["robot"].__setitem__("model_id", "kuka-kr6/v1")))
    case("joint order", "joint order", lambda d: _edit_contract(
        d, lambda c: c["robot"].__setitem__("joint_names", c["robot"]["joint_names"][::-1])))
    case("wider range", "beyond this robot", lambda d: _edit_contract(
        d, lambda c: c["runtime"]["upper"].__setitem__(0, 0.5)))
    case("faster", "beyond this robot", lambda d: _edit_contract(
        d, lambda c: c["runtime"]["max_speed"].__setitem__(2, 9.0)))
    case("hidden size", "has shape|do not match", lambda d: _edit_contract(
        d, lambda c: c["policy"].__setitem__("hidden", 64)))
    case("member count", "has shape|do not match", lambda d: _edit_contract(
        d, lambda c: c["policy"].__setitem__("members", 2)))
    case("tensor shape", "has shape", lambda d: _rewrite_tensors(
        d, WEIGHTS_FILE, "weights", lambda t: t.__setitem__(
            "net/params/head/kernel", np.zeros((3, 31, 8), np.float32))))
    case("tensor dtype", "dtype", lambda d: _rewrite_tensors(
        d, WEIGHTS_FILE, "weights", lambda t: t.__setitem__(
            "net/params/head/bias", t["net/params/head/bias"].astype(np.float64))))
    case("extra tensor", "unexpected", lambda d: _rewrite_tensors(
        d, WEIGHTS_FILE, "weights", lambda t: t.__setitem__("net/params/lstm9/x", np.zeros((3, 1), np.float32))))
    case("weights changed, hash fixed", "golden self-test failed", lambda d: _rewrite_tensors(
        d, WEIGHTS_FILE, "weights", lambda t: t.__setitem__(
            "net/params/head/bias", t["net/params/head/bias"] + 1e-3)))
    case("golden changed, hash fixed", "golden self-test failed", lambda d: _rewrite_tensors(
        d, GOLDEN_FILE, "golden", lambda t: t.__setitem__("member_actions", t["member_actions"] + 1e-4)))
    case("normalization listed differs", "normalization", lambda d: _edit_contract(
        d, lambda c: c["normalization"]["per_member"]["obs_std"][0].__setitem__(0, 2.0)))
    case("not an export", "not a ttmjx-policy-export", lambda d: _edit_contract(d, lambda c: c.__setitem__("format", "x")))
    case("runtime contract", "invalid runtime", lambda d: _edit_contract(
        d, lambda c: c["runtime"].__setitem__("obs_size", 15)))
    case("runtime frame of another width", "contract.json: policy.obs_size 13 differs from runtime.obs_size 16",
         lambda d: _edit_contract(d, lambda c: c["runtime"].__setitem__("obs_size", 16)))
    case("unknown runtime key", "invalid runtime", lambda d: _edit_contract(
        d, lambda c: c["runtime"].__setitem__("pickle", True)))
    for i, (name, match, mutate) in enumerate(cases):
        d = _copy(src, tmp_path, f"case{i}")
        mutate(d)
        with pytest.raises(ExportError, match=match):
            load_export(d)
    # The intact export still loads; a robot with other joint names refuses it.
    load_export(src)
    with pytest.raises(ExportError, match="joint order"):
        load_export(src, expected_joints=("a",) * 8)


# --------------------------------------------------------------------------- manifest
def test_manifest_hashes_every_file_and_loading_refuses_any_change(ensemble_export, tmp_path):
    """manifest.json lists every file with its SHA-256, the contract included; a changed,
    missing or unexpected file, or no manifest at all (format 1), is refused naming the file."""
    src = ensemble_export[0]
    man = json.load(open(os.path.join(src, MANIFEST_FILE)))
    assert man["format_version"] == 2 and set(man["files"]) == set(os.listdir(src)) - {MANIFEST_FILE}
    for name, entry in man["files"].items():
        data = open(os.path.join(src, name), "rb").read()
        assert entry == {"sha256": sha256_bytes(data), "bytes": len(data)}

    def flip(name):
        def mutate(d):
            path = os.path.join(d, name)
            data = bytearray(open(path, "rb").read())
            data[len(data) // 2] ^= 0x20        # one bit, mid-file (for the contract: one letter)
            open(path, "wb").write(bytes(data))
        return mutate
    cases = [
        (flip(CONTRACT_FILE), rf"{CONTRACT_FILE}: SHA-256 \w+ does not match {MANIFEST_FILE}"),
        (flip(WEIGHTS_FILE), rf"{WEIGHTS_FILE}: SHA-256 \w+ does not match {MANIFEST_FILE}"),
        (flip(GOLDEN_FILE), rf"{GOLDEN_FILE}: SHA-256 \w+ does not match {MANIFEST_FILE}"),
        (lambda d: os.remove(os.path.join(d, GOLDEN_FILE)), rf"{GOLDEN_FILE}: missing \(listed in"),
        (lambda d: open(os.path.join(d, "notes.txt"), "w").write("hi"), r"notes.txt: not listed in"),
        (lambda d: os.remove(os.path.join(d, MANIFEST_FILE)), r"manifest.json: missing: .*format version 1"),
        (lambda d: _edit_manifest(d, lambda m: m.__setitem__("format_version", 1)), r"format version 1, this"),
        (lambda d: _edit_manifest(d, lambda m: m["files"].__setitem__("../x", m["files"][GOLDEN_FILE])),
         r"lists '../x', expected a plain file name"),
    ]
    if HAVE_ONNX:
        cases.append((flip(ONNX_FILE), rf"{ONNX_FILE}: SHA-256 \w+ does not match {MANIFEST_FILE}"))
    for i, (mutate, match) in enumerate(cases):
        d = _copy(src, tmp_path, f"m{i}")
        mutate(d)
        with pytest.raises(ExportError, match=match):
            load_export(d)
        with pytest.raises(ExportError, match=match):
            read_contract(d)
    pol, _ = load_export(src)                       # untouched: loads
    assert pol.members == 3


def _edit_manifest(d, fn):
    path = os.path.join(d, MANIFEST_FILE)
    man = json.load(open(path))
    fn(man)
    json.dump(man, open(path, "w"))


# --------------------------------------------------------------------------- ONNX
@pytest.fixture(scope="module")
def mlp_export(tmp_path_factory):
    """A 2-member frame-stack MLP ensemble (k = 4) exported at 20 Hz (made once)."""
    out = str(tmp_path_factory.mktemp("exports") / "mlp")
    export(random_params(MLP, seed=8, members=2), MLP, World(), out, ensemble=True, control_hz=20)
    return out


@pytest.mark.parametrize("which", ["lstm", "framestack"])
def test_onnx_graph_equals_numpy_policy_on_the_golden_inputs(which, ensemble_export, mlp_export):
    """policy.onnx on onnxruntime (one thread) gives the numpy policy's actions, member actions
    and LSTM state, step by step from reset, on the golden frames and on fresh ones."""
    pytest.importorskip("onnxruntime")
    from safetensors.numpy import load

    from deploy.robot import load_onnx_export
    d = ensemble_export[0] if which == "lstm" else mlp_export
    npol, contract = load_export(d)
    opol, ocontract = load_onnx_export(d)
    assert ocontract == contract and opol.members == npol.members and 0 <= opol.self_test_error <= 1e-5
    section = read_contract(d)["onnx"]
    assert section["file"] == ONNX_FILE and section["golden_error"] <= 1e-5
    assert section["checked_with"].startswith("onnxruntime")
    golden = load(open(os.path.join(d, GOLDEN_FILE), "rb").read())
    fresh = observations(24, contract.frame_stack, seed=11)
    for frames, stacks in ((golden["frames"], golden["stacks"]), fresh):
        stacks = stacks[:, stacks.shape[1] - npol.spec.input_frames:]
        s_np, s_ox = npol.reset(), opol.reset()
        for t in range(len(frames)):
            s_np, m_np = npol.step_members(s_np, frames[t], stacks[t])
            s_ox2, a_ox = opol.step(s_ox, frames[t], stacks[t])
            _, m_ox = opol.step_members(s_ox, frames[t], stacks[t])
            s_ox = s_ox2
            assert a_ox.shape == (8,) and a_ox.dtype == np.float32
            np.testing.assert_allclose(m_ox, m_np, rtol=0, atol=1e-5)
            np.testing.assert_allclose(a_ox, m_np.mean(0), rtol=0, atol=1e-5)
            if which == "lstm":
                np.testing.assert_allclose(s_ox, s_np, rtol=0, atol=1e-5)
        assert np.abs(m_np).max() > 0.5                  # non-trivial actions
    np.testing.assert_allclose(opol.run(golden["frames"], golden["stacks"][:, -npol.spec.input_frames:]),
                               golden["actions"], rtol=0, atol=1e-5)


def test_onnx_optional(tmp_path, monkeypatch):
    """onnx=False writes no graph (and load_onnx_export says so); without the `onnx` package,
    onnx=True is a one-line error naming the extra to install and the default skips the graph."""
    params = random_params(MLP, seed=2)
    export(params, MLP, World(), str(tmp_path / "off"), onnx=False)
    assert ONNX_FILE not in os.listdir(tmp_path / "off") and read_contract(str(tmp_path / "off"))["onnx"] is None
    load_export(str(tmp_path / "off"))
    from deploy.robot import load_onnx_export
    with pytest.raises(ExportError, match="has no ONNX graph"):
        load_onnx_export(str(tmp_path / "off"))
    monkeypatch.setitem(sys.modules, "onnx", None)          # `import onnx` now raises ImportError
    with pytest.raises(ExportError, match=r"optional package 'onnx'.*pip install 'ttmjx\[onnx\]'"):
        export(params, MLP, World(), str(tmp_path / "on"), onnx=True)
    export(params, MLP, World(), str(tmp_path / "auto"))
    assert sorted(os.listdir(tmp_path / "auto")) == sorted([CONTRACT_FILE, WEIGHTS_FILE, GOLDEN_FILE, MANIFEST_FILE])


def test_load_needs_numpy_only(ensemble_export):
    """The robot's side (load_export, the numpy policy, the runner) never imports JAX."""
    code = ("import sys; from deploy.robot.exported import load_export; from deploy.robot.runner import Runner; "
            f"p, c = load_export({ensemble_export[0]!r}); "
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('jax', 'jaxlib', 'flax', 'mujoco', 'torch')); "
            "assert not bad, bad; print(p.members)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "3"


def test_export_checkpoint_reads_the_configuration_saved_with_the_checkpoint(tmp_path):
    """export_checkpoint opens a run through the one loader (training.checkpoint.load_checkpoint):
    the PolicyConfig, World and acting parameters saved with it; the member asked for."""
    from training.checkpoint import load_checkpoint
    run = os.path.join(ROOT, "tests", "data", "tiny_run_v0")
    loaded = load_checkpoint(run)
    out = export_checkpoint(run, str(tmp_path / "exp"), member=1, control_hz=20)
    pol, contract = load_export(out)
    doc = read_contract(out)
    pcfg = loaded.cfg.policy
    assert pol.members == 1 and contract.control_hz == 20.0 and contract.frame_stack == pcfg.frame_stack
    assert doc["policy"]["kind"] == pcfg.kind and doc["policy"]["hidden"] == pcfg.hidden
    assert doc["source"]["checkpoint"] == f"{os.path.abspath(loaded.directory)}@{loaded.step}"
    assert doc["source"]["members"] == [1] and doc["world"]["control_hz"] == loaded.cfg.world.control_hz
    frames, stacks = observations(10, pcfg.frame_stack, seed=1)
    np.testing.assert_allclose(pol.run(frames, stacks), jax_actions(pcfg, member(loaded.params, 1), frames, stacks),
                               rtol=0, atol=1e-5)
    with pytest.raises(ExportError, match="ensemble of 2 members"):
        export_checkpoint(run, str(tmp_path / "two"))
    with pytest.raises(FileNotFoundError, match="no checkpoint step 5"):
        export_checkpoint(run, str(tmp_path / "five"), step=5)
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        export_checkpoint(run, out, member=0)


def test_latency_benchmark_runs_on_one_thread():
    res = benchmark("lstm", hidden=64, layers=2, steps=50, warmup=5)
    assert res["threads"] == 1 and res["threads_env"]["OMP_NUM_THREADS"] == "1"
    assert 0 < res["p50_ms"] <= res["p99_ms"] <= res["max_ms"]
    assert 0 < res["prepared_p50_ms"] <= res["prepared_p99_ms"] and res["prepare_p50_ms"] > 0


def test_latency_benchmark_of_the_onnx_graph():
    pytest.importorskip("onnxruntime")
    res = benchmark("framestack", hidden=64, layers=2, members=2, steps=50, warmup=5, engine="onnx",
                    obs_size=16, frame_stack=8)
    assert res["engine"] == "onnx" and res["threads"] == 1 and res["onnxruntime"]
    assert res["obs_size"] == 16 and res["frame_stack"] == 8
    assert 0 < res["p50_ms"] <= res["p99_ms"] <= res["max_ms"]
