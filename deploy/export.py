"""Export a trained policy for the robot, and load it back (numpy only) with every check.

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
                       limits; the control rate and frame stack (`runtime`, a deploy.Contract);
                       the timing model and ranges the policy was trained under
                       (`timing`, deploy/timing_check.py: the station's default timing and
                       what a station is checked against);
                       the observation layout (ttmjx.world.observation) and order; the goal
                       frame and units; the policy type, sizes, recurrent state shape and
                       ensemble rule; the normalization; the source checkpoint; the SHA-256 of
                       both .safetensors files and the shape of every tensor; the ONNX graph's
                       inputs and outputs; the World config the policy was trained in.
  policy.onnx          (when the optional `onnx` package is installed, or asked for) one step of
                       the policy as an ONNX graph, normalization and the ensemble mean included
                       (deploy/onnx_policy.py); checked on the golden frames when written
  manifest.json        written last: `format`, `format_version` (2) and the SHA-256 and size of
                       every other file in the directory, the contract included

`export_checkpoint(path, out_dir)` exports a training checkpoint (opened by the one loader,
training.checkpoint.load_checkpoint: the configuration saved with it, never guessed);
`export(params, pcfg, world, out_dir)` exports parameters in hand. Both compute the golden
actions with models.make_policy (JAX). `load_export(dir)` (numpy only: this module imports JAX
lazily, inside export functions) refuses a tampered or mismatched export with an ExportError
naming the problem: no manifest (exports of format version 1 had none: they are refused, to be
exported again, since a manifest that could be deleted would protect nothing), a file missing
from or absent in the manifest, a hash that does not match, tensors of the wrong names/shapes/dtypes, a
contract for another robot (model id, joint names, limits wider than the robot's), or a golden
self-test whose numpy actions differ from the stored JAX actions by more than 1e-5.
`load_onnx_export(dir)` makes the same checks and serves policy.onnx on onnxruntime instead.

Ensembles: `ensemble=True` exports every member; the numpy policy steps each member with its
own state and normalizer and sends the MEAN of their actions (deploy/numpy_policy.py).
`member=i` exports one member.
"""
from __future__ import annotations

import datetime
import hashlib
import json
import math
import os

import numpy as np

from deploy.contract import (OBS_SIZES, REAL_OBS_SIZE, ROBOT_MODEL_ID, Contract, contract_from_dict,
                             contract_to_dict)
from deploy.numpy_policy import ACTION_SIZE, NORM_FIELDS, ExportedPolicy, PolicySpec, check_tensors
from deploy.onnx_policy import (INPUTS, IR_VERSION, OPSET, OUTPUTS, MissingExtra, OnnxPolicy,
                                import_onnxruntime, model_bytes, reference_session, session)
from deploy.timing_check import timing_record
from ttmjx.world import files, observation
from ttmjx.world.config import JOINT_NAMES, Robot, Table, World, opponent_half, to_dict

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


def _save_tensors(path: str, tensors: dict, metadata: dict) -> bytes:
    """Write a .safetensors file atomically; returns its bytes (for the hash)."""
    from safetensors.numpy import save
    data = save({k: np.ascontiguousarray(v) for k, v in tensors.items()}, metadata=metadata)
    files.write_bytes(path, data)
    return data


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


# --------------------------------------------------------------------------------------------
# Tensors
# --------------------------------------------------------------------------------------------
def _flatten(tree, prefix: str) -> dict:
    """Nested dicts (flax params, a Normalizer's _asdict) -> {'a/b/c': array}."""
    out = {}
    if hasattr(tree, "_asdict"):
        tree = tree._asdict()
    if isinstance(tree, dict) or hasattr(tree, "items"):
        for k, v in tree.items():
            out.update(_flatten(v, f"{prefix}/{k}" if prefix else str(k)))
        return out
    return {prefix: np.asarray(tree)}


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


