"""The GoalsEye run: demonstrations -> relabeled cache -> GCBC pretraining (the LFP point) ->
self-supervised practice iterations -> evaluation, with checkpoints that resume exactly.

Every random draw of iteration i comes from fold_in(seed key, i), and the state is saved at
iteration boundaries, so a run killed at any point and resumed ends with the same parameters,
bit for bit, as an uninterrupted one (on a CPU, where the arithmetic is deterministic).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import sys
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from training.cache import Cache, add_episodes, empty_cache
from training.data import data_normalizer, keep_for_training, relabel
from training.practice import Practice
from training.runconfig import RunConfig, resolve_backend
from training.update import TrainState, acting_params, init_train_state
from ttmjx.world import record
from ttmjx.world.backends import Backend


class Counters(NamedTuple):
    iteration: jax.Array      # [] int32 iterations finished (pretraining chunks + practice rounds)
    trajectories: jax.Array   # [] int32 demonstrations + practice episodes seen
    updates: jax.Array        # [] int32 optimizer steps


class Checkpointed(NamedTuple):
    state: TrainState
    cache: Cache
    key: jax.Array            # [2] uint32 the run's base key
    counters: Counters


# -- schedule -------------------------------------------------------------------------------
def pretrain_iterations(cfg: RunConfig) -> int:
    return math.ceil(cfg.pretrain_steps / cfg.steps_between_ssp) if cfg.pretrain_steps else 0


def practice_iterations(cfg: RunConfig) -> int:
    """Practice rounds until total_trajectories (demonstrations + practice) are reached; with
    practice off (LFP) the same number of train-only rounds, so step counts match."""
    return max(0, math.ceil((cfg.total_trajectories - cfg.demos) / cfg.episodes_per_ssp))


def total_iterations(cfg: RunConfig) -> int:
    return pretrain_iterations(cfg) + practice_iterations(cfg)


def is_eval_iteration(cfg: RunConfig, it: int) -> bool:
    """Evaluate after the last pretraining round (the LFP point), every eval_every trajectories
    of practice, and at the end."""
    n_pre, n_tot = pretrain_iterations(cfg), total_iterations(cfg)
    if it == n_pre - 1 or it == n_tot - 1:
        return True
    if it >= n_pre:
        done = (it - n_pre + 1) * cfg.episodes_per_ssp
        return done % cfg.eval_every < cfg.episodes_per_ssp
    return False


# -- data ----------------------------------------------------------------------------------
def load_demos(cfg: RunConfig, progress: bool) -> record.Trajectories | None:
    """The bootstrap demonstrations: a dataset directory, or collected now (cached on disk in
    the run directory so a resumed run does not collect them twice)."""
    if cfg.demos == 0:
        return None
    if cfg.demo_dir:
        traj, _ = record.load(cfg.demo_dir)
        if traj.size < cfg.demos:
            raise ValueError(f"{cfg.demo_dir} holds {traj.size} demonstrations, the run asks for demos={cfg.demos}")
        return jax.tree.map(lambda x: x[:cfg.demos], traj)
    from ttmjx.tools import demos
    path = os.path.join(cfg.run_dir, "demos")
    if os.path.exists(os.path.join(path, "trajectories.npz")):
        return record.load(path)[0]
    backend = resolve_backend(cfg.backend)
    traj = demos.collect(cfg.world, cfg.demo_source, cfg.demos, cfg.seed + 10_000, backend, progress=progress)
    record.save(path, traj, {"source": cfg.demo_source, "distribution": cfg.world.throws.name,
                             "seed": cfg.seed + 10_000, **demos.summary(traj, cfg.world)})
    return traj


def load_logs(paths, horizon: int) -> record.Trajectories | None:
    """Robot logs (deploy episode directories) as one record padded/truncated to `horizon`."""
    parts = []
    for d in paths:
        names = sorted(f[:-len(".meta.json")] for f in os.listdir(d) if f.endswith(".meta.json")
                       and not f.endswith(".deploy.meta.json"))
        if not names:
            raise FileNotFoundError(f"--data {d}: no episode logs (*.meta.json) found")
        for n in names:
            parts.append(fit_horizon(record.load(d, n)[0], horizon))
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


# -- the run -------------------------------------------------------------------------------
class Run:
    """A training run in cfg.run_dir: fresh or resumed."""

    def __init__(self, cfg: RunConfig, progress: bool = True, log=print):
        self.cfg, self.progress, self.log = cfg, progress, log
        self.backend_name = resolve_backend(cfg.backend)
        self.backend = Backend(cfg.world, self.backend_name)
        self.practice = Practice(cfg.world, cfg.policy, cfg.train, self.backend,
                                 cfg.episodes_per_ssp, cfg.steps_between_ssp)
        self.ckpt_dir = os.path.join(cfg.run_dir, "checkpoints")
        self.metrics_path = os.path.join(cfg.run_dir, "metrics.jsonl")
        self._stop = False
        self._writer = None
        self._absorbed: list[str] = []   # robot log directories already in the cache (absolute)

    # -- state -----------------------------------------------------------------------------
    def initial(self) -> Checkpointed:
        cfg = self.cfg
        key = jax.random.PRNGKey(cfg.seed)
        demos = load_demos(cfg, self.progress)
        logs = load_logs(cfg.data, cfg.world.horizon) if cfg.data else None
        self._absorbed = [os.path.abspath(d) for d in cfg.data]
        data = [x for x in (demos, logs) if x is not None]
        cache = empty_cache(cfg.train.capacity, cfg.world.horizon)
        if data:
            traj = record.concat([record.to_numpy(x) for x in data])
            keep = keep_for_training(traj, cfg.world.table, cfg.train.goal_margin)
            if not np.any(keep):
                raise ValueError("none of the demonstrations hit and landed near the opponent's half: "
                                 "nothing to imitate")
            norm = data_normalizer(relabel(traj), cfg.policy.obs_size, keep, cfg.train.min_std)
            # Demonstrations are marked (the sampler's demo_fraction); robot logs are practice.
            for part, is_demo in ((demos, True), (logs, False)):
                if part is not None:
                    cache = add_episodes(cache, jax.tree.map(jnp.asarray, record.to_numpy(part)), cfg.world.table,
                                         cfg.train.goal_margin, demo=is_demo)
            seen = traj.size
        else:  # GCSL: no demonstrations; normalize with a first look at the untrained policy's play
            norm = self._bootstrap_normalizer(key)
            seen = 0
        state = init_train_state(jax.random.fold_in(key, 1), cfg.policy, cfg.train, norm)
        return Checkpointed(state, cache, key, Counters(jnp.int32(0), jnp.int32(seen), jnp.int32(0)))

    def _bootstrap_normalizer(self, key):
        """GCSL has no demonstrations to normalize with: observation statistics from 64 episodes
        of the untrained policy, action statistics from the robot's home pose and ranges."""
        from models.normalizer import identity_normalizer, normalizer_from_data
        from models.policy import init_params, make_policy, observation_vector
        from ttmjx.world.env import uniform_goals
        from ttmjx.world import thrower
        cfg = self.cfg
        params = init_params(jax.random.fold_in(key, 2), cfg.policy, identity_normalizer(cfg.policy.obs_size))
        n = 64
        th = thrower.sample_throws(jax.random.fold_in(key, 3), cfg.world, n)
        traj = self.backend.rollout(make_policy(cfg.policy), params, jax.random.fold_in(key, 4), th,
                                    np.asarray(uniform_goals(jax.random.fold_in(key, 5), n, cfg.world.table)))
        obs = observation_vector(jnp.asarray(traj.obs), jnp.asarray(traj.ball_vel), cfg.policy.obs_size)
        # Actions of an untrained net carry no scale: use the joint ranges' spread instead.
        r = cfg.world.robot
        norm = normalizer_from_data(obs, jnp.asarray(traj.actions), jnp.asarray(traj.valid), cfg.train.min_std)
        span = (jnp.array(r.upper) - jnp.array(r.lower)) / 8
        home = jnp.array(r.home)
        return norm._replace(act_mean=home, act_std=jnp.minimum(span, 1.0))

    def absorb_logs(self, ck: Checkpointed) -> Checkpointed:
        """Robot practice closes the loop: relabel the logs in cfg.data, append them to the
        cache (saved with the next checkpoint), so the resumed run trains on them. A directory
        already absorbed by this run (recorded in its checkpoints) is not added twice."""
        cfg = self.cfg
        new = [d for d in cfg.data if os.path.abspath(d) not in self._absorbed]
        if len(new) < len(cfg.data):
            self.log(f"[ttmjx] already in the cache, not added again: "
                     f"{', '.join(d for d in cfg.data if d not in new)}")
        if not new:
            return ck
        logs = load_logs(new, cfg.world.horizon)
        cache = add_episodes(ck.cache, jax.tree.map(jnp.asarray, record.to_numpy(logs)), cfg.world.table,
                             cfg.train.goal_margin)
        self.log(f"[ttmjx] added {int(cache.count - ck.cache.count)} of {logs.size} logged episodes "
                 f"from {', '.join(new)} to the cache")
        self._absorbed += [os.path.abspath(d) for d in new]
        return ck._replace(cache=cache, counters=ck.counters._replace(
            trajectories=ck.counters.trajectories + logs.size))

    def template(self) -> Checkpointed:
        """Shapes and dtypes of a checkpoint (values unused)."""
        from models.normalizer import identity_normalizer
        cfg = self.cfg
        norm = identity_normalizer(cfg.policy.obs_size)
        state = init_train_state(jax.random.PRNGKey(0), cfg.policy, cfg.train, norm)
        return Checkpointed(state, empty_cache(cfg.train.capacity, cfg.world.horizon),
                            jnp.zeros(2, jnp.uint32), Counters(jnp.int32(0), jnp.int32(0), jnp.int32(0)))

    def save(self, ck: Checkpointed):
        from training import checkpoint
        checkpoint.save(self.ckpt_dir, int(ck.counters.iteration), ck,
                        {**config_dict(self.cfg), "absorbed_data": self._absorbed}, keep=self.cfg.keep_checkpoints)

    def restore(self) -> Checkpointed | None:
        from training import checkpoint
        if not checkpoint.steps(self.ckpt_dir):
            return None
        ck, saved = checkpoint.restore(self.ckpt_dir, self.template())
        mine = config_dict(self.cfg)
        diff = {k for k in set(saved) | set(mine) if saved.get(k) != mine.get(k) and k not in RESUME_MAY_CHANGE}
        if diff:
            raise ValueError(f"{self.cfg.run_dir} holds a run with a different config (fields {sorted(diff)}); "
                             f"resume with the same config or choose a new run_dir")
        self._absorbed = list(saved.get("absorbed_data", []))
        return ck

    # -- signals ---------------------------------------------------------------------------
    def _install_signals(self):
        def handler(signum, frame):
            if self._stop:  # a second Ctrl-C: stop now (the last checkpoint stays)
                raise KeyboardInterrupt
            self._stop = True
            self.log(f"\n[ttmjx] {signal.Signals(signum).name}: finishing this iteration, saving a checkpoint, "
                     f"then exiting (resume with the same command)")
        self._old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}

    def _restore_signals(self):
        for s, h in getattr(self, "_old", {}).items():
            signal.signal(s, h)

    # -- metrics ---------------------------------------------------------------------------
    def _write_metrics(self, row: dict):
        with open(self.metrics_path, "a") as f:
            f.write(json.dumps(row) + "\n")
        if self._writer is None:
            try:
                from tensorboardX import SummaryWriter
                self._writer = SummaryWriter(os.path.join(self.cfg.run_dir, "tensorboard"))
            except Exception:  # TensorBoard logs are a convenience, never a reason to stop
                self._writer = False
        if self._writer:
            for k, v in row.items():
                if isinstance(v, (int, float)) and k not in ("trajectories", "iteration") and math.isfinite(v):
                    self._writer.add_scalar(k, v, row["trajectories"])
            self._writer.flush()

    def _truncate_metrics(self, iteration: int):
        """Drop metric rows of iterations after the restored checkpoint (they will be redone)."""
        if not os.path.exists(self.metrics_path):
            return
        rows = [json.loads(line) for line in open(self.metrics_path) if line.strip()]
        with open(self.metrics_path, "w") as f:
            for r in rows:
                if r["iteration"] < iteration:
                    f.write(json.dumps(r) + "\n")

    def evaluate(self, params, key) -> dict:
        from eval.evaluate import evaluate_params
        return evaluate_params(self.cfg.world, self.cfg.policy, params, self.backend, key, self.cfg.eval_goals,
                               members=self.cfg.train.members)

    # -- the loop --------------------------------------------------------------------------
    def run(self, max_iterations: int | None = None) -> dict:
        """Train to the end (or `max_iterations` more iterations); returns the last metrics."""
        cfg = self.cfg
        os.makedirs(cfg.run_dir, exist_ok=True)
        ck = self.restore()
        if ck is None:
            write_config(cfg)
            ck = self.initial()
            self.save(ck)
            open(self.metrics_path, "w").close()
        else:
            self.log(f"[ttmjx] resuming {cfg.run_dir} at iteration {int(ck.counters.iteration)}")
            self._truncate_metrics(int(ck.counters.iteration))
            if cfg.data:
                ck = self.absorb_logs(ck)
        n_pre, n_tot = pretrain_iterations(cfg), total_iterations(cfg)
        base = jnp.asarray(ck.key)
        last = {}
        bar = self._bar(ck)
        self._install_signals()
        try:
            start = int(ck.counters.iteration)
            stop_at = n_tot if max_iterations is None else min(n_tot, start + max_iterations)
            for it in range(start, stop_at):
                t0 = time.perf_counter()
                practise = it >= n_pre and cfg.practice
                key = jax.random.fold_in(base, it)
                throws = self.practice.round_throws(base, it) if practise else None
                state, cache, loss, stats = self.practice.iteration(ck.state, ck.cache, key, throws)
                new_traj = cfg.episodes_per_ssp if practise else 0
                ck = Checkpointed(state, cache, ck.key, Counters(
                    jnp.int32(it + 1), ck.counters.trajectories + new_traj,
                    ck.counters.updates + (cfg.steps_between_ssp if self.practice.train_loop else 0)))
                row = {"iteration": it, "phase": "practice" if practise else ("pretrain" if it < n_pre else "lfp"),
                       "trajectories": int(ck.counters.trajectories), "updates": int(ck.counters.updates),
                       "cache_size": int(cache.size), "loss": float(np.mean(loss)),
                       "seconds": time.perf_counter() - t0}
                if stats is not None:
                    row.update({f"practice_{k}": float(v) for k, v in stats._asdict().items()})
                if is_eval_iteration(cfg, it):
                    row.update({f"eval_{k}": v for k, v in self.evaluate(acting_params(state), jax.random.fold_in(base, 10**6 + it)).items()})
                    last = row
                if (it + 1) % cfg.checkpoint_every == 0 or it + 1 == stop_at or self._stop:
                    self.save(ck)
                self._write_metrics(row)
                bar.update(new_traj if practise else 0)
                bar.set_postfix_str(_postfix(row))
                if self._stop:
                    self.log(f"[ttmjx] saved checkpoint at iteration {it + 1} in {self.ckpt_dir}")
                    break
        finally:
            bar.close()
            self._restore_signals()
            if self._writer:
                self._writer.close()
        plot_curves(self.metrics_path, os.path.join(cfg.run_dir, "learning_curve.png"))
        return {"run_dir": cfg.run_dir, "iteration": int(ck.counters.iteration),
                "trajectories": int(ck.counters.trajectories), "finished": int(ck.counters.iteration) >= n_tot,
                **{k: v for k, v in last.items() if k.startswith("eval_")}}

    def _bar(self, ck):
        from tqdm import tqdm
        total = self.cfg.total_trajectories if self.cfg.practice else max(self.cfg.demos, 1)
        return tqdm(total=total, initial=int(ck.counters.trajectories), unit="traj", disable=not self.progress,
                    file=sys.stderr, dynamic_ncols=True)


