"""The `es` demonstration source and the first stage of the `paper` procedure: an
evolution-strategies policy trained in simulation on a shaped reward until it returns balls
(paper, "Building up the initial bootstrap dataset": a standard ES policy trained fully in
simulation, used to bootstrap demonstrations; it was "narrow"). The `es` source wraps it with the
4-joint perturbation (ttmjx/tools/demos.py); training/bootstrap_paper.py imitates and practises
from its rollouts.

The algorithm is the standard OpenAI-ES (Salimans et al. 2017, "Evolution Strategies as a
Scalable Alternative to Reinforcement Learning"): Gaussian perturbations of the parameter mean
with antithetic (mirrored) sampling, centred-rank fitness shaping, the gradient estimate
`sum_i F_i eps_i / (n sigma)` and Adam with L2 weight decay on the mean. It is written here in JAX
over `Backend.rollout` instead of brax's ES trainer, which needs a brax Env on MJX (~1k physics
steps/s on a CPU). It only calls `Backend.rollout`, so `backend="mjx"` (a GPU) takes the same path
(the population policy is jit-traceable); the shipped weights were trained on the C backend and
the MJX path has not been exercised.

Schedule: two phases with two rewards (`Reward`). The contact phase (`CONTACT`, from random
weights; ttmjx/tools/assets/es_contact.*) converges to a BLOCK: the blade in the ball's path,
the ball falling back on the robot's half. The return phase (`RETURN`, from the contact weights)
adds a dense landing term, so that every ball that comes down closer to the opponent's half
scores more. ttmjx/tools/assets/es_policy.json holds the shipped run, its curve and its measured
numbers (docs/DATA.md and docs/DESIGN.md, "Measurements behind the code"). Like the
paper's ES policy it is narrow: trained at 100 Hz on the narrow throws only. Nothing was tuned
against a GoalsEye learning result: the return phase's weights were set once, from what a block
scores against a return, and the run stopped at its time limit.

The policy (`mlp_policy`) is a small MLP for ONE throw over the observation's joints (8), ball
position (3) and ball velocity (3) (`env.Obs`: frame[:11] and ball_vel; the velocity is read
from `Obs.ball_vel`, so it needs no 16-value observation), with fixed input normalisation, one
tanh hidden layer, and a tanh-bounded output that is the joint-target OFFSET from the home pose:
`target = home + scale * tanh(W2 h + b2)`. The goal (frame[-2:]) is NOT an input: the policy is
not goal-directed (demonstrations carry a zero placeholder goal and are relabeled later). With a
zero output layer the policy holds the home pose.

Shaped reward of one throw (`shaped_reward`, from the Trajectories record plus the blade centre,
which MuJoCo C kinematics computes from the recorded joints obs[..., :8]), weights CONTACT /
RETURN:

    - min(closest ball-to-blade-centre distance before the hit, 1 m)
    + 1.0 / 0.5 if the paddle touched the ball (`hit`)
    + 0.5 / 0.5 * clip(largest ball x-velocity after the hit, 0, 6 m/s) / 6
    + 0.5 / 0   * clip(ball's x progress after the hit, 0, 2.5 m) / 2.5
    + 0   / 2.0 * (1 - min(|landing - aim|, 3 m) / 3 m), hit balls; aim = the half's centre;
                  a ball still flying at the end counts where it was last seen
    + 2.0 / 2.0 if the ball landed on the opponent's half (`on_opponent`)

Population rollouts: every candidate of a generation plays the same K throws (common random
numbers) in ONE batched `Backend.rollout`. Candidates have their own parameters, but a rollout
shares its params across the batch, so the population policy receives the stacked parameter
vectors [P, D] and reads each throw's candidate index from the goal slot of the observation
(the goal the rollout is given is the index; the MLP never sees the goal).

Weights are saved as an uncompressed .npz of named float32 arrays (loaded with
allow_pickle=False) plus a JSON file with the training summary; the shipped ones live in
ttmjx/tools/assets/ (es_policy.npz, es_policy.json).
"""
from __future__ import annotations

import functools
import io
import json
import math
import os
import sys
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from ttmjx.world import backends, files, observation
from ttmjx.world.config import World

ASSETS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "assets")
WEIGHTS_NAME = "es_policy.npz"
META_NAME = "es_policy.json"
FORMAT_VERSION = 1