def policy_tensors(params) -> tuple[dict, bool]:
    """PolicyParams (one member or an ensemble) -> (flat float32 tensors, is_ensemble)."""
    tensors = {**_flatten(params.net, "net"), **_flatten(params.norm, "norm")}
    head = tensors.get("net/params/head/bias")
    if head is None or head.ndim not in (1, 2):
        raise ExportError(f"params.net has no head bias [8] or [N, 8] (keys {sorted(tensors)[:6]}...)")
    return {k: np.asarray(v, np.float32) for k, v in tensors.items()}, head.ndim == 2


def _member_to_export(n: int, member: int | None, ensemble: bool) -> int | None:
    """The one member of an n-member ensemble to export (None: all of them)."""
    if ensemble and member is not None:
        raise ExportError("pass either ensemble=True (--ensemble: all members, actions averaged) "
                          "or member=i (--member i), not both")
    if ensemble:
        return None
    if member is None and n != 1:
        raise ExportError(f"the params hold an ensemble of {n} members: pass ensemble=True "
                          f"(--ensemble: all members, actions averaged) or member=i "
                          f"(--member i, 0 <= i < {n})")
    member = 0 if member is None else member
    if not 0 <= member < n:
        raise ExportError(f"member={member} is out of range for an ensemble of {n} members")
    return int(member)


def select_members(tensors: dict, is_ensemble: bool, member: int | None, ensemble: bool) -> tuple[dict, list]:
    """The tensors to export (leading [N] axis) and which members of the source they are."""
    if not is_ensemble:
        if member not in (None, 0):
            raise ExportError(f"member={member}: the params hold one member (no ensemble axis)")
        return {k: v[None] for k, v in tensors.items()}, [0]
    n = int(tensors["net/params/head/bias"].shape[0])
    one = _member_to_export(n, member, ensemble)
    if one is None:
        return tensors, list(range(n))
    return {k: v[one:one + 1] for k, v in tensors.items()}, [one]


def _spec(pcfg) -> PolicySpec:
    return PolicySpec(pcfg.kind, int(pcfg.hidden), int(pcfg.layers), int(pcfg.obs_size),
                      int(pcfg.frame_stack))


def export_tensors(params, pcfg, member: int | None, ensemble: bool) -> tuple[PolicySpec, dict, list]:
    """(spec, tensors with a leading [N] member axis, the source's member indices) of the
    members to export, checked against the PolicyConfig."""
    if pcfg.obs_size not in OBS_SIZES:
        raise ExportError(f"PolicyConfig.obs_size={pcfg.obs_size}: the robot's frames hold one of "
                          f"{OBS_SIZES} values")
    tensors, members = select_members(*policy_tensors(params), member, ensemble)
    spec = _spec(pcfg)
    try:
        check_tensors(spec, tensors)
    except ValueError as e:
        raise ExportError(f"params do not match the PolicyConfig: {e}") from e
    return spec, tensors, members


# --------------------------------------------------------------------------------------------
# Golden observations
# --------------------------------------------------------------------------------------------
def _fly(pos: np.ndarray, vel: np.ndarray, dt: float, table: Table, substeps: int = 10):
    """The golden ball over dt: gravity and a table bounce, in `substeps` steps -> (pos, vel)."""
    for _ in range(substeps):
        vel[2] -= 9.81 * dt / substeps
        pos = pos + vel * dt / substeps
        if pos[2] < table.top_z + 0.02 and abs(pos[0]) < table.half_length and vel[2] < 0:
            vel[2] = -0.9 * vel[2]
        pos[2] = max(pos[2], 0.02)
    return pos, vel


