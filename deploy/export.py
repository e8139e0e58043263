"""Export a trained policy for the robot, and load it back (numpy only) with every check.

An export is a directory of three files, nothing pickled:

  weights.safetensors  float32 tensors named by their flattened parameter paths, each with a
                       leading member axis [N, ...] (N = 1 for one member):
                       `net/params/lstm0/hf/kernel`, ..., `net/params/head/bias`,
                       `norm/obs_mean`, `norm/obs_std`, `norm/act_mean`, `norm/act_std`
  golden.safetensors   a short random-but-valid observation sequence (`frames` [L, 13],
                       `stacks` [L, k, 13]) and the JAX policy's actions on it from a zero
                       state (`member_actions` [N, L, 8], `actions` [L, 8] = their mean)
  contract.json        what the runner, the robot and the policy must agree on: format and
                       version; the robot model id and joint order, units, ranges and speed
                       limits; the control rate and frame stack (`runtime`, a deploy.Contract);
                       the observation layout and order; the goal frame and units; the policy
                       type, sizes, recurrent state shape and ensemble rule; the normalization;
                       the source checkpoint; the SHA-256 of both .safetensors files and the
                       shape of every tensor; the World config the policy was trained in.

`export(...)` writes them (JAX: it computes the golden actions with models.make_policy).
`load_export(dir)` (numpy only: this module imports JAX lazily, inside export functions)
refuses a tampered or mismatched export with an ExportError naming the problem: a hash that
does not match, tensors of the wrong names/shapes/dtypes, a contract for another robot (model
id, joint names, limits wider than the robot's), or a golden self-test whose numpy actions
differ from the stored JAX actions by more than 1e-5.

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

from deploy.contract import (ROBOT_MODEL_ID, Contract, contract_from_dict, contract_to_dict)
from deploy.numpy_policy import ACTION_SIZE, ExportedPolicy, PolicySpec, check_tensors
from ttmjx.world.config import JOINT_NAMES, Table, World, opponent_half, to_dict

EXPORT_FORMAT = "ttmjx-policy-export"
EXPORT_VERSION = 1
WEIGHTS_FILE = "weights.safetensors"
GOLDEN_FILE = "golden.safetensors"
CONTRACT_FILE = "contract.json"
GOLDEN_TOL = 1e-5          # max |numpy - JAX| over the golden actions (fixed here, not read)
GOLDEN_STEPS = 16
ENSEMBLE_RULE = ("mean of the members' actions (absolute joint targets, after each member's own "
                 "denormalization); each member keeps its own recurrent state")
JOINT_UNITS = ("m", "m", "rad", "rad", "rad", "rad", "rad", "rad")
FRAME_LAYOUT = [(n, u) for n, u in zip(JOINT_NAMES, JOINT_UNITS)] + [
    ("ball_x", "m"), ("ball_y", "m"), ("ball_z", "m"), ("goal_x", "m"), ("goal_y", "m")]


class ExportError(ValueError):
    """An export that cannot be written, or one that must not be run (the message says why)."""


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------
def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _save_tensors(path: str, tensors: dict, metadata: dict) -> bytes:
    """Write a .safetensors file; returns its bytes (for the hash)."""
    from safetensors.numpy import save
    data = save({k: np.ascontiguousarray(v) for k, v in tensors.items()}, metadata=metadata)
    with open(path, "wb") as f:
        f.write(data)
    return data


def _read_tensors(directory: str, name: str, sha256: str) -> dict:
    """Read a .safetensors file once, check its SHA-256, then parse those same bytes."""
    from safetensors.numpy import load
    path = os.path.join(directory, name)
    if not os.path.isfile(path):
        raise ExportError(f"{path}: missing (an incomplete export?)")
    with open(path, "rb") as f:
        data = f.read()
    got = sha256_bytes(data)
    if got != sha256:
        raise ExportError(f"{path}: SHA-256 {got} does not match the contract's {sha256}: the file "
                          f"was modified or belongs to another export; refusing to load it")
    try:
        return dict(load(data))
    except Exception as e:  # noqa: BLE001 - the library raises its own error types
        raise ExportError(f"{path}: not a readable safetensors file ({e})") from e


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


def select_members(tensors: dict, is_ensemble: bool, member: int | None, ensemble: bool) -> tuple[dict, list]:
    """The tensors to export (leading [N] axis) and which members of the source they are."""
    if not is_ensemble:
        if member not in (None, 0):
            raise ExportError(f"member={member}: the params hold one member (no ensemble axis)")
        return {k: v[None] for k, v in tensors.items()}, [0]
    n = int(tensors["net/params/head/bias"].shape[0])
    if ensemble and member is not None:
        raise ExportError("pass either ensemble=True (--ensemble: all members, actions averaged) "
                          "or member=i (--member i), not both")
    if ensemble:
        return tensors, list(range(n))
    if member is None:
        if n == 1:
            member = 0
        else:
            raise ExportError(f"the params hold an ensemble of {n} members: pass ensemble=True "
                              f"(--ensemble: all members, actions averaged) or member=i "
                              f"(--member i, 0 <= i < {n})")
    if not 0 <= member < n:
        raise ExportError(f"member={member} is out of range for an ensemble of {n} members")
    return {k: v[member:member + 1] for k, v in tensors.items()}, [int(member)]


# --------------------------------------------------------------------------------------------
# Golden observations
# --------------------------------------------------------------------------------------------
def golden_frames(contract: Contract, table: Table, steps: int = GOLDEN_STEPS, seed: int = 0) -> np.ndarray:
    """[steps, 13] float32 frames a robot could see at the contract's rate: joints wandering
    from home within their ranges and speed limits, an incoming ball (gravity, table bounce),
    a goal on the opponent's half."""
    rng = np.random.default_rng(seed)
    dt = contract.dt
    lo, hi = np.asarray(contract.lower), np.asarray(contract.upper)
    step = np.asarray(contract.max_speed) * contract.speed_margin * dt
    q = np.asarray(contract.home, np.float64).copy()
    pos = np.array([1.75, rng.uniform(-0.4, 0.4), rng.uniform(0.9, 1.0)])
    vel = np.array([rng.uniform(-7.5, -6.0), rng.uniform(-0.8, 0.8), rng.uniform(0.0, 1.5)])
    (gx0, gx1), (gy0, gy1) = opponent_half(table)
    goal = np.array([rng.uniform(gx0, gx1), rng.uniform(gy0, gy1)])
    frames = []
    for _ in range(steps):
        frames.append(np.concatenate([q, pos, goal]))
        q = np.clip(q + rng.uniform(-0.5, 0.5, 8) * step, lo, hi)
        for _ in range(10):                           # the ball, in 10 sub-steps per tick
            vel[2] -= 9.81 * dt / 10
            pos = pos + vel * dt / 10
            if pos[2] < table.top_z + 0.02 and abs(pos[0]) < table.half_length and vel[2] < 0:
                vel[2] = -0.9 * vel[2]
            pos[2] = max(pos[2], 0.02)
    return np.asarray(frames, np.float32)


