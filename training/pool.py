"""The run's starting data: bootstrap demonstrations and robot logs, relabeled into the one
cache, and the normalizer fixed from them (or, with no demonstrations, from a first look at the
untrained policy's play)."""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

from models.normalizer import Normalizer, identity_normalizer, normalizer_from_data
from models.policy import init_params, make_policy
from training.cache import Cache, add_episodes, empty_cache
from training.checkpoint import steps as checkpoint_steps
from training.data import data_normalizer, keep_for_training, relabel
from training.runconfig import RunConfig
from ttmjx.tools import demos
from ttmjx.world import observation, record, thrower
from ttmjx.world.backends import Backend, resolve_backend
from ttmjx.world.config import World
from ttmjx.world.env import uniform_goals


# The demonstrations collected last in this process, by (world, source, count, seed, backend):
# the lanes of a table, collected together (`collect_for_lanes`), and a table's later programs
# that start from the same seeds' demonstrations (LFP at 0.2's updates after GoalsEye) take them
# from here. Kept until the next collection (a 15-lane paper-sim table: about 1 GB of host memory).
_COLLECTED: dict = {}


def _collect_key(cfg: RunConfig) -> tuple:
    return (cfg.world, cfg.demo_source, cfg.demos, cfg.seed + 10_000, resolve_backend(cfg.backend))


def needs_collecting(cfg: RunConfig) -> bool:
    """Whether cfg's run starts by collecting demonstrations: it has some, no dataset directory,
    none saved in its run directory and no checkpoint to resume from."""
    return (cfg.demos > 0 and not cfg.demo_dir
            and not os.path.exists(os.path.join(cfg.run_dir, "demos", "trajectories.npz"))
            and not checkpoint_steps(os.path.join(cfg.run_dir, "checkpoints")))


def collect_for_lanes(cfgs: list[RunConfig], progress: bool, place=None, devices: int = 1) -> None:
    """Collect the demonstrations of every run in `cfgs` that starts by collecting, the runs of a
    source and count together (demos.collect_lanes: one rollout per chunk for all their seeds,
    split over `devices` by `place` on MJX), into the memo `load_demos` reads: so a table's setup
    plays its lanes' demonstrations at once."""
    want = {_collect_key(c): c for c in cfgs if needs_collecting(c)}
    kept = {k: v for k, v in _COLLECTED.items() if k in want}
    groups: dict = {}
    for k, c in want.items():
        if k not in kept:
            groups.setdefault((c.world, c.demo_source, c.demos, k[-1]), []).append(k)
    for (world, source, n, backend), keys in groups.items():
        trajs = demos.collect_lanes(world, source, n, [k[3] for k in keys], backend, progress=progress,
                                    place=place, devices=devices)
        kept.update(zip(keys, trajs))
    if want:
        _COLLECTED.clear()
        _COLLECTED.update(kept)


def load_demos(cfg: RunConfig, progress: bool) -> record.Trajectories | None:
    """The bootstrap demonstrations: a dataset directory, or collected now (cached on disk in
    the run directory so a resumed run does not collect them twice)."""
    if cfg.demos == 0:
        return None
    if cfg.demo_dir:
        check_dataset(cfg.demo_dir, cfg.world)
        traj, _ = record.load(cfg.demo_dir)
        if traj.size < cfg.demos:
            raise ValueError(f"{cfg.demo_dir} holds {traj.size} demonstrations, the run asks for demos={cfg.demos}")
        return jax.tree.map(lambda x: x[:cfg.demos], traj)
    path = os.path.join(cfg.run_dir, "demos")
    if os.path.exists(os.path.join(path, "trajectories.npz")):
        return record.load(path)[0]
    key = _collect_key(cfg)
    if key not in _COLLECTED:
        _COLLECTED.clear()
        _COLLECTED[key] = demos.collect(cfg.world, cfg.demo_source, cfg.demos, cfg.seed + 10_000, key[-1],
                                        progress=progress)
    traj = _COLLECTED[key]
    record.save(path, traj, {"source": cfg.demo_source, "source_version": demos.SOURCE_VERSION,
                             "distribution": cfg.world.throws.name,
                             "seed": cfg.seed + 10_000, **demos.summary(traj, cfg.world)})
    return traj