def _postfix(row: dict) -> str:
    s = f"it {row['iteration']} loss {row['loss']:.3f}"
    if "eval_within_30cm" in row:
        s += f" | eval <=30cm {row['eval_within_30cm']:.0%} <=20cm {row['eval_within_20cm']:.0%}"
    return s


# Fields that may differ when resuming (they do not change the computation).
RESUME_MAY_CHANGE = {"run_dir", "data", "keep_checkpoints", "total_trajectories", "checkpoint_every",
                     "absorbed_data"}


def config_dict(cfg: RunConfig) -> dict:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def write_config(cfg: RunConfig):
    with open(os.path.join(cfg.run_dir, "config.json"), "w") as f:
        json.dump(config_dict(cfg), f, indent=2)


def plot_curves(metrics_path: str, png: str) -> str | None:
    """Learning curves against total trajectories (demonstrations + practice)."""
    if not os.path.exists(metrics_path):
        return None
    rows = [json.loads(line) for line in open(metrics_path) if line.strip()]
    ev = [r for r in rows if "eval_within_30cm" in r]
    if not ev:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    x = [r["trajectories"] for r in ev]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    a.plot(x, [100 * r["eval_within_30cm"] for r in ev], "o-", label="<= 30 cm")
    a.plot(x, [100 * r["eval_within_20cm"] for r in ev], "s-", label="<= 20 cm")
    a.plot(x, [100 * r["eval_hit_rate"] for r in ev], ":", color="gray", label="hit rate")
    a.set_xlabel("total trajectories (demonstrations + practice)"), a.set_ylabel("% of balls")
    a.legend(), a.grid(alpha=0.3)
    b.plot(x, [r["eval_mean_dist"] for r in ev], "o-", color="C2")
    b.set_xlabel("total trajectories"), b.set_ylabel("mean distance to goal (m)"), b.grid(alpha=0.3)
    fig.suptitle(os.path.basename(os.path.dirname(os.path.abspath(metrics_path))))
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