def stack_frames(frames: np.ndarray, k: int) -> np.ndarray:
    """[L, O] -> [L, k, O]: the runner's FrameStack (oldest first, first frame repeated)."""
    t = frames.shape[0]
    idx = np.clip(np.arange(t)[:, None] - (k - 1) + np.arange(k)[None, :], 0, t - 1)
    return frames[idx]


def _jax_member_actions(pcfg, tensors: dict, frames: np.ndarray, stacks: np.ndarray) -> np.ndarray:
    """[N, L, 8]: models.make_policy(pcfg) from a zero state, each member, in JAX."""
    import jax
    import jax.numpy as jnp

    from models.normalizer import Normalizer
    from models.policy import PolicyParams, make_policy

    def unflatten(prefix):
        tree = {}
        for name, v in tensors.items():
            if not name.startswith(prefix + "/"):
                continue
            node, parts = tree, name[len(prefix) + 1:].split("/")
            for p in parts[:-1]:
                node = node.setdefault(p, {})
            node[parts[-1]] = jnp.asarray(v)
        return tree

    norm = unflatten("norm")
    params = PolicyParams(unflatten("net"), Normalizer(**{k: norm[k] for k in Normalizer._fields}))
    policy = make_policy(pcfg)

    class Obs:   # what make_policy reads (env.Obs fields); the key is unused
        def __init__(self, frame, frames):
            self.frame, self.frames, self.ball_vel = frame, frames, jnp.zeros(3, jnp.float32)

    def one(p):
        def body(carry, xs):
            return policy.apply(p, carry, Obs(*xs), None)
        return jax.lax.scan(body, policy.init(p, None), (jnp.asarray(frames), jnp.asarray(stacks)))[1]

    return np.asarray(jax.jit(jax.vmap(one))(params), np.float32)