def golden_frames(contract: Contract, table: Table, steps: int = GOLDEN_STEPS, seed: int = 0) -> np.ndarray:
    """[steps, O] float32 frames (O: the contract's obs_size) a robot could see at the contract's rate: joints wandering
    from home within their ranges and speed limits, an incoming ball (gravity, table bounce),
    a goal on the opponent's half."""
    rng = np.random.default_rng(seed)
    lo, hi = np.asarray(contract.lower), np.asarray(contract.upper)
    step = np.asarray(contract.max_speed) * contract.speed_margin * contract.dt
    q = np.asarray(contract.home, np.float64).copy()
    pos = np.array([1.75, rng.uniform(-0.4, 0.4), rng.uniform(0.9, 1.0)])
    vel = np.array([rng.uniform(-7.5, -6.0), rng.uniform(-0.8, 0.8), rng.uniform(0.0, 1.5)])
    (gx0, gx1), (gy0, gy1) = opponent_half(table)
    goal = np.array([rng.uniform(gx0, gx1), rng.uniform(gy0, gy1)])
    frames = []
    for _ in range(steps):
        frames.append(observation.make_frame(q, pos, goal, vel.copy() if contract.obs_size == 16 else None))
        q = np.clip(q + rng.uniform(-0.5, 0.5, 8) * step, lo, hi)
        pos, vel = _fly(pos, vel, contract.dt, table)
    return np.asarray(frames, np.float32)


def _jax_member_actions(pcfg, tensors: dict, frames: np.ndarray, stacks: np.ndarray) -> np.ndarray:
    """frames [L, O], stacks [L, k, O] -> [N, L, 8]: models.make_policy(pcfg) from a zero state,
    each member, in JAX."""
    import jax
    import jax.numpy as jnp

    from models.normalizer import Normalizer
    from models.policy import PolicyParams, make_policy
    from ttmjx.world.env import Obs

    tensors = {k: jnp.asarray(v) for k, v in tensors.items()}
    norm = _unflatten(tensors, "norm")
    params = PolicyParams(_unflatten(tensors, "net"), Normalizer(**{k: norm[k] for k in Normalizer._fields}))
    policy = make_policy(pcfg)

    def one(p):
        def body(carry, xs):
            frame, stack, t = xs
            return policy.apply(p, carry, Obs(frame, jnp.zeros(3, jnp.float32), stack, t), None)
        xs = (jnp.asarray(frames), jnp.asarray(stacks), jnp.arange(len(frames), dtype=jnp.int32))
        return jax.lax.scan(body, policy.init(p, None), xs)[1]

    return np.asarray(jax.jit(jax.vmap(one))(params), np.float32)


def golden_set(pcfg, tensors: dict, runtime: Contract, table: Table, steps: int, seed: int) -> dict:
    """The golden file's arrays: frames [L, O], their stacks [L, k, O] (the runner's
    padding), the JAX members' actions [N, L, 8] and their mean [L, 8]."""
    frames = golden_frames(runtime, table, steps, seed)
    stacks = observation.frame_stack(frames[None], runtime.frame_stack)[0]
    member_actions = _jax_member_actions(pcfg, tensors, frames, stacks)
    return {"frames": frames, "stacks": stacks, "member_actions": member_actions,
            "actions": member_actions.mean(axis=0).astype(np.float32)}


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------
def runtime_contract(world_cfg: World, pcfg, control_hz: float | None = None) -> Contract:
    """The runtime contract of a policy trained in world_cfg, run at control_hz (default: the
    training rate). The frame stack is the policy's (frame-stack MLP) or the world's."""
    hz = float(world_cfg.control_hz if control_hz is None else control_hz)
    if not (math.isfinite(hz) and hz > 0):
        raise ExportError(f"control_hz={control_hz}, expected > 0")
    r = world_cfg.robot
    k = pcfg.frame_stack if pcfg.kind == "framestack" else world_cfg.frame_stack
    return Contract(control_hz=hz, frame_stack=int(k), obs_size=int(pcfg.obs_size),
                    extrapolate_s=float(world_cfg.timing.extrapolate_s), episode_s=world_cfg.episode_s,
                    lower=tuple(r.lower), upper=tuple(r.upper), max_speed=tuple(r.max_speed),
                    speed_margin=r.speed_margin, home=tuple(r.home), home_noise=tuple(r.home_noise))


def _refuse_existing(out_dir: str) -> None:
    for name in (*REQUIRED_FILES, ONNX_FILE, MANIFEST_FILE):
        if os.path.exists(os.path.join(out_dir, name)):
            raise FileExistsError(f"{os.path.join(out_dir, name)} already exists; refusing to "
                                  f"overwrite an export (choose a new --out or delete it first)")


