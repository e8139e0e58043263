"""An exported policy, loaded (numpy only, with every check): the export format and its reader.

The writer is deploy/sim/export.py (it needs JAX to compute the golden actions).

An export is a directory of four or five files, nothing pickled:

  weights.safetensors  float32 tensors named by their flattened parameter paths, each with a
                       leading member axis [N, ...] (N = 1 for one member):
                       `net/params/lstm0/hf/kernel`, ..., `net/params/head/bias`,
                       `norm/obs_mean`, `norm/obs_std`, `norm/act_mean`, `norm/act_std`
  golden.safetensors   a short random-but-valid observation sequence (`frames` [L, O],
                       `stacks` [L, k, O]) and the JAX policy's actions on it from a zero
                       state (`member_actions` [N, L, 8], `actions` [L, 8] = their mean)
  contract.json        what the runner, the robot and the policy must agree on: format and
                       version; the robot model id and joint order, units, ranges and speed
                       limits; the control rate and frame stack (`runtime`, a Contract);
                       the timing model and ranges the policy was trained under
                       (`timing`, deploy/robot/timing_check.py: the station's default timing and
                       what a station is checked against);
                       the observation layout (ttmjx.world.observation) and order; the goal
                       frame and units; the policy type, sizes, recurrent state shape and
                       ensemble rule; the normalization; the source checkpoint; the SHA-256 of
                       both .safetensors files and the shape of every tensor; the ONNX graph's
                       inputs and outputs; the World config the policy was trained in.
  policy.onnx          (when the optional `onnx` package is installed, or asked for) one step of
                       the policy as an ONNX graph, normalization and the ensemble mean included
                       (deploy/robot/onnx_policy.py); checked on the golden frames when written
  manifest.json        written last: `format`, `format_version` (2) and the SHA-256 and size of
                       every other file in the directory, the contract included

`load_export(dir)` (numpy only) refuses a tampered or mismatched export with an ExportError
naming the problem: no manifest (exports of format version 1 had none: they are refused, to be
exported again, since a manifest that could be deleted would protect nothing), a file missing
from or absent in the manifest, a hash that does not match, tensors of the wrong names, shapes or
dtypes, a contract for another robot (model id, joint names, limits wider than the robot's), or a
golden self-test whose numpy actions differ from the stored JAX actions by more than GOLDEN_TOL.
`load_onnx_export(dir)` makes the same checks and serves policy.onnx on onnxruntime instead.

Ensembles: `ensemble=True` exports every member; the numpy policy steps each member with its
own state and normalizer and sends the MEAN of their actions (deploy/robot/numpy_policy.py).
`member=i` exports one member.
"""
from __future__ import annotations

import hashlib
import json
import os

import numpy as np

from deploy.robot.contract import REAL_OBS_SIZE, ROBOT_MODEL_ID, Contract, contract_from_dict
from deploy.robot.numpy_policy import ACTION_SIZE, NORM_FIELDS, ExportedPolicy, PolicySpec, check_tensors
from deploy.robot.onnx_policy import MissingExtra, OnnxPolicy
from ttmjx.world import observation
from ttmjx.world.config import JOINT_NAMES, World

EXPORT_FORMAT = "ttmjx-policy-export"
EXPORT_VERSION = 2         # 2: manifest.json hashes every file; optional policy.onnx
WEIGHTS_FILE = "weights.safetensors"
GOLDEN_FILE = "golden.safetensors"
CONTRACT_FILE = "contract.json"
ONNX_FILE = "policy.onnx"
MANIFEST_FILE = "manifest.json"
REQUIRED_FILES = (CONTRACT_FILE, WEIGHTS_FILE, GOLDEN_FILE)
GOLDEN_TOL = 1e-5          # max |numpy - JAX| over the golden actions (fixed here, not read)
GOLDEN_STEPS = 16
ENSEMBLE_RULE = ("mean of the members' actions (absolute joint targets, after each member's own "
                 "denormalization); each member keeps its own recurrent state")
JOINT_UNITS = ("m", "m", "rad", "rad", "rad", "rad", "rad", "rad")