def episode_names(d: str) -> list[str]:
    """Names of the episode logs in a robot log directory (ttmjx robot run --out)."""
    if not os.path.isdir(d):
        raise FileNotFoundError(f"--data {d}: not a directory of robot logs")
    names = sorted(f[:-len(".meta.json")] for f in os.listdir(d) if f.endswith(".meta.json")
                   and not f.endswith(".deploy.meta.json"))
    if not names:
        raise FileNotFoundError(f"--data {d}: no episode logs (*.meta.json) found")
    return names


def _read_meta(path: str) -> dict:
    import json
    try:
        with open(path) as f:
            meta = json.load(f)
    except (OSError, ValueError) as e:
        raise record.RecordError(f"{path}: unreadable metadata ({e})") from e
    if not isinstance(meta, dict):
        raise record.RecordError(f"{path}: metadata is not a JSON object")
    return meta


def check_dataset(directory: str, world: World) -> None:
    """A demonstrations directory (--demo-dir) was collected in this run's world: the same
    control rate, observation layout and episode length. Refused, naming both values, when not:
    relabelled at another rate it would train on steps of the wrong length."""
    _, meta_path = record.dataset_files(directory)
    meta = _read_meta(meta_path)
    theirs = meta.get("world")
    if isinstance(theirs, dict):
        hz = theirs.get("control_hz")
        if hz is not None and hz != world.control_hz:
            raise ValueError(f"--demo-dir {directory}: collected at {hz} Hz ({meta_path}), this run trains at "
                             f"{world.control_hz} Hz (--world.control-hz); collect it again at {world.control_hz} Hz "
                             f"(ttmjx demos --control-hz) or train at {hz} Hz")
        vel = theirs.get("ball_velocity_obs")
        if vel is not None and bool(vel) != world.ball_velocity_obs:
            raise ValueError(f"--demo-dir {directory}: observation layout ball_velocity_obs={vel} ({meta_path}), this "
                             f"run has --world.ball-velocity-obs {world.ball_velocity_obs}")
    horizon = meta.get("horizon")
    if horizon is not None and horizon != world.horizon:
        raise ValueError(f"--demo-dir {directory}: episodes of {horizon} control steps ({meta_path}), this run's "
                         f"are {world.horizon} ({world.episode_s:g} s at {world.control_hz} Hz); collect it again "
                         f"in this run's world")


def check_log(directory: str, name: str, world: World) -> None:
    """A robot log (--data) was played under a contract this run can learn from: the run's
    control rate, observation size and joint order. Refused, naming both values, when not."""
    from ttmjx.world.config import JOINT_NAMES
    meta_path = os.path.join(directory, f"{name}.meta.json")
    contract = _read_meta(meta_path).get("contract")
    if not isinstance(contract, dict):
        return          # a log without its contract (older runner): nothing to compare
    hz = contract.get("control_hz")
    if hz is not None and float(hz) != float(world.control_hz):
        raise ValueError(f"--data {directory}: {name} was played at {hz:g} Hz ({meta_path}), this run trains at "
                         f"{world.control_hz} Hz (--world.control-hz); its steps would be relabelled as "
                         f"{1000 / world.control_hz:g} ms apart instead of {1000 / hz:g} ms")
    size = contract.get("obs_size")
    if size is not None and size != world.obs_size:
        raise ValueError(f"--data {directory}: {name} was played with {size}-value observations ({meta_path}), "
                         f"this run's policy sees {world.obs_size} (--world.ball-velocity-obs "
                         f"{world.ball_velocity_obs})")
    names = contract.get("joint_names")
    if names is not None and tuple(names) != JOINT_NAMES:
        raise ValueError(f"--data {directory}: {name} has joint order {tuple(names)} ({meta_path}), "
                         f"this run's is {JOINT_NAMES}")


def check_sources(cfg: RunConfig) -> None:
    """The demonstration dataset and robot log directories a run names exist and were recorded
    in this run's world (checked before the run directory is created)."""
    if cfg.demo_dir and cfg.demos:
        check_dataset(cfg.demo_dir, cfg.world)
    for d in cfg.data:
        for n in episode_names(d):
            check_log(d, n, cfg.world)