def _robot_section(r: Robot) -> dict:
    return {"model_id": ROBOT_MODEL_ID, "joint_names": list(JOINT_NAMES),
            "joint_units": list(JOINT_UNITS), "lower": list(r.lower), "upper": list(r.upper),
            "max_speed": list(r.max_speed), "max_speed_units": "m/s (gantry), rad/s (arm)",
            "speed_margin": r.speed_margin, "home": list(r.home)}


def _observation_section(spec: PolicySpec, runtime: Contract) -> dict:
    names, units = frame_layout(runtime.obs_size)
    vel = runtime.obs_size == 16
    return {"frame_size": len(names), "frame": names, "units": units, "ball_velocity": vel,
            **({"ball_velocity_rule": "the slope of the line through the tracker's two newest samples "
                                      "(the line the ball position is read from)"} if vel else {}),
            "extrapolate_s": runtime.extrapolate_s,
            "frame_stack": runtime.frame_stack, "stack_order": "oldest first",
            "stack_padding": "the episode's first frame repeated",
            "timing": "joints and ball interpolated to each control deadline t0 + n / control_hz",
            "policy_input": ("the current frame (lstm)" if spec.kind == "lstm"
                             else f"the last {spec.frame_stack} frames flattened (framestack)")}


def _goal_section(table: Table) -> dict:
    (gx, gy) = opponent_half(table).tolist()
    return {"frame": "world: x along the table toward the opponent, y across, z up; table "
                     "centre at the origin, robot at negative x (docs/DESIGN.md)",
            "units": "m", "region": {"x": gx, "y": gy}}


def _policy_section(spec: PolicySpec, n: int, trained_hz: int) -> dict:
    lstm = spec.kind == "lstm"
    return {"kind": spec.kind, "hidden": spec.hidden, "layers": spec.layers,
            "obs_size": spec.obs_size, "frame_stack": spec.frame_stack,
            "input_frames": spec.input_frames, "members": n,
            "ensemble_rule": ENSEMBLE_RULE if n > 1 else "single member",
            "state": ({"shape": [n, spec.layers, 2, spec.hidden], "dtype": "float32",
                       "layout": "[member, layer, (c, h), hidden]",
                       "initial": "zeros at every episode start"} if lstm else None),
            "cell": ("flax OptimizedLSTMCell: gates i, f, g, o; c' = f c + i g; "
                     "h' = o tanh(c')" if lstm else "ReLU MLP"),
            "trained_control_hz": trained_hz}


def _file_section(name: str, data: bytes) -> dict:
    return {"file": name, "sha256": sha256_bytes(data)}


def contract_doc(spec: PolicySpec, tensors: dict, runtime: Contract, world_cfg: World,
                 weights: bytes, golden: bytes, golden_steps: int, seed: int, source: str,
                 members: list, onnx_section: dict | None = None) -> dict:
    """contract.json of an export (module docstring); weights/golden: the files' bytes;
    onnx_section: policy.onnx's (onnx_section()), None when the export has no graph."""
    n = int(tensors["net/params/head/bias"].shape[0])
    return {
        "format": EXPORT_FORMAT, "version": EXPORT_VERSION,
        "robot": _robot_section(world_cfg.robot),
        "runtime": contract_to_dict(runtime),
        "observation": _observation_section(spec, runtime),
        "action": {"names": list(JOINT_NAMES), "units": list(JOINT_UNITS),
                   "meaning": "absolute joint position targets, before the runner's safety filter"},
        "goal": _goal_section(world_cfg.table),
        "policy": _policy_section(spec, n, world_cfg.control_hz),
        "normalization": {"per_member": {k: tensors[f"norm/{k}"].tolist() for k in NORM_FIELDS},
                          "rule": "x = (obs - obs_mean) / obs_std; action = y * act_std + act_mean"},
        "weights": {**_file_section(WEIGHTS_FILE, weights), "bytes": len(weights),
                    "dtype": "float32", "member_axis": 0,
                    "tensors": {k: list(v.shape) for k, v in sorted(tensors.items())}},
        "golden": {**_file_section(GOLDEN_FILE, golden), "steps": int(golden_steps),
                   "tolerance": GOLDEN_TOL, "seed": int(seed)},
        "onnx": onnx_section,
        "source": {"checkpoint": str(source), "members": members,
                   "exported_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")},
        "world": to_dict(world_cfg),
        # The timing the policy was trained under and its ranges, hashed (deploy/timing_check.py):
        # the station's default, and what a station's timing is checked against.
        "timing": timing_record(world_cfg.timing),
    }