class ExportError(ValueError):
    """An export that cannot be written, or one that must not be run (the message says why)."""


def frame_layout(width: int = REAL_OBS_SIZE) -> tuple[list[str], list[str]]:
    """(names, units) of the robot's frame columns: ttmjx.world.observation's layout of `width`."""
    names = observation.names(width, JOINT_NAMES)
    units = ["m"] * 3 + (["m/s"] * 3 if width == 16 else []) + ["m"] * 2
    return names, [*JOINT_UNITS, *units]


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------
def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _parse_tensors(directory: str, files: dict, name: str, sha256: str) -> dict:
    """Parse a .safetensors file from the bytes the manifest check read (files: name ->
    bytes), after checking them against the contract's SHA-256 too."""
    from safetensors.numpy import load
    path = os.path.join(directory, name)
    if name not in files:
        raise ExportError(f"{path}: named by the contract but not in {MANIFEST_FILE}")
    data = files[name]
    got = sha256_bytes(data)
    if got != sha256:
        raise ExportError(f"{path}: SHA-256 {got} does not match the contract's {sha256}: the file "
                          f"was modified or belongs to another export; refusing to load it")
    try:
        return dict(load(data))
    except Exception as e:  # noqa: BLE001 - the library raises its own error types
        raise ExportError(f"{path}: not a readable safetensors file ({e})") from e


def _unflatten(tensors: dict, prefix: str) -> dict:
    """Inverse of _flatten for the tensors under `prefix`."""
    tree = {}
    for name, v in tensors.items():
        if not name.startswith(prefix + "/"):
            continue
        node, parts = tree, name[len(prefix) + 1:].split("/")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = v
    return tree


# --------------------------------------------------------------------------------------------
# Load
# --------------------------------------------------------------------------------------------
def _check_format(doc, path: str, what: str, version_key: str) -> None:
    """ExportError unless doc is a dict of this export format (`format`) and version (`version_key`)."""
    if not isinstance(doc, dict) or doc.get("format") != EXPORT_FORMAT:
        raise ExportError(f"{path}: not a {EXPORT_FORMAT} {what}")
    if doc.get(version_key) != EXPORT_VERSION:
        raise ExportError(f"{path}: export format version {doc.get(version_key)!r}, this runner "
                          f"reads version {EXPORT_VERSION}")


def _read_manifest(directory: str) -> dict:
    """manifest.json's `files` (name -> {sha256, bytes}), its format and version checked."""
    path = os.path.join(directory, MANIFEST_FILE)
    if not os.path.isdir(directory):
        raise ExportError(f"{directory}: not a directory (expected a policy export)")
    try:
        with open(path, "rb") as f:
            doc = json.loads(f.read())
    except FileNotFoundError:
        raise ExportError(f"{path}: missing: not a policy export, an incomplete one, or one of "
                          f"format version 1 (no manifest: refused; export the checkpoint again "
                          f"with `ttmjx export`)") from None
    except (OSError, ValueError) as e:
        raise ExportError(f"{path}: unreadable manifest ({e})") from e
    _check_format(doc, path, "manifest", "format_version")
    listed = doc.get("files")
    if not isinstance(listed, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("sha256"), str) for v in listed.values()):
        raise ExportError(f"{path}: no 'files' table of {{name: {{sha256, bytes}}}}")
    for name in listed:
        if name != os.path.basename(name) or name in (MANIFEST_FILE, ".", "..") or not name:
            raise ExportError(f"{path}: lists {name!r}, expected a plain file name of this directory")
    return listed


