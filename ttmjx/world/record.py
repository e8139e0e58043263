"""The trajectory record: the one data format of the project.

Demonstrations, practice rollouts and robot logs are all `Trajectories`. On disk a record is
an uncompressed .npz of plain numeric arrays (no object arrays, loaded with
allow_pickle=False) plus a `meta.json` beside it; see docs/DATA.md.
"""
from __future__ import annotations

import json
import os
from typing import NamedTuple

import numpy as np

from ttmjx.world import files

SCHEMA_VERSION = 1

# Column layout of one observation frame (13 values; 16 with ball velocity).
OBS_JOINTS = slice(0, 8)
OBS_BALL = slice(8, 11)


class Trajectories(NamedTuple):
    """B throws of T control steps. Every field is an array (numpy or jax)."""
    obs: "np.ndarray"            # [B, T, 13] joints (8), ball position (3), goal (2)
    ball_vel: "np.ndarray"       # [B, T, 3] ball velocity (for the 16-value observation)
    actions: "np.ndarray"        # [B, T, 8] joint targets sent (after clipping)
    valid: "np.ndarray"          # [B, T] bool, steps before the episode ended
    goal: "np.ndarray"           # [B, 2] commanded goal (x, y)
    hit: "np.ndarray"            # [B] bool, the paddle touched the ball
    hit_step: "np.ndarray"       # [B] int32, control step of first paddle contact, -1 if none
    landing: "np.ndarray"        # [B, 2] first table contact after the hit, or where a hit ball
                                 #        fell through table height; NaN if not hit
    on_opponent: "np.ndarray"    # [B] bool, landed on the opponent's half
    bounce_own: "np.ndarray"     # [B] bool, bounced on the robot's half before the hit
    net: "np.ndarray"            # [B] bool, touched the net
    launch_pos: "np.ndarray"     # [B, 3]
    launch_vel: "np.ndarray"     # [B, 3]
    launch_spin: "np.ndarray"    # [B, 3]
    aim: "np.ndarray"            # [B, 2] where the thrower aimed the first bounce

    @property
    def size(self) -> int:
        return int(self.obs.shape[0])


class TrueTrack(NamedTuple):
    """The simulation's truth beside a record of B throws of T control steps (S physics steps
    each), where `obs` holds what the policy SAW: under a timing model (every preset but `tiny`)
    the tracker's delayed, extrapolated ball and the delayed joint feedback, not the state.
    Carried by evaluation and recording paths only (Backend.rollout(truth=True)), never by the
    practice rollout. Table frame, m; steps after the episode ended (`valid` False) are not
    meaningful."""
    ball: "np.ndarray"           # [B, T, 3] the ball's centre at the start of each control step
    joints: "np.ndarray"         # [B, T, 8] the joint positions at the start of each control step
    ball_physics: "np.ndarray"   # [B, T * S + 1, 3] the ball's centre at the start and after each
                                 #   physics step: ball_physics[:, t * S] == ball[:, t]


FIELD_DTYPES = {
    "obs": np.float32, "ball_vel": np.float32, "actions": np.float32, "valid": np.bool_,
    "goal": np.float32, "hit": np.bool_, "hit_step": np.int32, "landing": np.float32,
    "on_opponent": np.bool_, "bounce_own": np.bool_, "net": np.bool_,
    "launch_pos": np.float32, "launch_vel": np.float32, "launch_spin": np.float32,
    "aim": np.float32,
}
# Trailing shape per field after the batch (and time) axes; None = the episode length T.
FIELD_SHAPES = {
    "obs": (None, 13), "ball_vel": (None, 3), "actions": (None, 8), "valid": (None,),
    "goal": (2,), "hit": (), "hit_step": (), "landing": (2,), "on_opponent": (),
    "bounce_own": (), "net": (), "launch_pos": (3,), "launch_vel": (3,), "launch_spin": (3,),
    "aim": (2,),
}


class RecordError(ValueError):
    """A trajectory file that is missing, truncated, of another schema or malformed."""


def to_numpy(traj: Trajectories) -> Trajectories:
    return Trajectories(*(np.asarray(x).astype(FIELD_DTYPES[f]) for f, x in zip(Trajectories._fields, traj)))


def validate(traj: Trajectories, where: str = "trajectories") -> None:
    """Raise RecordError naming the field if any array has the wrong shape or dtype kind."""
    b = np.shape(traj.obs)[0] if np.ndim(traj.obs) == 3 else None
    t = np.shape(traj.obs)[1] if np.ndim(traj.obs) == 3 else None
    if b is None:
        raise RecordError(f"{where}: obs must be [B, T, 13], got shape {np.shape(traj.obs)}")
    for f in Trajectories._fields:
        x = getattr(traj, f)
        want = (b,) + tuple(t if s is None else s for s in FIELD_SHAPES[f])
        if tuple(np.shape(x)) != want:
            raise RecordError(f"{where}: field {f!r} has shape {tuple(np.shape(x))}, expected {want}")
    check_finite(traj, where)