def onnx_graph(spec: PolicySpec, tensors: dict, golden: dict, want: bool | None) -> tuple:
    """(policy.onnx bytes, its contract section) or (None, None): want=None builds the graph
    when the `onnx` package is installed, True requires it (ExportError naming the install
    command if absent), False skips it. The graph is run on the golden frames (onnxruntime, or
    onnx's reference evaluator without it) and refused if it differs from the JAX actions."""
    if want is False:
        return None, None
    try:
        data = model_bytes(spec, tensors, doc=f"{EXPORT_FORMAT} v{EXPORT_VERSION}: one {spec.kind} step")
    except MissingExtra as e:
        if want is None:
            return None, None
        raise ExportError(str(e)) from None
    n = int(tensors["net/params/head/bias"].shape[0])
    try:
        ort = import_onnxruntime()
        evaluator, checked = session(data), f"onnxruntime {ort.__version__}"
    except MissingExtra:
        evaluator, checked = reference_session(data), "onnx.reference (onnxruntime not installed)"
    policy = OnnxPolicy(spec, n, data, evaluator=evaluator)
    err = self_test(policy, golden, what="ONNX graph")
    return data, onnx_section(spec, n, data, err, checked)


def onnx_section(spec: PolicySpec, n: int, data: bytes, err: float, checked: str) -> dict:
    """The contract's `onnx` section: the file, its opset, inputs and outputs with shapes."""
    state = [n, spec.layers, 2, spec.hidden]
    shapes = {"frame": [spec.obs_size], "frames": [spec.frame_stack, spec.obs_size],
              "state": state, "state_out": state, "action": [ACTION_SIZE],
              "member_actions": [n, ACTION_SIZE]}
    return {**_file_section(ONNX_FILE, data), "bytes": len(data), "opset": OPSET,
            "ir_version": IR_VERSION, "dtype": "float32",
            "inputs": {k: shapes[k] for k in INPUTS[spec.kind]},
            "outputs": {k: shapes[k] for k in OUTPUTS[spec.kind]},
            "state_layout": "[member, layer, (c, h), hidden], zeros at every episode start" if spec.kind == "lstm" else None,
            "computes": "normalization, network, denormalization and the mean over members: "
                        "`action` equals the numpy policy's action",
            "golden_error": err, "checked_with": checked}


def write_manifest(out_dir: str, written: dict) -> None:
    """manifest.json: format, format_version and SHA-256 + size of every file (name -> bytes)."""
    doc = {"format": EXPORT_FORMAT, "format_version": EXPORT_VERSION,
           "files": {name: {"sha256": sha256_bytes(data), "bytes": len(data)}
                     for name, data in sorted(written.items())}}
    files.write_json(os.path.join(out_dir, MANIFEST_FILE), doc, indent=1)