def verified_files(directory: str) -> dict:
    """{name: bytes} of every file of an export, each read once and checked against
    manifest.json: a missing file, a file the manifest does not list, or a SHA-256 that does
    not match is an ExportError naming the file."""
    listed = _read_manifest(directory)
    for name in REQUIRED_FILES:
        if name not in listed:
            raise ExportError(f"{os.path.join(directory, MANIFEST_FILE)}: does not list {name}")
    present = set(os.listdir(directory)) - {MANIFEST_FILE}
    extra = sorted(present - set(listed))
    if extra:
        raise ExportError(f"{os.path.join(directory, extra[0])}: not listed in {MANIFEST_FILE}: an "
                          f"unexpected file in the export; refusing to load it")
    out = {}
    for name, entry in sorted(listed.items()):
        path = os.path.join(directory, name)
        if name not in present or not os.path.isfile(path):
            raise ExportError(f"{path}: missing (listed in {MANIFEST_FILE}); an incomplete export")
        with open(path, "rb") as f:
            data = f.read()
        got = sha256_bytes(data)
        if got != entry["sha256"]:
            raise ExportError(f"{path}: SHA-256 {got} does not match {MANIFEST_FILE}'s "
                              f"{entry['sha256']}: the file was modified; refusing to load it")
        out[name] = data
    return out


def read_contract(directory: str, verified: dict | None = None) -> dict:
    """The parsed contract.json of an export (every file checked against the manifest, then
    format and version). verified: verified_files(directory) if already read."""
    path = os.path.join(directory, CONTRACT_FILE)
    verified = verified_files(directory) if verified is None else verified
    try:
        doc = json.loads(verified[CONTRACT_FILE])
    except ValueError as e:
        raise ExportError(f"{path}: unreadable contract ({e})") from e
    _check_format(doc, path, "contract", "version")
    for key in ("robot", "runtime", "policy", "weights", "golden", "normalization"):
        if not isinstance(doc.get(key), dict):
            raise ExportError(f"{path}: the contract has no {key!r} section")
    return doc


def _check_robot(doc: dict, runtime: Contract, expected_robot: str, expected_joints,
                 robot_limits: Contract | None, tol: float = 1e-9) -> None:
    rob = doc["robot"]
    if rob.get("model_id") != expected_robot:
        raise ExportError(f"the export is for robot {rob.get('model_id')!r}, this is {expected_robot!r}; "
                          f"refusing to run it")
    if tuple(rob.get("joint_names", ())) != tuple(expected_joints):
        raise ExportError(f"the export's joint order {rob.get('joint_names')} differs from this "
                          f"robot's {list(expected_joints)}; refusing to run it")
    if tuple(runtime.joint_names) != tuple(expected_joints):
        raise ExportError(f"the runtime contract's joint order {list(runtime.joint_names)} differs "
                          f"from this robot's {list(expected_joints)}")
    if robot_limits is None:
        return
    names = list(expected_joints)
    for field, worse in (("lower", lambda e, r: e < r - tol), ("upper", lambda e, r: e > r + tol),
                         ("max_speed", lambda e, r: e > r + tol)):
        e, r = np.asarray(getattr(runtime, field)), np.asarray(getattr(robot_limits, field))
        bad = np.flatnonzero(worse(e, r))
        if bad.size:
            j = int(bad[0])
            raise ExportError(f"the export's {field}[{names[j]}] = {e[j]:.6g} is beyond this robot's "
                              f"{r[j]:.6g}; refusing a contract wider than the robot")
    if runtime.speed_margin > robot_limits.speed_margin + tol:
        raise ExportError(f"the export's speed_margin {runtime.speed_margin} exceeds this robot's "
                          f"{robot_limits.speed_margin}")