# --------------------------------------------------------------------------------------------
# Export
# --------------------------------------------------------------------------------------------
def _spec(pcfg) -> PolicySpec:
    return PolicySpec(pcfg.kind, int(pcfg.hidden), int(pcfg.layers), int(pcfg.obs_size),
                      int(pcfg.frame_stack))


def export(params, pcfg, world_cfg: World, out_dir: str, member: int | None = None,
           ensemble: bool = False, source: str = "", control_hz: float | None = None,
           golden_steps: int = GOLDEN_STEPS, seed: int = 0) -> str:
    """Write an export of `params` (models.PolicyParams, one member or an ensemble with a leading
    [N] axis) into out_dir (created; an existing export there is an error). Returns out_dir.

    control_hz: the robot's control rate (default: world_cfg.control_hz, the rate the policy was
    trained at; the runner steps the policy at this rate). source: the checkpoint path.
    """
    if pcfg.obs_size != 13:
        raise ExportError(f"PolicyConfig.obs_size={pcfg.obs_size}: the robot observes 13 values per "
                          f"frame (no ball velocity); only 13-value policies can be exported")
    for name in (CONTRACT_FILE, WEIGHTS_FILE, GOLDEN_FILE):
        if os.path.exists(os.path.join(out_dir, name)):
            raise FileExistsError(f"{os.path.join(out_dir, name)} already exists; refusing to "
                                  f"overwrite an export (choose a new --out or delete it first)")
    tensors, is_ens = policy_tensors(params)
    tensors, members = select_members(tensors, is_ens, member, ensemble)
    spec = _spec(pcfg)
    try:
        n = check_tensors(spec, tensors)
    except ValueError as e:
        raise ExportError(f"params do not match the PolicyConfig: {e}") from e

    hz = float(world_cfg.control_hz if control_hz is None else control_hz)
    if not (math.isfinite(hz) and hz > 0):
        raise ExportError(f"control_hz={control_hz}, expected > 0")
    r = world_cfg.robot
    k = pcfg.frame_stack if pcfg.kind == "framestack" else world_cfg.frame_stack
    runtime = Contract(control_hz=hz, frame_stack=int(k), episode_s=world_cfg.episode_s,
                       lower=tuple(r.lower), upper=tuple(r.upper), max_speed=tuple(r.max_speed),
                       speed_margin=r.speed_margin, home=tuple(r.home))

    frames = golden_frames(runtime, world_cfg.table, golden_steps, seed)
    stacks = stack_frames(frames, runtime.frame_stack)
    member_actions = _jax_member_actions(pcfg, tensors, frames, stacks)
    golden = {"frames": frames, "stacks": stacks, "member_actions": member_actions,
              "actions": member_actions.mean(axis=0).astype(np.float32)}

    os.makedirs(out_dir, exist_ok=True)
    meta = {"format": EXPORT_FORMAT, "kind": spec.kind}
    w_bytes = _save_tensors(os.path.join(out_dir, WEIGHTS_FILE), tensors, meta)
    g_bytes = _save_tensors(os.path.join(out_dir, GOLDEN_FILE), golden, meta)
    norm = {k2: tensors[f"norm/{k2}"].tolist() for k2 in ("obs_mean", "obs_std", "act_mean", "act_std")}
    (gx, gy) = opponent_half(world_cfg.table).tolist()
    doc = {
        "format": EXPORT_FORMAT,
        "version": EXPORT_VERSION,
        "robot": {"model_id": ROBOT_MODEL_ID, "joint_names": list(JOINT_NAMES),
                  "joint_units": list(JOINT_UNITS), "lower": list(r.lower), "upper": list(r.upper),
                  "max_speed": list(r.max_speed), "max_speed_units": "m/s (gantry), rad/s (arm)",
                  "speed_margin": r.speed_margin, "home": list(r.home)},
        "runtime": contract_to_dict(runtime),
        "observation": {
            "frame_size": 13, "frame": [n_ for n_, _ in FRAME_LAYOUT],
            "units": [u for _, u in FRAME_LAYOUT],
            "ball_velocity": False,
            "frame_stack": runtime.frame_stack, "stack_order": "oldest first",
            "stack_padding": "the episode's first frame repeated",
            "timing": "joints and ball interpolated to each control deadline t0 + n / control_hz",
            "policy_input": ("the current frame (lstm)" if spec.kind == "lstm"
                             else f"the last {pcfg.frame_stack} frames flattened (framestack)"),
        },
        "action": {"names": list(JOINT_NAMES), "units": list(JOINT_UNITS),
                   "meaning": "absolute joint position targets, before the runner's safety filter"},
        "goal": {"frame": "world: x along the table toward the opponent, y across, z up; table "
                          "centre at the origin, robot at negative x (docs/DESIGN.md)",
                 "units": "m", "region": {"x": gx, "y": gy}},
        "policy": {"kind": spec.kind, "hidden": spec.hidden, "layers": spec.layers,
                   "obs_size": spec.obs_size, "frame_stack": spec.frame_stack,
                   "input_frames": spec.input_frames, "members": n,
                   "ensemble_rule": ENSEMBLE_RULE if n > 1 else "single member",
                   "state": ({"shape": [n, spec.layers, 2, spec.hidden], "dtype": "float32",
                              "layout": "[member, layer, (c, h), hidden]",
                              "initial": "zeros at every episode start"}
                             if spec.kind == "lstm" else None),
                   "cell": ("flax OptimizedLSTMCell: gates i, f, g, o; c' = f c + i g; "
                            "h' = o tanh(c')" if spec.kind == "lstm" else "ReLU MLP"),
                   "trained_control_hz": world_cfg.control_hz},
        "normalization": {"per_member": norm,
                          "rule": "x = (obs - obs_mean) / obs_std; action = y * act_std + act_mean"},
        "weights": {"file": WEIGHTS_FILE, "sha256": sha256_bytes(w_bytes), "bytes": len(w_bytes),
                    "dtype": "float32", "member_axis": 0,
                    "tensors": {k2: list(v.shape) for k2, v in sorted(tensors.items())}},
        "golden": {"file": GOLDEN_FILE, "sha256": sha256_bytes(g_bytes), "steps": int(golden_steps),
                   "tolerance": GOLDEN_TOL, "seed": int(seed)},
        "source": {"checkpoint": str(source), "members": members,
                   "exported_at": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")},
        "world": to_dict(world_cfg),
    }
    tmp = os.path.join(out_dir, CONTRACT_FILE + ".tmp")
    with open(tmp, "w") as f:
        json.dump(doc, f, indent=1)
    os.replace(tmp, os.path.join(out_dir, CONTRACT_FILE))   # last: its presence marks a complete export
    return out_dir


# --------------------------------------------------------------------------------------------
# Load
# --------------------------------------------------------------------------------------------
def read_contract(directory: str) -> dict:
    """The parsed contract.json of an export (format and version checked)."""
    path = os.path.join(directory, CONTRACT_FILE)
    if not os.path.isfile(path):
        raise ExportError(f"{path}: missing (not a policy export directory?)")
    try:
        with open(path) as f:
            doc = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise ExportError(f"{path}: unreadable contract ({e})") from e
    if not isinstance(doc, dict) or doc.get("format") != EXPORT_FORMAT:
        raise ExportError(f"{path}: not a {EXPORT_FORMAT} contract")
    if doc.get("version") != EXPORT_VERSION:
        raise ExportError(f"{path}: export version {doc.get('version')!r}, this runner reads "
                          f"version {EXPORT_VERSION}")
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


def self_test(policy: ExportedPolicy, golden: dict, tol: float = GOLDEN_TOL) -> float:
    """Run the numpy policy on the golden frames; max |numpy - JAX| (raises ExportError > tol)."""
    frames, stacks = golden.get("frames"), golden.get("stacks")
    member_actions = golden.get("member_actions")
    n, k = policy.members, policy.spec.input_frames
    if frames is None or stacks is None or member_actions is None or frames.ndim != 2:
        raise ExportError("golden file lacks frames [L, 13], stacks [L, k, 13] or member_actions")
    length = frames.shape[0]
    if (frames.shape != (length, policy.spec.obs_size) or stacks.shape[0] != length
            or stacks.shape[2] != policy.spec.obs_size or stacks.shape[1] < k
            or member_actions.shape != (n, length, ACTION_SIZE)):
        raise ExportError(f"golden arrays have shapes frames {frames.shape}, stacks {stacks.shape}, "
                          f"member_actions {member_actions.shape}; expected ({length}, 13), "
                          f"({length}, >={k}, 13), ({n}, {length}, 8)")
    got = policy.run(frames, stacks[:, stacks.shape[1] - k:], members=True)
    err = float(np.max(np.abs(got - member_actions))) if got.size else 0.0
    mean_err = float(np.max(np.abs(got.mean(0) - golden.get("actions", member_actions.mean(0)))))
    err = max(err, mean_err)
    if not err <= tol:
        raise ExportError(f"golden self-test failed: the numpy policy's actions differ from the JAX "
                          f"policy's by up to {err:.3g} (> {tol:g}); refusing to run it")
    return err


def load_export(directory: str, expected_robot: str = ROBOT_MODEL_ID,
                expected_joints=JOINT_NAMES, robot_limits: Contract | None = Contract(),
                run_self_test: bool = True) -> tuple[ExportedPolicy, Contract]:
    """(numpy policy, runtime Contract) of an export, after every check (module docstring).

    robot_limits: this robot's joint ranges and speed limits (default: ttmjx's robot config); an
    export whose contract is wider anywhere is refused (None skips the check). The returned
    policy's `policy_hash` is 'sha256:<weights hash>' and `self_test_error` the golden error.
    """
    doc = read_contract(directory)
    try:
        runtime = contract_from_dict(doc["runtime"])
    except (TypeError, ValueError) as e:
        raise ExportError(f"{directory}: invalid runtime contract: {e}") from e
    _check_robot(doc, runtime, expected_robot, expected_joints, robot_limits)
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

    w = doc["weights"]
    tensors = _read_tensors(directory, w.get("file", WEIGHTS_FILE), str(w.get("sha256")))
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
    for k in ("obs_mean", "obs_std", "act_mean", "act_std"):
        listed_norm = np.asarray(norm.get(k, []), np.float32)
        if listed_norm.shape != tensors[f"norm/{k}"].shape or not np.array_equal(listed_norm, tensors[f"norm/{k}"]):
            raise ExportError(f"the contract's normalization {k} differs from the weights' norm/{k}")

    policy = ExportedPolicy(spec, tensors, policy_hash="sha256:" + w["sha256"])
    if run_self_test:
        g = doc["golden"]
        golden = _read_tensors(directory, g.get("file", GOLDEN_FILE), str(g.get("sha256")))
        policy.self_test_error = self_test(policy, golden)
    policy.contract_doc = doc
    return policy, runtime


def export_world(doc: dict) -> World:
    """The World config an export was trained in (contract 'world'; defaults if absent)."""
    from ttmjx.world.config import from_dict
    return from_dict(World, doc["world"]) if isinstance(doc.get("world"), dict) else World()


# --------------------------------------------------------------------------------------------
# From a checkpoint (JAX, orbax)
# --------------------------------------------------------------------------------------------
def _find_params(tree, path=""):
    """(path, subtree) of every {'net': ..., 'norm': {obs_mean, ...}} inside a restored tree."""
    found = []
    if isinstance(tree, dict):
        norm = tree.get("norm")
        if "net" in tree and isinstance(norm, dict) and "obs_mean" in norm:
            found.append((path, tree))
        for k, v in tree.items():
            found += _find_params(v, f"{path}/{k}")
    elif isinstance(tree, (list, tuple)):
        for i, v in enumerate(tree):
            found += _find_params(v, f"{path}/{i}")
    return found


def infer_policy_config(net: dict, obs_size: int):
    """models.PolicyConfig from the parameter shapes (with or without a leading [N] axis)."""
    from models.config import PolicyConfig
    p = net["params"] if "params" in net else net
    lstm = sorted(k for k in p if k.startswith("lstm"))
    dense = sorted(k for k in p if k.startswith("dense"))
    if lstm:
        hidden = int(np.shape(p["lstm0"]["hf"]["kernel"])[-1])
        return PolicyConfig(kind="lstm", hidden=hidden, layers=len(lstm), obs_size=obs_size)
    if dense:
        fan_in, hidden = np.shape(p["dense0"]["kernel"])[-2:]
        return PolicyConfig(kind="framestack", hidden=int(hidden), layers=len(dense),
                            obs_size=obs_size, frame_stack=int(fan_in) // obs_size)
    raise ExportError(f"cannot tell the policy type from parameters {sorted(p)}")


def checkpoint_dir(path: str) -> str:
    """A checkpoint directory: `path` itself, or `path/checkpoints` (a run directory)."""
    from training import checkpoint
    for cand in (path, os.path.join(path, "checkpoints"), os.path.join(path, "ckpt")):
        if checkpoint.steps(cand):
            return cand
    raise FileNotFoundError(f"no checkpoint in {path!r} (nor in its checkpoints/ subdirectory)")


def params_from_checkpoint(path: str, step: int | None = None):
    """(PolicyParams, PolicyConfig, World, source) from a training checkpoint.

    Reads the saved tree's metadata, finds the one subtree {'net', 'norm'} (models.PolicyParams;
    in a `ttmjx train` checkpoint: state.ema, the acting policy) and restores only that (orbax partial restore
    to numpy: the trajectory cache and optimizer state are not read; no pickle). The
    PolicyConfig is the saved config's 'policy' if there is one (checked against the parameter
    shapes), else read from the shapes; the World is the saved config's 'world' (defaults if
    absent).
    """
    import jax
    import orbax.checkpoint as ocp
    from etils import epath

    from models.config import PolicyConfig
    from models.normalizer import Normalizer
    from models.policy import PolicyParams
    from training import checkpoint
    from ttmjx.world.config import from_dict
    directory = os.path.abspath(checkpoint_dir(path))
    saved = checkpoint.steps(directory)
    step = saved[-1] if step is None else int(step)
    if step not in saved:
        raise FileNotFoundError(f"no checkpoint step {step} in {directory!r}; saved steps: {saved}")
    config = checkpoint.restore_config(directory, step) or {}
    state_dir = epath.Path(directory) / str(step) / "state"
    handler = ocp.PyTreeCheckpointHandler()
    meta = handler.metadata(state_dir)
    found = _find_params(getattr(meta, "tree", meta))
    if not found:
        raise ExportError(f"checkpoint {directory} step {step} holds no policy parameters "
                          f"({{'net', 'norm'}} subtree)")
    # A `ttmjx train` state holds the trained weights (params) and their moving average (ema),
    # which is the policy that acts.
    found.sort(key=lambda x: ({"ema": 0, "params": 1}.get(x[0].split("/")[-1], 2), len(x[0])))
    where, sub_meta = found[0]
    keys = [k for k in where.split("/") if k]
    item = sub_meta
    for k in reversed(keys):
        item = {k: item}
    restore_args = jax.tree.map(lambda m: ocp.RestoreArgs(restore_type=np.ndarray), item)
    tree = handler.restore(state_dir, args=ocp.args.PyTreeRestore(
        item=item, restore_args=restore_args, partial_restore=True))
    for k in keys:
        tree = tree[k]
    norm = Normalizer(**{k: np.asarray(tree["norm"][k]) for k in Normalizer._fields})
    params = PolicyParams(tree["net"], norm)
    inferred = infer_policy_config(tree["net"], int(np.shape(norm.obs_mean)[-1]))
    pcfg = inferred
    if isinstance(config.get("policy"), dict):
        pcfg = PolicyConfig(**config["policy"])
        if pcfg.kind != inferred.kind or any(getattr(pcfg, f) != getattr(inferred, f) for f in
                                             ("hidden", "layers", "obs_size", "input_frames")):
            raise ExportError(f"checkpoint config policy {pcfg} does not match its parameters ({inferred})")
    world = from_dict(World, config["world"]) if isinstance(config.get("world"), dict) else World()
    return params, pcfg, world, f"{directory}@{step}{where}"

