"""The `paper` bootstrap's last policy, as a demonstrator: weights on disk and the policy that
plays them (ttmjx/tools/demos.py, source `paper`).

The paper's procedure ("Building up the initial bootstrap dataset"; built by
training/bootstrap_paper.py) ends with a goal-conditioned policy trained by relabelled imitation
of the narrow ES data and self-practice toward goals shifted up the table, then over the whole
half. Its demonstrations are gathered with goals uniform over the opponent's half and 4 of the 8
joints perturbed (demos.Perturbation). This module holds what that needs below the `models`
layer: the weights file (safetensors, no pickle) and a frame-stack MLP forward that is the
same function as `models.policy.make_policy` for `kind="framestack"`
(tests/test_paper_bootstrap.py compares them), averaged over the ensemble's members as
`ttmjx eval` plays an ensemble.

The goal: the demonstrator draws its own goal per episode (uniform over the half) and writes it
into the frames it feeds its network; the goal columns of the observation it is given are
ignored, so the dataset keeps the zero placeholder goal and the trainer relabels every
demonstration with its landing, as for every other source.
"""
from __future__ import annotations

import functools
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx.world import backends, files, observation
from ttmjx.world.config import World
from ttmjx.world.env import uniform_goals

ASSETS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")
WEIGHTS_NAME = "paper_policy.safetensors"
META_NAME = "paper_policy.json"
FORMAT = "ttmjx-bootstrap-policy"
FORMAT_VERSION = 1
NORM_NAMES = ("norm/obs_mean", "norm/obs_std", "norm/act_mean", "norm/act_std")


def save_weights(directory: str, tensors: dict, meta: dict) -> str:
    """Write `tensors` (name -> float32 array [N, ...], the member axis first: `dense{i}/kernel`,
    `dense{i}/bias`, `head/kernel`, `head/bias` and NORM_NAMES) as DIR/paper_policy.safetensors
    and `meta` (must hold `layers`, `hidden`, `frame_stack`, `obs_size`) as DIR/paper_policy.json,
    each atomically. Returns the weights path."""
    from safetensors.numpy import save
    for k in ("layers", "hidden", "frame_stack", "obs_size"):
        if k not in meta:
            raise ValueError(f"bootstrap weights: meta lacks {k!r}")
    arrays = {k: np.ascontiguousarray(np.asarray(v, np.float32)) for k, v in tensors.items()}
    _check(arrays, meta, "tensors")
    os.makedirs(directory, exist_ok=True)
    path = os.path.join(directory, WEIGHTS_NAME)
    files.write_bytes(path, save(arrays))
    files.write_json(os.path.join(directory, META_NAME), {"format": FORMAT, "format_version": FORMAT_VERSION, **meta})
    return path


def load_weights(directory: str | None = None) -> tuple[dict, dict]:
    """(tensors, meta) of a weights directory (default: the shipped ones in ttmjx/tools/assets);
    ValueError naming the file and the problem when something is off."""
    from safetensors.numpy import load
    directory = directory or ASSETS
    path, meta_path = os.path.join(directory, WEIGHTS_NAME), os.path.join(directory, META_NAME)
    for p in (path, meta_path):
        if not os.path.exists(p):
            raise ValueError(f"{p}: missing (build the bootstrap with `ttmjx demos --source paper --rebuild`)")
    with open(meta_path) as f:
        meta = json.load(f)
    if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{meta_path}: format {meta.get('format')!r} version {meta.get('format_version')!r}, "
                         f"this ttmjx reads {FORMAT!r} version {FORMAT_VERSION}")
    try:
        with open(path, "rb") as f:
            tensors = load(f.read())
    except Exception as e:
        raise ValueError(f"{path}: truncated or corrupt ({type(e).__name__}: {e})") from e
    _check(tensors, meta, path)
    return tensors, meta