def self_test(policy, golden: dict, tol: float = GOLDEN_TOL, what: str = "numpy policy") -> float:
    """Run a policy (numpy or ONNX, `run(frames, stacks, members)`) on the golden frames;
    max |policy - JAX| (raises ExportError > tol)."""
    frames, stacks = golden.get("frames"), golden.get("stacks")
    member_actions = golden.get("member_actions")
    n, k, o = policy.members, policy.spec.input_frames, policy.spec.obs_size
    if frames is None or stacks is None or member_actions is None or frames.ndim != 2:
        raise ExportError(f"golden file lacks frames [L, {o}], stacks [L, k, {o}] or member_actions")
    length = frames.shape[0]
    if (frames.shape != (length, o) or stacks.shape[0] != length
            or stacks.shape[2] != o or stacks.shape[1] < k
            or member_actions.shape != (n, length, ACTION_SIZE)):
        raise ExportError(f"golden arrays have shapes frames {frames.shape}, stacks {stacks.shape}, "
                          f"member_actions {member_actions.shape}; expected ({length}, {o}), "
                          f"({length}, >={k}, {o}), ({n}, {length}, {ACTION_SIZE})")
    got = policy.run(frames, stacks[:, stacks.shape[1] - k:], members=True)
    err = float(np.max(np.abs(got - member_actions))) if got.size else 0.0
    mean_err = float(np.max(np.abs(got.mean(0) - golden.get("actions", member_actions.mean(0)))))
    err = max(err, mean_err)
    if not err <= tol:
        raise ExportError(f"golden self-test failed: the {what}'s actions differ from the JAX "
                          f"policy's by up to {err:.3g} (> {tol:g}); refusing to run it")
    return err


def _runtime_of(doc: dict, directory: str) -> Contract:
    try:
        return contract_from_dict(doc["runtime"])
    except (TypeError, ValueError) as e:
        raise ExportError(f"{os.path.join(directory, CONTRACT_FILE)}: invalid runtime contract: {e}") from e


def _policy_of(doc: dict, runtime: Contract, directory: str) -> tuple[PolicySpec, int]:
    """(spec, members) of the contract's policy section, checked against the runtime."""
    pol = doc["policy"]
    try:
        # Exports before the mixture head have no head fields: theirs is the mean head.
        spec = PolicySpec(pol["kind"], pol["hidden"], pol["layers"], pol["obs_size"],
                          pol["frame_stack"], pol.get("head", "mean"), pol.get("components", 1)).check()
        members = int(pol["members"])
    except (KeyError, TypeError, ValueError) as e:
        raise ExportError(f"{directory}: invalid policy section ({e})") from e
    path = os.path.join(directory, CONTRACT_FILE)
    if spec.obs_size != runtime.obs_size:
        raise ExportError(f"{path}: policy.obs_size {spec.obs_size} differs from runtime.obs_size "
                          f"{runtime.obs_size}: the policy reads {spec.obs_size} values per frame, the "
                          f"contract's runtime section claims frames of {runtime.obs_size}; the export "
                          f"contradicts itself (export the checkpoint again)")
    if spec.kind == "framestack" and spec.frame_stack != runtime.frame_stack:
        raise ExportError(f"{path}: policy.frame_stack {spec.frame_stack} differs from runtime.frame_stack "
                          f"{runtime.frame_stack}: the frame-stack policy needs {spec.frame_stack} frames; the "
                          f"export contradicts itself (export the checkpoint again)")
    return spec, members


def _weights_of(doc: dict, spec: PolicySpec, members: int, directory: str, verified: dict) -> dict:
    """The weight tensors, checked against their hash, the contract's tensor list, the policy
    and the contract's normalization."""
    w = doc["weights"]
    tensors = _parse_tensors(directory, verified, w.get("file", WEIGHTS_FILE), str(w.get("sha256")))
    listed = {k: tuple(v) for k, v in (w.get("tensors") or {}).items()}
    actual = {k: tuple(v.shape) for k, v in tensors.items()}
    if listed != actual:
        diff = sorted(set(listed.items()) ^ set(actual.items()))[:4]
        raise ExportError(f"the weights' tensors differ from the contract's list (e.g. {diff})")
    try:
        check_tensors(spec, tensors, members)
    except ValueError as e:
        raise ExportError(f"{directory}: {e}") from e
    norm = doc["normalization"].get("per_member", {})
    for k in NORM_FIELDS:
        listed_norm = np.asarray(norm.get(k, []), np.float32)
        if listed_norm.shape != tensors[f"norm/{k}"].shape or not np.array_equal(listed_norm, tensors[f"norm/{k}"]):
            raise ExportError(f"the contract's normalization {k} differs from the weights' norm/{k}")
    return tensors


