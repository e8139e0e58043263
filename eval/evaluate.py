"""Evaluation of trained policies: uniform goals, the five-goal protocol or a user's goal set
(a --goals value in the grammar of ttmjx.world.goalspec, shared with `ttmjx robot run`), no
exploration noise; an ensemble plays the goals in equal blocks, one block per
member. Scoring is the world's one strict goal-metrics function (ttmjx.world.goals); `--out`
writes the per-episode record (eval.report)."""
from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np

from eval.heldout import with_heldout_loss
from eval.report import check_out_dir, write_eval_dir
from models.config import PolicyConfig
from models.policy import ensemble_size, make_policy, member
from training.budget import episodes_that_fit
from training.checkpoint import load_checkpoint
from training.seeds import stacked
from ttmjx.world import thrower
from ttmjx.world.backends import Backend, lane, lane_of_one, resolve_backend
from ttmjx.world.config import THROW_DISTRIBUTIONS, World
from ttmjx.world.env import uniform_goals
from ttmjx.world.goals import (GOAL_REGIONS, five_goals, goal_metrics, member_success, per_goal_metrics,
                               region_success)
from ttmjx.world.goalspec import GoalSpec, goal_spec
from ttmjx.world.record import Trajectories


def rollout_goals(world: World, pcfg: PolicyConfig, params, backend: Backend, keys, goals, members=None,
                  truth: bool = False):
    """Trajectories [L, N] of the policy in L lanes (params leaves [L, ...], keys [L]) toward
    goals [L, N, 2], one throw each; one run is a lane of one (rollout_goals_one). An ensemble
    plays in equal blocks: goals and their throws are repeated cyclically up to a multiple of
    the members and the repeats dropped, so every member count sees the same N goals and
    throws, once each. truth=True: (Trajectories, TrueTrack) [L, N], the simulation's true ball
    and joints beside them (`ttmjx eval --out`; Backend.rollout)."""
    goals = np.asarray(goals, np.float32)
    n = goals.shape[1]
    k_throw, k_roll = split_lanes(keys)
    th = jax.vmap(lambda k: thrower.sample_throws(k, world, n))(k_throw)
    idx = padded(np.arange(n), members)
    out = backend.rollout(make_policy(pcfg), params, k_roll, jax.tree.map(lambda x: x[:, idx], th), goals[:, idx],
                          members=members, truth=truth)
    cut = lambda tree: type(tree)(*(x[:, :n] for x in tree))  # noqa: E731
    return (cut(out[0]), cut(out[1])) if truth else cut(out)


def rollout_goals_one(world: World, pcfg: PolicyConfig, params, backend: Backend, key, goals, members=None,
                      truth: bool = False):
    """`rollout_goals` of one run, as a lane of one: params, key and goals [N, 2] without the lane
    axis -> Trajectories [N] (truth=True: and TrueTrack [N])."""
    return lane(rollout_goals(world, pcfg, lane_of_one(params), backend, lane_of_one(key), lane_of_one(goals),
                              members, truth))


def split_lanes(keys):
    """Two keys per lane from keys [L]: ([L], [L])."""
    return tuple(jax.numpy.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0))


def padded(goals: np.ndarray, members: int | None) -> np.ndarray:
    """Repeat goals cyclically up to a multiple of the ensemble size."""
    n = members or 1
    total = math.ceil(len(goals) / n) * n
    return goals[np.arange(total) % len(goals)]


def uniform_runs(world: World, pcfg: PolicyConfig, params, backend: Backend, keys, n_goals: int = 200,
                 members: int | None = None) -> tuple[list[dict], Trajectories]:
    """L independent uniform evaluations: params leaves [L, ...], keys [L] -> ([goal_metrics] per
    lane, Trajectories [L, n_goals]) over n_goals uniform goals on the opponent's half, lane l's
    goals and throws drawn from keys[l] alone (uniform_plan; evaluate_uniform is a lane of one)."""
    goals, k_run = uniform_plan(world, keys, n_goals)
    tr = rollout_goals(world, pcfg, params, backend, k_run, goals, members)
    return [goal_metrics(tr.landing[i], goals[i], tr.hit[i], tr.on_opponent[i]) for i in range(len(goals))], tr


def uniform_plan(world: World, keys, n_goals: int):
    """(goals [L, n_goals, 2] uniform on the opponent's half, rollout keys [L]) of uniform_runs'
    keys [L]."""
    k_goal, k_run = split_lanes(keys)
    goals = jax.vmap(lambda k: uniform_goals(k, n_goals, world.table))(k_goal)
    return np.asarray(goals, np.float32), k_run


def evaluate_uniform(world: World, pcfg: PolicyConfig, params, backend: Backend, key, n_goals: int = 200,
                     members: int | None = None) -> dict:
    """goal_metrics of one run (params and key without the lane axis) over n_goals uniform goals
    on the opponent's half: uniform_runs on a lane of one."""
    return uniform_runs(world, pcfg, lane_of_one(params), backend, lane_of_one(key), n_goals, members)[0][0]