# Fixed input normalisation: (x - centre) / scale for joints (offsets from home), ball position
# (centre over the robot's half of the table) and ball velocity.
BALL_CENTRE = (-0.5, 0.0, 0.95)
BALL_SCALE = (1.5, 0.5, 0.25)
VEL_SCALE = (6.0, 2.0, 3.0)
# Largest joint-target offset from home per joint (m for the gantry, rad for the arm).
ACTION_SCALE = (0.25, 0.9, 1.5, 1.2, 1.2, 1.5, 1.5, 1.5)
N_FEATURES = 14
PARAM_NAMES = ("W1", "b1", "W2", "b2", "in_centre", "in_scale", "home", "action_scale")
TRAINABLE = ("W1", "b1", "W2", "b2")
# Shaped-reward terms (see the module docstring and `Reward`).
CLOSE_CAP = 1.0
NEAR_X = -0.9   # blade distances are computed only where the ball is beyond this x (robot side)
LAND_SCALE = 3.0  # m: the landing term falls linearly from 1 at the aim point to 0 this far away


class Reward(NamedTuple):
    """Weights of the shaped reward's terms (`shaped_reward`). The reach term -min(closest, 1)
    always has weight 1."""
    hit: float = 1.0        # the paddle touched the ball
    vel: float = 0.5        # clip(largest ball x-velocity after the hit, 0, 6 m/s) / 6
    progress: float = 0.5   # clip(ball's x progress after the hit, 0, 2.5 m) / 2.5
    land: float = 0.0       # 1 - min(|landing - aim|, LAND_SCALE) / LAND_SCALE, hit balls only
    ret: float = 2.0        # the first bounce after the hit was on the opponent's half
    aim: tuple = (0.685, 0.0)   # m, table frame: the centre of the opponent's half


# Phase 1 (contact): the reward of the first shipped weights. Its optimum in reach is a block
# (the blade in the ball's path, the ball falling back on the robot's half): the return bonus is a
# cliff that no candidate near a block reaches.
CONTACT = Reward()
# Phase 2 (return): a dense landing term (how close to the opponent's half's centre the hit ball
# comes down, wherever it lands) makes a faster, higher return better than a block at every
# step, so the search climbs from the block to returns; the hit weight is halved so that a
# harder stroke that sometimes misses is not worse than a sure block.
RETURN = Reward(hit=0.5, vel=0.5, progress=0.0, land=2.0, ret=2.0)
REWARDS = {"contact": CONTACT, "return": RETURN}


# ----------------------------------------------------------------------------------------------
# The policy
# ----------------------------------------------------------------------------------------------

def init_params(cfg: World, key, hidden: int = 32) -> dict:
    """Initial parameters: random hidden layer, zero output layer (the policy holds home)."""
    r = cfg.robot
    w1 = jax.random.normal(key, (N_FEATURES, hidden), jnp.float32) / math.sqrt(N_FEATURES)
    return {
        "W1": w1, "b1": jnp.zeros(hidden, jnp.float32),
        "W2": jnp.zeros((hidden, 8), jnp.float32), "b2": jnp.zeros(8, jnp.float32),
        "in_centre": jnp.asarray(np.concatenate([r.home, BALL_CENTRE, np.zeros(3)]), jnp.float32),
        "in_scale": jnp.asarray(np.concatenate([ACTION_SCALE, BALL_SCALE, VEL_SCALE]), jnp.float32),
        "home": jnp.asarray(r.home, jnp.float32),
        "action_scale": jnp.asarray(ACTION_SCALE, jnp.float32),
    }


def features(obs, params):
    """[14] normalised joints, ball position, ball velocity of one observation."""
    x = jnp.concatenate([observation.joints_and_ball(obs.frame), obs.ball_vel])
    return (x - params["in_centre"]) / params["in_scale"]


def mlp_action(params, obs):
    """[8] absolute joint targets of one observation."""
    h = jnp.tanh(features(obs, params) @ params["W1"] + params["b1"])
    return params["home"] + params["action_scale"] * jnp.tanh(h @ params["W2"] + params["b2"])