def load_export(directory: str, expected_robot: str = ROBOT_MODEL_ID,
                expected_joints=JOINT_NAMES, robot_limits: Contract | None = Contract(),
                run_self_test: bool = True) -> tuple[ExportedPolicy, Contract]:
    """(numpy policy, runtime Contract) of an export, after every check (module docstring).

    robot_limits: this robot's joint ranges and speed limits (default: ttmjx's robot config); an
    export whose contract is wider anywhere is refused (None skips the check). The returned
    policy's `policy_hash` is 'sha256:<weights hash>' and `self_test_error` the golden error.
    """
    verified, doc, runtime, spec, tensors = _checked_export(directory, expected_robot, expected_joints,
                                                            robot_limits)
    policy = ExportedPolicy(spec, tensors, policy_hash="sha256:" + doc["weights"]["sha256"])
    if run_self_test:
        policy.self_test_error = self_test(policy, _golden_of(doc, directory, verified))
    policy.contract_doc = doc
    return policy, runtime


def read_weights(directory: str, expected_robot: str = ROBOT_MODEL_ID, expected_joints=JOINT_NAMES,
                 robot_limits: Contract | None = Contract()) -> tuple[PolicySpec, dict]:
    """(spec, weight tensors with a leading [members] axis) of an export, after every check of
    load_export but the golden self-test: the weights for another engine (the JAX policy of
    deploy.sim.parity)."""
    _, _, _, spec, tensors = _checked_export(directory, expected_robot, expected_joints, robot_limits)
    return spec, tensors


def _checked_export(directory: str, expected_robot, expected_joints, robot_limits) -> tuple:
    """(verified files, contract, runtime Contract, spec, weight tensors) after every check of
    load_export but the golden self-test."""
    verified = verified_files(directory)
    doc = read_contract(directory, verified)
    runtime = _runtime_of(doc, directory)
    _check_robot(doc, runtime, expected_robot, expected_joints, robot_limits)
    spec, members = _policy_of(doc, runtime, directory)
    return verified, doc, runtime, spec, _weights_of(doc, spec, members, directory, verified)


def _golden_of(doc: dict, directory: str, verified: dict) -> dict:
    g = doc["golden"]
    return _parse_tensors(directory, verified, g.get("file", GOLDEN_FILE), str(g.get("sha256")))


def load_onnx_export(directory: str, threads: int = 1, expected_robot: str = ROBOT_MODEL_ID,
                     expected_joints=JOINT_NAMES, robot_limits: Contract | None = Contract()
                     ) -> tuple[OnnxPolicy, Contract]:
    """(ONNX policy on onnxruntime with `threads` intra-op threads, runtime Contract): every
    check of load_export, then policy.onnx's golden self-test. ExportError if the export has
    no graph or onnxruntime is not installed."""
    verified, doc, runtime, spec, tensors = _checked_export(directory, expected_robot, expected_joints,
                                                            robot_limits)
    section = doc.get("onnx")
    if not isinstance(section, dict) or section.get("file") not in verified:
        raise ExportError(f"{os.path.join(directory, ONNX_FILE)}: this export has no ONNX graph "
                          f"(written without the `onnx` package or with --onnx off); export again")
    data = verified[section["file"]]
    if sha256_bytes(data) != section.get("sha256"):
        raise ExportError(f"{os.path.join(directory, section['file'])}: SHA-256 differs from the "
                          f"contract's onnx.sha256; refusing to load it")
    n = int(tensors["net/params/head/bias"].shape[0])
    try:
        policy = OnnxPolicy(spec, n, data, threads=threads, policy_hash="sha256:" + section["sha256"])
    except MissingExtra as e:
        raise ExportError(str(e)) from None
    policy.self_test_error = self_test(policy, _golden_of(doc, directory, verified), what="ONNX graph")
    policy.contract_doc = doc
    return policy, runtime


def export_world(doc: dict) -> World:
    """The World config an export was trained in (contract 'world'; defaults if absent)."""
    from ttmjx.world.config import from_dict
    return from_dict(World, doc["world"]) if isinstance(doc.get("world"), dict) else World()