def export(params, pcfg, world_cfg: World, out_dir: str, member: int | None = None,
           ensemble: bool = False, source: str = "", control_hz: float | None = None,
           golden_steps: int = GOLDEN_STEPS, seed: int = 0, onnx: bool | None = None) -> str:
    """Write an export of `params` (models.PolicyParams, one member or an ensemble with a leading
    [N] axis) into out_dir (created; an existing export there is an error). Returns out_dir.

    control_hz: the robot's control rate (default: world_cfg.control_hz, the rate the policy was
    trained at; the runner steps the policy at this rate). source: the checkpoint path.
    onnx: write policy.onnx: None when the `onnx` package is installed, True always (an error
    without it), False never.
    """
    _refuse_existing(out_dir)
    spec, tensors, members = export_tensors(params, pcfg, member, ensemble)
    runtime = runtime_contract(world_cfg, pcfg, control_hz)
    golden = golden_set(pcfg, tensors, runtime, world_cfg.table, golden_steps, seed)
    graph, graph_section = onnx_graph(spec, tensors, golden, onnx)
    # Every file is written into a hidden staging directory that becomes out_dir only when the
    # export is complete (files.staged_dir): a full disk or a kill leaves no half export under
    # out_dir, so the same command runs again.
    with files.staged_dir(out_dir, last=(MANIFEST_FILE,)) as stage:
        meta = {"format": EXPORT_FORMAT, "kind": spec.kind}
        written = {WEIGHTS_FILE: _save_tensors(os.path.join(stage, WEIGHTS_FILE), tensors, meta),
                   GOLDEN_FILE: _save_tensors(os.path.join(stage, GOLDEN_FILE), golden, meta)}
        if graph is not None:
            files.write_bytes(os.path.join(stage, ONNX_FILE), graph)
            written[ONNX_FILE] = graph
        doc = contract_doc(spec, tensors, runtime, world_cfg, written[WEIGHTS_FILE], written[GOLDEN_FILE],
                           golden_steps, seed, source, members, graph_section)
        written[CONTRACT_FILE] = (json.dumps(files.json_safe(doc), indent=1, allow_nan=False) + "\n").encode()
        files.write_bytes(os.path.join(stage, CONTRACT_FILE), written[CONTRACT_FILE])
        # Last: the manifest's presence marks a complete export (a loader refuses a directory
        # without it).
        write_manifest(stage, written)
    return out_dir


def export_checkpoint(path: str, out_dir: str, step: int | None = None, member: int | None = None,
                      ensemble: bool = False, control_hz: float | None = None,
                      onnx: bool | None = None) -> str:
    """Export the acting (moving-average) policy of a training checkpoint; returns out_dir.

    path: a run directory or its checkpoints/ directory; step: default the newest intact one.
    The checkpoint is opened by training.checkpoint.load_checkpoint, with the PolicyConfig and
    World saved beside it; the contract's source names '<checkpoints dir>@<step>'. member /
    ensemble / control_hz / onnx as in `export`. Raises FileNotFoundError or ValueError (the loader's,
    naming the file and the reason) or ExportError."""
    from training.checkpoint import load_checkpoint
    _refuse_existing(out_dir)
    loaded = load_checkpoint(path, step)
    return export(loaded.params, loaded.cfg.policy, loaded.cfg.world, out_dir, member=member,
                  ensemble=ensemble, source=f"{os.path.abspath(loaded.directory)}@{loaded.step}",
                  control_hz=control_hz, onnx=onnx)


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
        raise ExportError(f"{directory}: invalid runtime contract: {e}") from e


def _policy_of(doc: dict, runtime: Contract, directory: str) -> tuple[PolicySpec, int]:
    """(spec, members) of the contract's policy section, checked against the runtime."""
    pol = doc["policy"]
    try:
        spec = PolicySpec(pol["kind"], pol["hidden"], pol["layers"], pol["obs_size"],
                          pol["frame_stack"]).check()
        members = int(pol["members"])
    except (KeyError, TypeError, ValueError) as e:
        raise ExportError(f"{directory}: invalid policy section ({e})") from e
    if spec.obs_size != runtime.obs_size:
        raise ExportError(f"the policy reads {spec.obs_size} values per frame, the robot gives "
                          f"{runtime.obs_size}")
    if spec.kind == "framestack" and spec.frame_stack != runtime.frame_stack:
        raise ExportError(f"the frame-stack policy needs {spec.frame_stack} frames, the runtime "
                          f"contract stacks {runtime.frame_stack}")
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