@functools.lru_cache(maxsize=None)
def mlp_policy() -> backends.Policy:
    """The ES policy for ONE throw; params from `init_params` / `load_policy`. Stateless. One
    object: compiled rollouts are kept by the policy they play."""
    return backends.Policy(init=lambda params, key: jnp.zeros(()),
                           apply=lambda params, carry, obs, key: (carry, mlp_action(params, obs)))


def split_params(params: dict):
    """(trainable dict, fixed dict)."""
    return ({k: params[k] for k in TRAINABLE}, {k: params[k] for k in params if k not in TRAINABLE})


def population_policy(fixed: dict, unravel: Callable) -> backends.Policy:
    """A policy whose params are the stacked trainable vectors [P, D] of a population; each
    throw's candidate index is the goal's x of its observation."""
    def apply(thetas, carry, obs, key):
        idx = jnp.round(observation.goal(obs.frame)[0]).astype(jnp.int32)
        params = {**fixed, **unravel(thetas[idx])}
        return carry, mlp_action(params, obs)
    return backends.Policy(init=lambda params, key: jnp.zeros(()), apply=apply)


# ----------------------------------------------------------------------------------------------
# Weights on disk (no pickle)
# ----------------------------------------------------------------------------------------------

def save_params(path: str, params: dict, meta: dict | None = None) -> str:
    """Write params as an uncompressed .npz of named float32 arrays (`path`, ".npz" appended if
    missing) and, if meta is given, a JSON file beside it (same name, ".json")."""
    if not path.endswith(".npz"):
        path = path + ".npz"
    missing = [k for k in PARAM_NAMES if k not in params]
    if missing:
        raise ValueError(f"params lack {missing}")
    arrays = {k: np.asarray(params[k], np.float32) for k in PARAM_NAMES}
    arrays["format_version"] = np.asarray(FORMAT_VERSION, np.int32)
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    files.write_bytes(path, buf.getvalue())
    if meta is not None:
        files.write_json(path[:-4] + ".json", {"format_version": FORMAT_VERSION, **meta})
    return path


def load_params(path: str) -> dict:
    """Params written by `save_params`, loaded with allow_pickle=False; ValueError names the
    problem if the file is missing or malformed."""
    if not os.path.exists(path):
        raise ValueError(f"{path}: ES weights file missing")
    try:
        with np.load(path, allow_pickle=False) as z:
            files = set(z.files)
            missing = [k for k in PARAM_NAMES + ("format_version",) if k not in files]
            if missing:
                raise ValueError(f"{path}: missing arrays {missing}")
            if int(z["format_version"]) != FORMAT_VERSION:
                raise ValueError(f"{path}: format_version {int(z['format_version'])}, this ttmjx "
                                 f"reads {FORMAT_VERSION}")
            params = {k: np.array(z[k]) for k in PARAM_NAMES}
    except ValueError:
        raise
    except Exception as e:  # zipfile.BadZipFile, EOFError on truncation
        raise ValueError(f"{path}: truncated or corrupt ({type(e).__name__}: {e})") from e
    n_in, hidden = params["W1"].shape
    want = {"W1": (N_FEATURES, hidden), "b1": (hidden,), "W2": (hidden, 8), "b2": (8,),
            "in_centre": (N_FEATURES,), "in_scale": (N_FEATURES,), "home": (8,), "action_scale": (8,)}
    for k, shape in want.items():
        if params[k].shape != shape or params[k].dtype != np.float32 or not np.all(np.isfinite(params[k])):
            raise ValueError(f"{path}: array {k!r} has shape {params[k].shape} dtype {params[k].dtype} "
                             f"(expected finite float32 {shape})")
    return params


def read_meta(params_dir: str | None = None) -> dict:
    """The JSON record beside the weights (default: the shipped ones): the run, the numbers."""
    with open(os.path.join(params_dir or ASSETS, META_NAME)) as f:
        return json.load(f)


def shipped_dir(distribution: str, weights_name: str = WEIGHTS_NAME) -> str:
    """Where shipped weights for a throw distribution live: ttmjx/tools/assets/ for narrow throws
    (the first builds), ttmjx/tools/assets/<distribution>/ for the others; a distribution with no
    build of its own gets the narrow one (which the loaders refuse or the caller names)."""
    d = os.path.join(ASSETS, distribution)
    return d if distribution != "narrow" and os.path.exists(os.path.join(d, weights_name)) else ASSETS