def load_logs(paths, horizon: int, world: World | None = None) -> record.Trajectories | None:
    """Robot logs (deploy episode directories) as one record padded/truncated to `horizon`;
    with `world`, each log's contract is checked against it first (check_log)."""
    names = [(d, n) for d in paths for n in episode_names(d)]
    if world is not None:
        for d, n in names:
            check_log(d, n, world)
    parts = [fit_horizon(record.load(d, n)[0], horizon) for d, n in names]
    return record.concat(parts) if parts else None


def fit_horizon(traj: record.Trajectories, horizon: int) -> record.Trajectories:
    """Pad (valid=False, last frame repeated) or truncate a record to `horizon` steps."""
    t = traj.obs.shape[1]
    if t == horizon:
        return traj
    def fit(x):
        if x.ndim < 2 or x.shape[1] != t:
            return x
        if t > horizon:
            return x[:, :horizon]
        pad = np.repeat(x[:, -1:], horizon - t, 1)
        return np.concatenate([x, np.zeros_like(pad) if x.dtype == bool else pad], 1)
    return record.Trajectories(*(fit(np.asarray(x)) for x in traj))


def append_record(cache: Cache, traj: record.Trajectories, cfg: RunConfig, demo: bool = False) -> Cache:
    """Relabel and append a host record (demonstrations are flagged for the sampler)."""
    return add_episodes(cache, jax.tree.map(jnp.asarray, record.to_numpy(traj)), cfg.world.table,
                        cfg.train.goal_margin, demo=demo)


def starting_pool(cfg: RunConfig, demos_: record.Trajectories | None, logs: record.Trajectories | None,
                  backend: Backend, key) -> tuple[Cache, Normalizer, int]:
    """(cache, normalizer, trajectories seen) at the start of a run."""
    cache = empty_cache(cfg.train.capacity, cfg.world.horizon)
    data = [x for x in (demos_, logs) if x is not None]
    if not data:   # GCSL: no demonstrations
        return cache, bootstrap_normalizer(cfg, backend, key), 0
    traj = record.concat([record.to_numpy(x) for x in data])
    keep = keep_for_training(traj, cfg.world.table, cfg.train.goal_margin)
    if not np.any(keep):
        raise ValueError("none of the demonstrations hit and landed near the opponent's half: nothing to imitate")
    norm = data_normalizer(relabel(traj), cfg.policy.obs_size, keep, cfg.train.min_std)
    # Demonstrations are marked (the sampler's demo_fraction); robot logs are practice.
    for part, is_demo in ((demos_, True), (logs, False)):
        if part is not None:
            cache = append_record(cache, part, cfg, demo=is_demo)
    return cache, norm, traj.size


def bootstrap_normalizer(cfg: RunConfig, backend: Backend, key) -> Normalizer:
    """GCSL has no demonstrations to normalize with: observation statistics from 64 episodes
    of the untrained policy, action statistics from the robot's home pose and ranges."""
    params = init_params(jax.random.fold_in(key, 2), cfg.policy, identity_normalizer(cfg.policy.obs_size))
    n = 64
    th = thrower.sample_throws(jax.random.fold_in(key, 3), cfg.world, n)
    traj = backend.rollout_one(make_policy(cfg.policy), params, jax.random.fold_in(key, 4), th,
                           np.asarray(uniform_goals(jax.random.fold_in(key, 5), n, cfg.world.table)))
    obs = observation.to_width(jnp.asarray(traj.obs), cfg.policy.obs_size, jnp.asarray(traj.ball_vel), xp=jnp)
    # Actions of an untrained net carry no scale: use the joint ranges' spread instead.
    r = cfg.world.robot
    norm = normalizer_from_data(obs, jnp.asarray(traj.actions), jnp.asarray(traj.valid), cfg.train.min_std)
    span = (jnp.array(r.upper) - jnp.array(r.lower)) / 8
    return norm._replace(act_mean=jnp.array(r.home), act_std=jnp.minimum(span, 1.0))