def five_run(world: World, pcfg: PolicyConfig, params, backend: Backend, key, per_goal: int = 40,
             members: int | None = None) -> tuple[dict, Trajectories]:
    """(metrics, Trajectories) of the five-goal protocol: per_goal attempts at each of goals A-E;
    totals plus per goal."""
    goals, names = five_goals(per_goal)
    tr = rollout_goals_one(world, pcfg, params, backend, key, goals, members)
    out = goal_metrics(tr.landing, goals, tr.hit, tr.on_opponent)
    out["per_goal"] = per_goal_metrics(tr.landing, goals, tr.hit, tr.on_opponent, list(names))
    return out, tr


def goal_set_run(world: World, pcfg: PolicyConfig, params, backend: Backend, key, goals,
                 members: int | None = None) -> tuple[dict, Trajectories]:
    """(goal_metrics, Trajectories [N]) of one attempt at each of the user's goals [N, 2]. The
    throws are those of a uniform evaluation of as many goals with the same key."""
    goals, k_run = goal_set_plan(key, goals)
    tr = rollout_goals_one(world, pcfg, params, backend, k_run, goals, members)
    return goal_metrics(tr.landing, goals, tr.hit, tr.on_opponent), tr


def goal_set_plan(key, goals):
    """(goals [N, 2], the rollout key) of goal_set_run's `key`: the key a uniform evaluation of
    as many goals rolls out with, so a goal file is attempted on its throws."""
    return np.asarray(goals, np.float32), jax.random.split(key)[1]


def with_regions(metrics: dict, tr: Trajectories, table, members: int | None = None) -> dict:
    """metrics plus the diagnostics of `ttmjx report`: `<region>_30cm`, within 30 cm over the
    goals of each of GOAL_REGIONS (NaN for a region no goal fell in), and for an ensemble
    `member<i>_30cm`, each member alone over the block of goals it played."""
    outcome = (tr.landing, tr.goal, tr.hit, tr.on_opponent)
    out = {**metrics, **{f"{name}_30cm": float(v) for name, v in zip(GOAL_REGIONS, region_success(*outcome, table))}}
    if members and members > 1:
        out.update({f"member{i}_30cm": float(v) for i, v in enumerate(member_success(*outcome, members))})
    return out


def training_evaluation(cfgs, heldout: bool = False):
    """The evaluation of a training program's lanes (training.trainer.Run calls it with its
    lanes' configs, in lane order; one RunConfig is a lane of one): (params [L, ...], backend,
    keys [L]) -> [metrics] per lane, each lane's goals and throws as if it ran alone:
    cfg.eval_goals uniform goals, the whole ensemble playing, with success by goal region.
    heldout=True adds each run's loss on its own held-out demonstrations (eval.heldout:
    `heldout_loss`, `member<i>_heldout_loss`; none without demonstrations)."""
    cfgs = [cfgs] if not isinstance(cfgs, (list, tuple)) else list(cfgs)
    cfg = cfgs[0]

    def evaluate(params, backend: Backend, keys) -> list[dict]:
        metrics, tr = uniform_runs(cfg.world, cfg.policy, params, backend, keys, cfg.eval_goals,
                                   members=cfg.train.members)
        return [with_regions(m, Trajectories(*(x[s] for x in tr)), cfg.world.table, cfg.train.members)
                for s, m in enumerate(metrics)]
    return with_heldout_loss(cfgs, evaluate) if heldout else evaluate


EVAL_UNIFORM_GOALS = 200     # `--goals uniform`: as many uniform goals as `ttmjx eval`'s default


def evaluate_checkpoint(path: str, goals: str = "200", per_goal: int = 40, distribution: str | None = None,
                        backend: str | None = None, seed: int = 1234, member_index: int | None = None,
                        step: int | None = None, out: str | None = None) -> dict:
    """`ttmjx eval`: metrics of a run's checkpoint (its moving-average policy) on `goals`, a
    --goals value (ttmjx.world.goalspec, the one grammar `ttmjx robot run` reads too): N uniform
    goals ('uniform': EVAL_UNIFORM_GOALS), 'five' (per_goal attempts at each of A-E), or goals
    inline or in a goal file (one attempt each); throws of the run's distribution or
    `distribution`; one member alone with member_index. With `out`, the metrics, one row per
    episode and the ball tracks are written there (eval.report). evaluate_checkpoints on a lane
    of one."""
    return evaluate_checkpoints([path], goals, per_goal, distribution, backend, seed, member_index, step, out)[0]