def load_policy(cfg: World, params_dir: str | None = None):
    """(Policy, params) of the ES source. params_dir: a directory holding es_policy.npz (default:
    the shipped weights for cfg's throws, `shipped_dir`) or the path of an .npz file itself. The home pose and
    the normalisation come from the weights file, not from cfg; the shipped policy was trained at
    100 Hz on narrow throws and is not meant for other rates or distributions."""
    path = params_dir or shipped_dir(cfg.throws.name)
    if os.path.isdir(path):
        path = os.path.join(path, WEIGHTS_NAME)
    params = jax.tree.map(jnp.asarray, load_params(path))
    return mlp_policy(), params


# ----------------------------------------------------------------------------------------------
# Shaped reward
# ----------------------------------------------------------------------------------------------

class Paddle:
    """Blade centre ("paddle" site) from joint vectors by MuJoCo C kinematics."""

    def __init__(self, cfg: World):
        import mujoco
        from ttmjx.world import scene
        self.mujoco = mujoco
        self.m = scene.model(cfg)
        self.d = mujoco.MjData(self.m)
        ids = scene.ids(self.m)
        self.qadr, self.site = ids.robot_qpos, ids.paddle_site

    def __call__(self, joints) -> np.ndarray:
        """joints [N, 8] -> blade centres [N, 3]."""
        joints = np.asarray(joints, np.float64)
        out = np.empty((len(joints), 3))
        d, m, kin = self.d, self.m, self.mujoco.mj_kinematics
        for i, q in enumerate(joints):
            d.qpos[self.qadr] = q
            kin(m, d)
            out[i] = d.site_xpos[self.site]
        return out


def shaped_reward(traj, paddle: Paddle, reward: Reward = CONTACT) -> dict:
    """Per-throw shaped reward and its terms ([B] arrays) of a Trajectories record, weighted by
    `reward` (`Reward`)."""
    obs = np.asarray(traj.obs)
    valid = np.asarray(traj.valid, bool)
    hit = np.asarray(traj.hit, bool)
    hit_step = np.asarray(traj.hit_step)
    b, t = valid.shape
    steps = np.arange(t)[None, :]
    ball = observation.ball_pos(obs)
    pre = valid & np.where(hit[:, None], steps <= hit_step[:, None], True)
    near = pre & (ball[..., 0] < NEAR_X)
    dist = np.full((b, t), np.inf)
    if near.any():
        dist[near] = np.linalg.norm(paddle(observation.joints(obs[near])) - ball[near], axis=-1)
    closest = np.minimum(dist.min(axis=1), CLOSE_CAP)
    post = valid & hit[:, None] & (steps > hit_step[:, None])
    vx = np.where(post, np.asarray(traj.ball_vel)[..., 0], -np.inf).max(axis=1)
    vx = np.where(hit, np.clip(vx, 0.0, 6.0), 0.0)
    x_hit = np.take_along_axis(ball[..., 0], np.maximum(hit_step, 0)[:, None], 1)[:, 0]
    x_max = np.where(post, ball[..., 0], -np.inf).max(axis=1)
    progress = np.where(hit, np.clip(x_max - x_hit, 0.0, 2.5), 0.0)
    ret = np.asarray(traj.on_opponent, bool)
    # Where the hit ball came down (table contact or fall through table height); a ball still
    # flying when the episode ended: its last observed position.
    last = np.maximum(valid.sum(1) - 1, 0)
    last_xy = ball[np.arange(b), last, :2]
    land_xy = np.asarray(traj.landing, np.float64)
    land_xy = np.where(np.isfinite(land_xy), land_xy, last_xy)
    miss = np.linalg.norm(land_xy - np.asarray(reward.aim), axis=-1)
    land = np.where(hit, 1.0 - np.minimum(miss, LAND_SCALE) / LAND_SCALE, 0.0)
    total = (-closest + reward.hit * hit + reward.vel * vx / 6.0 + reward.progress * progress / 2.5
             + reward.land * land + reward.ret * ret)
    return {"reward": total, "closest": closest, "hit": hit, "return": ret, "vx": vx,
            "progress": progress, "land": land}


# ----------------------------------------------------------------------------------------------
# OpenAI-ES
# ----------------------------------------------------------------------------------------------

class ESConfig(NamedTuple):
    sigma: float = 0.05          # perturbation scale (parameter space)
    lr: float = 0.02             # Adam step size on the mean
    weight_decay: float = 0.005  # L2 coefficient (Salimans et al.)
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-8


