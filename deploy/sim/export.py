"""Export a trained policy for the robot: the writer of the format that deploy/robot/exported.py
describes and reads. `export_checkpoint(path, out_dir)` exports a training checkpoint (opened by
training.checkpoint.load_checkpoint: the configuration saved with it, never guessed);
`export(params, pcfg, world, out_dir)` exports parameters in hand. Both compute the golden
actions with models.make_policy (JAX), and the export is staged and renamed when whole."""
from __future__ import annotations

import datetime
import json
import math
import os

import numpy as np

from deploy.robot.contract import OBS_SIZES, ROBOT_MODEL_ID, Contract, contract_to_dict
from deploy.robot.exported import (
    CONTRACT_FILE,
    ENSEMBLE_RULE,
    EXPORT_FORMAT,
    EXPORT_VERSION,
    GOLDEN_FILE,
    GOLDEN_STEPS,
    GOLDEN_TOL,
    JOINT_UNITS,
    MANIFEST_FILE,
    ONNX_FILE,
    REQUIRED_FILES,
    WEIGHTS_FILE,
    ExportError,
    _unflatten,
    frame_layout,
    self_test,
    sha256_bytes,
)
from deploy.robot.numpy_policy import ACTION_SIZE, NORM_FIELDS, PolicySpec, check_tensors
from deploy.robot.onnx_policy import (
    INPUTS,
    IR_VERSION,
    OPSET,
    OUTPUTS,
    MissingExtra,
    OnnxPolicy,
    import_onnxruntime,
    model_bytes,
    reference_session,
    session,
)
from deploy.robot.timing_check import timing_record
from ttmjx.world import files, observation
from ttmjx.world.config import JOINT_NAMES, Robot, Table, World, opponent_half, to_dict


def _save_tensors(path: str, tensors: dict, metadata: dict) -> bytes:
    """Write a .safetensors file atomically; returns its bytes (for the hash)."""
    from safetensors.numpy import save
    data = save({k: np.ascontiguousarray(v) for k, v in tensors.items()}, metadata=metadata)
    files.write_bytes(path, data)
    return data


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
    mixture = pcfg.head == "mixture"
    return PolicySpec(pcfg.kind, int(pcfg.hidden), int(pcfg.layers), int(pcfg.obs_size),
                      int(pcfg.frame_stack), pcfg.head, int(pcfg.components) if mixture else 1)


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
            "head": spec.head, "components": spec.components,
            "head_rule": ("y is the action" if spec.head == "mean" else
                          "y = [logits K | means K x 8 | log stds K x 8]; the action is the means "
                          "of the component with the largest logit"),
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
    if spec.head != "mean":
        if want:
            raise ExportError(f"policy.onnx is built for the mean head only; this policy's head is "
                              f"{spec.head!r} (export with --onnx auto or off; the numpy engine plays it)")
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