def evaluate_checkpoints(paths: list[str], goals: str = "200", per_goal: int = 40, distribution: str | None = None,
                         backend: str | None = None, seed: int = 1234, member_index: int | None = None,
                         step: int | None = None, out: str | None = None) -> list[dict]:
    """evaluate_checkpoint's metrics of every run in `paths` (one per run, in order), the runs
    played as the lanes of one rollout: params [L, ...]; every lane gets the goals and keys
    one run gets alone, so each is scored exactly as it is scored alone. The runs must share
    what the rollout is built from (shared_config). `out` (one run's records) takes one run."""
    if distribution is not None and distribution not in THROW_DISTRIBUTIONS:
        raise ValueError(f"distribution {distribution!r}; expected one of {THROW_DISTRIBUTIONS}")
    if not paths:
        raise ValueError("no run to evaluate: expected at least one run directory")
    if out is not None:
        if len(paths) != 1:
            raise ValueError(f"out={out!r} with {len(paths)} runs: the records are one run's; expected one run")
        check_out_dir(out)
    loaded = [load_checkpoint(p, step) for p in paths]
    cfg = shared_config(paths, [ld.cfg for ld in loaded], backend)
    world = cfg.world if distribution is None else cfg.world.with_throws(distribution)
    # explicit goals lie on this run's table; counts are bounded by what fits in this device's
    # memory, shared by the L lanes that play at once
    spec = goal_spec(goals, world.table, most=max(1, episodes_that_fit(World()) // len(paths)))
    be = Backend(world, resolve_backend(backend or cfg.backend))
    members, params = lane_params(loaded, cfg.train.members, member_index)
    goals, names, k_run = eval_plan(spec, world, jax.random.PRNGKey(seed), per_goal)
    # every lane plays the goals and rollout key of a run alone (Backend.rollout: a lane's draws
    # and record are its own), so a batch's seed scores what `--seed-index K` scores
    same = lambda x: stacked([x] * len(paths))  # noqa: E731
    # With --out the rollout also carries the true ball (tracks.npz); the record is the same.
    played = rollout_goals(world, cfg.policy, params, be, same(k_run), same(goals), members, truth=out is not None)
    tr, true = played if out is not None else (played, None)
    res = [lane_metrics(lane(tr, i), goals, names, world, ld) for i, ld in enumerate(loaded)]
    if out is not None:
        write_eval_dir(out, res[0], lane(tr), world, lane(true))
    return res


def shared_config(paths: list[str], cfgs: list, backend: str | None):
    """The first run's RunConfig, once every run agrees with it on what one rollout of their lanes
    is built from: the world, the policy, the ensemble size and (unless `backend` names one) the
    backend; ValueError naming the first run and field that differ."""
    first = cfgs[0]
    shared = lambda c: {"world": c.world, "policy": c.policy, "train.members": c.train.members,  # noqa: E731
                        **({} if backend else {"backend": c.backend})}
    for path, c in zip(paths[1:], cfgs[1:]):
        for name, want in shared(first).items():
            diff = first_difference(want, shared(c)[name], name)
            if diff is not None:
                field, a, b = diff
                raise ValueError(f"{path}: {field} is {b!r}, {paths[0]}'s is {a!r}; runs evaluated together "
                                 f"must share the world, the policy, the ensemble size and the backend")
    return first


def first_difference(a, b, name: str):
    """(dotted field, a's value, b's value) of the first field in which a and b differ, looking
    inside dataclasses (the innermost field names what differs); None where they are equal."""
    if a == b:
        return None
    if dataclasses.is_dataclass(a) and type(a) is type(b):
        inner = (first_difference(getattr(a, f.name), getattr(b, f.name), f"{name}.{f.name}")
                 for f in dataclasses.fields(a))
        return next((d for d in inner if d is not None), (name, a, b))
    return name, a, b


def lane_params(loaded: list, members: int, member_index: int | None):
    """(members, acting params [L, ...] of the runs stacked along the lane axis): the ensemble
    [L, N, ...] playing in blocks, or with member_index that member alone in every lane (members
    None, [L, ...])."""
    params = [ld.params for ld in loaded]
    if member_index is not None:
        if not 0 <= member_index < ensemble_size(params[0]):
            raise ValueError(f"--member {member_index} is out of range: the run has {members} members")
        members, params = None, [member(p, member_index) for p in params]
    return members, stacked(params)


def lane_metrics(tr: Trajectories, goals, names, world: World, loaded) -> dict:
    """One run's result from its lane of the rollout (Trajectories [N] toward goals [N, 2]):
    goal_metrics, per goal for 'five' (names), the throw distribution and the checkpoint's
    trajectories and step."""
    res = goal_metrics(tr.landing, goals, tr.hit, tr.on_opponent)
    if names is not None:
        res["per_goal"] = per_goal_metrics(tr.landing, goals, tr.hit, tr.on_opponent, list(names))
    return {**res, "distribution": world.throws.name, "trajectories": int(loaded.ck.counters.trajectories),
            "step": loaded.step}


def eval_plan(spec: GoalSpec, world: World, key, per_goal: int):
    """(goals [N, 2], their names for 'five' else None, the rollout key) of a parsed --goals value:
    the goals and keys of evaluate_uniform, five_run and goal_set_run, so `ttmjx eval` scores what
    they score."""
    if spec.kind == "five":
        goals, names = five_goals(per_goal)
        return goals, names, key
    if spec.kind == "points":
        goals, k_run = goal_set_plan(key, spec.goals)
        return goals, None, k_run
    goals, k_run = lane(uniform_plan(world, lane_of_one(key), spec.count or EVAL_UNIFORM_GOALS))
    return goals, None, k_run