class ESState(NamedTuple):
    mean: jax.Array   # [D]
    m: jax.Array      # [D] Adam first moment
    v: jax.Array      # [D] Adam second moment
    step: jax.Array   # int32 Adam steps taken


def es_init(x0) -> ESState:
    x0 = jnp.asarray(x0, jnp.float32)
    return ESState(x0, jnp.zeros_like(x0), jnp.zeros_like(x0), jnp.int32(0))


def es_ask(state: ESState, key, population: int, sigma: float):
    """Antithetic population: (thetas [P, D], eps [P/2, D]); rows 0..P/2-1 are mean + sigma*eps,
    rows P/2.. their mirrors. population must be even."""
    if population < 2 or population % 2:
        raise ValueError(f"population must be an even number >= 2 (antithetic pairs), got {population}")
    eps = jax.random.normal(key, (population // 2, state.mean.shape[0]), jnp.float32)
    thetas = jnp.concatenate([state.mean + sigma * eps, state.mean - sigma * eps])
    return thetas, eps


def centered_ranks(x) -> np.ndarray:
    """Fitness shaping: ranks mapped linearly to [-0.5, 0.5] (ties broken by order)."""
    x = np.asarray(x)
    ranks = np.empty(len(x))
    ranks[np.argsort(x, kind="stable")] = np.arange(len(x))
    return ranks / max(len(x) - 1, 1) - 0.5


def es_tell(state: ESState, eps, fitness, es: ESConfig) -> ESState:
    """One Adam ascent step of the mean along the ES gradient estimate of `fitness` [P]."""
    half = eps.shape[0]
    shaped = jnp.asarray(centered_ranks(fitness), jnp.float32)
    grad = (shaped[:half] - shaped[half:]) @ eps / (2 * half * es.sigma)
    grad = grad - es.weight_decay * state.mean
    step = state.step + 1
    m = es.beta1 * state.m + (1 - es.beta1) * grad
    v = es.beta2 * state.v + (1 - es.beta2) * grad**2
    mhat = m / (1 - es.beta1 ** step.astype(jnp.float32))
    vhat = v / (1 - es.beta2 ** step.astype(jnp.float32))
    return ESState(state.mean + es.lr * mhat / (jnp.sqrt(vhat) + es.eps), m, v, step)


def openai_es(fitness_fn: Callable, x0, generations: int, population: int, seed: int = 0,
              es: ESConfig = ESConfig(), callback: Callable | None = None):
    """Maximise fitness_fn(thetas [P, D], generation) -> [P] from x0 [D]; returns the final
    ESState and the history (one dict per generation). callback(gen, state, info) may return
    True to stop."""
    state = es_init(x0)
    key = jax.random.PRNGKey(seed)
    history = []
    for gen in range(generations):
        thetas, eps = es_ask(state, jax.random.fold_in(key, gen), population, es.sigma)
        fit = np.asarray(fitness_fn(thetas, gen), np.float64)
        state = es_tell(state, eps, fit, es)
        info = {"generation": gen, "fitness_mean": float(fit.mean()), "fitness_max": float(fit.max())}
        history.append(info)
        if callback is not None and callback(gen, state, info):
            break
    return state, history


# ----------------------------------------------------------------------------------------------
# Training in the world
# ----------------------------------------------------------------------------------------------

def evaluate(cfg: World, policy, params, throws, seed: int = 0, backend="c", paddle=None,
             reward: Reward = CONTACT) -> dict:
    """Hit and return rates (and the mean shaped reward) of one policy on a batch of throws."""
    be = backend if isinstance(backend, backends.Backend) else backends.Backend(cfg, backend)
    n = np.shape(throws.launch_pos)[0]
    traj = be.rollout_one(policy, params, jax.random.PRNGKey(seed), throws, np.zeros((n, 2), np.float32))
    r = shaped_reward(traj, paddle or Paddle(cfg), reward)
    return {"n": int(n), "hit_rate": float(np.mean(traj.hit)), "return_rate": float(np.mean(traj.on_opponent)),
            "reward": float(np.mean(r["reward"])), "closest": float(np.mean(r["closest"])),
            "land": float(np.mean(r["land"]))}


def _take(throws, idx):
    return jax.tree.map(lambda x: np.asarray(x)[idx], throws)


def train_es(cfg: World, generations: int, population: int, seed: int, backend: str = "c",
             progress: bool = True, throws_per_candidate: int = 8, hidden: int = 32,
             es: ESConfig = ESConfig(), pool: int = 2048, val_throws: int = 64, eval_every: int = 10,
             init: dict | None = None, time_limit_s: float | None = None,
             checkpoint: str | None = None, reward: Reward = CONTACT):
    """Train the ES policy on cfg's throw distribution; returns (params, history).

    Each generation: `population` antithetic candidates each play the same
    `throws_per_candidate` throws drawn from a pool of `pool` throws sampled once; the fitness
    of a candidate is its mean shaped reward. Every `eval_every` generations (and at the end) the
    mean is evaluated on `val_throws` held-out throws; the returned params are the best mean so
    far by (return rate, hit rate, shaped reward), written to `checkpoint` (an .npz path) when
    given. `init` continues from given params; `time_limit_s` stops early (wall clock).
    history: one dict per generation (population fitness and rates, seconds, and the
    validation numbers on evaluated generations).
    """
    from ttmjx.world import thrower
    t_start = time.perf_counter()
    key = jax.random.PRNGKey(seed)
    k_init, k_pool, k_val, k_es = jax.random.split(key, 4)
    params = init if init is not None else init_params(cfg, k_init, hidden)
    params = jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), params)
    train, fixed = split_params(params)
    x0, unravel = ravel_pytree(train)
    throw_pool = jax.tree.map(np.asarray, thrower.sample_throws(k_pool, cfg, pool))
    val = jax.tree.map(np.asarray, thrower.sample_throws(k_val, cfg, val_throws))
    be = backends.Backend(cfg, backend)
    paddle = Paddle(cfg)
    pop_policy = population_policy(fixed, unravel)
    single = mlp_policy()
    k = throws_per_candidate
    rng = np.random.default_rng(seed)
    goals = np.stack([np.repeat(np.arange(population), k), np.zeros(population * k)], 1).astype(np.float32)
    best = {"score": None, "params": params, "generation": -1, "val": None}
    history: list[dict] = []
    last = {}

    def fitness(thetas, gen):
        idx = rng.choice(pool, k, replace=False)
        th = _take(throw_pool, np.tile(idx, population))
        traj = be.rollout_one(pop_policy, thetas, jax.random.fold_in(k_es, 10_000 + gen), th, goals)
        r = shaped_reward(traj, paddle, reward)
        last.update({kk: np.asarray(v, np.float64).reshape(population, k).mean(1) for kk, v in r.items()})
        return last["reward"]

    def evaluate_mean(state, gen, info):
        p = {**fixed, **unravel(state.mean)}
        v = evaluate(cfg, single, p, val, seed=seed + 1, backend=be, paddle=paddle, reward=reward)
        info.update({"val_" + kk: vv for kk, vv in v.items() if kk != "n"})
        score = (v["return_rate"], v["hit_rate"], v["reward"])
        if best["score"] is None or score > best["score"]:
            best.update(score=score, params=jax.tree.map(np.asarray, p), generation=gen, val=v)
            if checkpoint:
                save_params(checkpoint, best["params"], {"generation": gen, "validation": v})
        info["best_generation"] = best["generation"]

    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=generations, unit="gen", file=sys.stderr)

    def callback(gen, state, info):
        info.update({"hit_rate": float(last["hit"].mean()), "return_rate": float(last["return"].mean()),
                     "closest": float(last["closest"].mean()), "land": float(last["land"].mean()),
                     "seconds": time.perf_counter() - t_start})
        out_of_time = time_limit_s is not None and info["seconds"] > time_limit_s
        if (gen + 1) % eval_every == 0 or gen == generations - 1 or out_of_time:
            evaluate_mean(state, gen, info)
        history.append(info)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(fit=f"{info['fitness_mean']:.2f}", hit=f"{info['hit_rate']:.2f}",
                            ret=f"{info['return_rate']:.2f}", d=f"{info['closest']:.2f}")
        return out_of_time

    openai_es(fitness, x0, generations, population, seed, es, callback)
    if bar is not None:
        bar.close()
    return jax.tree.map(jnp.asarray, best["params"]), history