def _check(t: dict, meta: dict, where: str):
    layers, hidden, k, o = meta["layers"], meta["hidden"], meta["frame_stack"], meta["obs_size"]
    if o not in observation.WIDTHS:
        raise ValueError(f"{where}: obs_size {o}, expected one of {observation.WIDTHS}")
    n = np.shape(t.get("head/bias", np.zeros((0, 8))))[0]
    want = {f"dense{i}/kernel": (n, k * o if i == 0 else hidden, hidden) for i in range(layers)}
    want.update({f"dense{i}/bias": (n, hidden) for i in range(layers)})
    want.update({"head/kernel": (n, hidden, 8), "head/bias": (n, 8), "norm/obs_mean": (n, o), "norm/obs_std": (n, o),
                 "norm/act_mean": (n, 8), "norm/act_std": (n, 8)})
    if set(t) != set(want):
        raise ValueError(f"{where}: tensors {sorted(t)}, expected {sorted(want)}")
    for name, shape in want.items():
        x = t[name]
        if tuple(x.shape) != shape or x.dtype != np.float32 or not np.all(np.isfinite(x)) or n < 1:
            raise ValueError(f"{where}: tensor {name!r} has shape {tuple(x.shape)} dtype {x.dtype} "
                             f"(expected finite float32 {shape})")


def mlp_forward(params: dict, layers: int, x):
    """One member: x [k, O] raw frames -> joint targets [8] (models.networks.MLPNet with the
    models.normalizer statistics around it)."""
    h = ((x - params["norm/obs_mean"]) / params["norm/obs_std"]).reshape(-1)
    for i in range(layers):
        h = jax.nn.relu(h @ params[f"dense{i}/kernel"] + params[f"dense{i}/bias"])
    a = h @ params["head/kernel"] + params["head/bias"]
    return a * params["norm/act_std"] + params["norm/act_mean"]


def goal_policy(cfg: World, meta: dict) -> backends.Policy:
    """The bootstrap policy for ONE throw (params: the tensors of `load_weights`, as JAX
    arrays): per episode a goal uniform over the opponent's half, written into the last
    `frame_stack` frames it sees; the mean of its members' joint targets."""
    return _goal_policy(cfg, int(meta["layers"]), int(meta["frame_stack"]), int(meta["obs_size"]))


@functools.lru_cache(maxsize=None)
def _goal_policy(cfg: World, layers: int, k: int, o: int) -> backends.Policy:
    """goal_policy, one object per configuration: compiled rollouts are kept by the policy."""
    if cfg.frame_stack < k:
        raise ValueError(f"the bootstrap policy stacks {k} frames; the world keeps {cfg.frame_stack} "
                         f"(World.frame_stack)")
    table = cfg.table

    def init(params, key):
        return uniform_goals(key, 1, table)[0]

    def apply(params, goal, obs, key):
        frames = observation.to_width(obs.frames[-k:], o, jnp.broadcast_to(obs.ball_vel, (k, 3)), xp=jnp)
        frames = observation.with_goal(frames, goal, xp=jnp)
        actions = jax.vmap(lambda p: mlp_forward(p, layers, frames))(params)
        return goal, actions.mean(0)
    return backends.Policy(init=init, apply=apply)


def load_policy(cfg: World, directory: str | None = None):
    """(Policy, params) of the `paper` source's last stage (without the joint perturbation,
    which demos.source_policy adds); default: the shipped build for cfg's throws."""
    from ttmjx.tools import es
    directory = directory or es.shipped_dir(cfg.throws.name, WEIGHTS_NAME)
    tensors, meta = load_weights(directory)
    built = meta.get("world", {}).get("throws", {}).get("name")
    if built is not None and built != cfg.throws.name:
        raise ValueError(f"the paper bootstrap's policy in {directory} was built on {built} throws, not "
                         f"{cfg.throws.name}: build it for them (ttmjx demos --source paper --rebuild all "
                         f"--distribution {cfg.throws.name}) or use --source striker")
    return goal_policy(cfg, meta), {k: jnp.asarray(v) for k, v in tensors.items()}


def read_meta(directory: str | None = None) -> dict:
    """The weights' JSON record (how they were built, the numbers measured)."""
    with open(os.path.join(directory or ASSETS, META_NAME)) as f:
        return json.load(f)