def check_finite(traj: Trajectories, where: str = "trajectories") -> None:
    """Raise RecordError naming the field and the first episode and step if an observation,
    ball velocity or action of a valid step, or a goal, is NaN or infinite (training on it
    would turn the weights into NaN)."""
    valid = np.asarray(traj.valid, bool)
    for f in ("obs", "ball_vel", "actions"):
        bad = valid & ~np.all(np.isfinite(np.asarray(getattr(traj, f), np.float64)), axis=-1)
        if bad.any():
            b, t = np.argwhere(bad)[0]
            raise RecordError(f"{where}: field {f!r} is not finite at episode {b}, step {t}")
    bad = ~np.all(np.isfinite(np.asarray(traj.goal, np.float64)), axis=-1)
    if bad.any():
        raise RecordError(f"{where}: field 'goal' is not finite at episode {int(np.argwhere(bad)[0][0])}")


def concat(parts: list[Trajectories]) -> Trajectories:
    """Concatenate records along B (they must share T)."""
    return Trajectories(*(np.concatenate([getattr(p, f) for p in parts]) for f in Trajectories._fields))


def save(directory: str, traj: Trajectories, meta: dict, name: str = "trajectories",
         extra: dict | None = None) -> str:
    """Write `name`.npz and `name`.meta.json into `directory`; refuses to overwrite, and writes
    nothing for a record that does not validate. extra: more plain numeric arrays with a leading
    [B] axis stored in the same .npz under their own names (the truth of `ttmjx demos`:
    `true_ball_pos`, `true_joints`); `load` reads only the record, `extra_arrays` the rest."""
    path = os.path.join(directory, f"{name}.npz")
    meta_path = os.path.join(directory, f"{name}.meta.json")
    if os.path.exists(path) or os.path.exists(meta_path):
        raise FileExistsError(f"{path} already exists; refusing to overwrite a dataset "
                              f"(choose a new --out or delete it first)")
    traj = to_numpy(traj)
    validate(traj, path)
    extra = {k: np.asarray(v) for k, v in (extra or {}).items()}
    for k, v in extra.items():
        if k in Trajectories._fields or v.dtype.kind not in "biuf" or v.shape[:1] != (traj.size,):
            raise RecordError(f"{path}: extra array {k!r} ({v.dtype}, shape {v.shape}) must be a plain numeric "
                              f"array of {traj.size} rows whose name is not a record field")
    os.makedirs(directory, exist_ok=True)
    tmp = path + ".tmp.npz"
    np.savez(tmp, **traj._asdict(), **extra)
    os.replace(tmp, path)  # atomic: a crash never leaves a half-written dataset under the name
    files.write_json(meta_path, {"schema_version": SCHEMA_VERSION, "n": traj.size,
                                 "horizon": int(traj.obs.shape[1]), **meta})
    return path


def extra_arrays(directory: str, name: str = "trajectories") -> dict:
    """The arrays a dataset holds beside the record (`save`'s extra), by name; RecordError names
    the file if it is unreadable."""
    path, _ = dataset_files(directory, name)
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files if k not in Trajectories._fields}
    except Exception as e:  # zipfile.BadZipFile, EOFError, ValueError on truncation
        raise RecordError(f"{path}: truncated or corrupt ({type(e).__name__}: {e})") from e


def dataset_files(directory: str, name: str = "trajectories") -> tuple[str, str]:
    """(npz path, metadata path) of a dataset; RecordError if either is missing."""
    path = os.path.join(directory, f"{name}.npz")
    meta_path = os.path.join(directory, f"{name}.meta.json")
    if not os.path.isdir(directory):
        kind = "is not a directory" if os.path.exists(directory) else "does not exist"
        raise RecordError(f"dataset directory {directory!r} {kind}")
    for p in (path, meta_path):
        if not os.path.exists(p):
            raise RecordError(f"{p}: missing (not a ttmjx dataset directory?)")
    return path, meta_path


def load(directory: str, name: str = "trajectories") -> tuple[Trajectories, dict]:
    """Load a record written by `save` without pickle; RecordError names the file and problem."""
    path, meta_path = dataset_files(directory, name)
    try:
        with open(meta_path) as f:
            meta = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise RecordError(f"{meta_path}: unreadable metadata ({e})") from e
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise RecordError(f"{meta_path}: schema_version {meta.get('schema_version')!r}, "
                          f"this ttmjx reads version {SCHEMA_VERSION}")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [f for f in Trajectories._fields if f not in z.files]
            if missing:
                raise RecordError(f"{path}: missing arrays {missing}")
            traj = Trajectories(*(z[f] for f in Trajectories._fields))
    except RecordError:
        raise
    except Exception as e:  # zipfile.BadZipFile, EOFError, ValueError on truncation
        raise RecordError(f"{path}: truncated or corrupt ({type(e).__name__}: {e})") from e
    validate(traj, path)
    if traj.size != meta.get("n"):
        raise RecordError(f"{path}: holds {traj.size} trajectories but {meta_path} says n={meta.get('n')}")
    return traj, meta
