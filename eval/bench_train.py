"""`ttmjx bench --train PRESET [--seeds N]`: where the time of a training round goes.

The pieces of one round of S seeds trained as one program (training/seeds.py), each timed
after a first call that compiles it: the practice rollout, relabel + insert into the pools,
the S updates, the whole round as training runs it (on MJX one compiled program), and the
evaluation. From them: trajectories and updates per second, compile time, peak device memory
and the projected wall time of the preset's whole run: the process's start (interpreter and
imports), its setup as the run does it (the demonstrations collected, the starting states built
and saved), its schedule of pretraining chunks and practice rounds, each timed as the run steps
it (training.trainer.Run.step: throws, the compiled round, the checks, the metrics), the blocks
of throws solved, its evaluations as the run calls them (with the held-out loss; the first also
collects the held-out demonstrations), and its checkpoints (a save timed on the starting pool;
later saves write fuller pools).
"""
from __future__ import annotations

import dataclasses
import os
import resource
import shutil
import statistics
import tempfile
import time

import jax
import numpy as np

from eval.evaluate import training_evaluation
from training.cache import add_episodes
from training.checkpoint import Checkpointed
from training.practice import THROW_BLOCK, practice_policy
from training.runconfig import preset
from training.schedule import (is_checkpoint_iteration, is_eval_iteration, practice_iterations, pretrain_iterations,
                               total_iterations)
from training.seeds import seed_configs
from training.trainer import Run
from training.update import acting_params
from ttmjx.world.env import uniform_goals


def timed(fn, reps: int) -> tuple[float, float, object]:
    """(seconds of the first call, median seconds of `reps` more, the last result)."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), out


def process_age_s() -> float:
    """Seconds since this process started (Linux: /proc), so that the projection counts the
    interpreter's start and the imports the real command pays too; 0 where unknown."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = float(f.read().rsplit(")", 1)[1].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(uptime - start_ticks / os.sysconf("SC_CLK_TCK"), 0.0)
    except (OSError, ValueError, IndexError):
        return 0.0


def peak_memory() -> dict:
    """Peak bytes on the device (accelerators report it) and this process's peak resident set."""
    stats = jax.local_devices()[0].memory_stats() or {}
    out = {"peak_host_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20}
    if "peak_bytes_in_use" in stats:
        out["peak_device_gib"] = stats["peak_bytes_in_use"] / 2 ** 30
    return out


def bench_training(name: str, seeds: int = 1, reps: int = 2, demos: int | None = None, backend: str | None = None,
                   log=print, mjx_impl: str = "jax") -> dict:
    """The round of preset `name` with `seeds` seeds in one program -> figures (seconds, rates;
    `throws_block_s` solves the throws of THROW_BLOCK rounds, once per that many rounds).
    `demos` caps the demonstrations collected (None: the preset's, so that the setup is timed as
    the run does it); `mjx_impl` is the world's MJX implementation (jax or warp)."""
    scratch = tempfile.mkdtemp(prefix="ttmjx-bench-")   # the seeds' demonstrations; removed at the end
    try:
        return _bench(name, seeds, reps, demos, backend, log, scratch, mjx_impl)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def _bench(name: str, seeds: int, reps: int, demos: int | None, backend: str | None, log, scratch: str,
           mjx_impl: str = "jax") -> dict:
    cfg = preset(name)
    cfg = dataclasses.replace(cfg, world=dataclasses.replace(cfg.world, mjx_impl=mjx_impl),
                              demos=min(cfg.demos, demos) if demos and cfg.demos else cfg.demos,
                              backend=backend or cfg.backend, run_dir=os.path.join(scratch, name))
    t0 = time.perf_counter()
    runs = Run(seed_configs(cfg, seeds), progress=False, log=log)   # one seed: a batch of one, as `ttmjx train`
    ck = jax.block_until_ready(runs.start())   # as the run starts: demonstrations, states, first saves
    setup_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    runs.save(ck._replace(counters=ck.counters._replace(iteration=ck.counters.iteration + 1)))
    save_s = time.perf_counter() - t0
    pr, be, w, m = runs.practice, runs.backend, cfg.world, cfg.episodes_per_ssp
    n_pre, n_prac, n_tot = pretrain_iterations(cfg), practice_iterations(cfg), total_iterations(cfg)
    out = {"preset": name, "seeds": seeds, "backend": be.name, "episodes_per_round": m * seeds,
           "updates_per_round": cfg.steps_between_ssp * seeds, "startup_s": process_age_s() - setup_s - save_s,
           "setup_s": setup_s, "save_s": save_s, "device": be.kind.device()}

    def piece(label: str, fn):
        first, steady, res = timed(fn, reps)
        out[f"{label}_s"], out[f"{label}_first_call_s"] = steady, first
        log(f"[bench] {label}: {steady:.3f} s per call ({first:.1f} s first call)")
        return res

    # The projection's pieces, first and in the run's order (its compiles share autotuning with
    # what ran before them): an iteration of each phase as Run.step plays it (throws, the
    # compiled round, the finiteness check, the metrics to the host), then the evaluation as
    # the run calls it (its first call collects the held-out demonstrations).
    # Each call goes on from the last one's state: a round's physics costs more for a policy that
    # has learnt to reach the ball (its contacts) than for the untrained start.
    evaluate = training_evaluation([r.cfg for r in runs.runs], heldout=True)   # as `ttmjx train` evaluates
    latest = [ck]

    def step_on(it: int) -> Checkpointed:
        latest[0] = runs.step(latest[0], it)[0]
        return latest[0]
    if n_pre:
        piece("pretrain_step", lambda: step_on(0))
    if n_prac:
        piece("practice_step", lambda: step_on(n_pre))
    ck = latest[0]                      # the pieces below from the stepped state too
    base = np.asarray(ck.key)
    keys = jax.vmap(jax.random.fold_in, in_axes=(0, None))(base, 0)
    params = acting_params(ck.state)
    piece("evaluation", lambda: evaluate(params, be, keys))

    # Where a round's time goes, piece by piece (not in the projection)
    blocks = iter(range(1, reps + 2))   # a new block of rounds each call: the solve is not cached
    piece("throws_block", lambda: pr.round_throws(base, THROW_BLOCK * next(blocks)))
    throws = pr.round_throws(base, 0)
    goals = jax.vmap(lambda k: uniform_goals(k, m, w.table, cfg.train.practice_goal_margin))(keys)
    policy = practice_policy(cfg.policy, cfg.train)
    traj = piece("rollout", lambda: be.rollout(policy, params, keys, throws, goals, members=cfg.train.members))
    append = jax.jit(jax.vmap(lambda c, t: add_episodes(c, t, w.table, cfg.train.practice_keep_margin)))
    cache = piece("relabel_insert", lambda: append(ck.cache, jax.tree.map(jax.numpy.asarray, traj)))
    if pr.train_loop is not None:
        piece("updates", lambda: pr.train_loop(ck.state, cache, keys))
    piece("round", lambda: pr.iteration(ck.state, ck.cache, keys, throws))
    del cache, traj

    n_eval = sum(is_eval_iteration(cfg, i) for i in range(n_tot))
    n_save = sum(is_checkpoint_iteration(cfg, i, n_tot) for i in range(n_tot))
    # the first call of each step solved one block of throws; the run solves one per THROW_BLOCK rounds
    n_blocks = len({i // THROW_BLOCK for i in range(n_pre, n_tot)}) if n_prac else 0
    steps = [(p, n) for p, n in (("pretrain_step", n_pre), ("practice_step", n_prac)) if n]
    compile_s = sum(max(out[f"{p}_first_call_s"] - out[f"{p}_s"], 0.0) for p in [p for p, _ in steps] + ["evaluation"])
    per_round = out["practice_step_s"] if n_prac else out["round_s"]
    out.update({
        "trajectories_per_s": m * seeds / per_round,
        "updates_per_s": cfg.steps_between_ssp * seeds / per_round if cfg.practice else 0.0,
        "compile_s": compile_s,
        "schedule": {"pretrain_chunks": n_pre, "practice_rounds": n_prac, "evaluations": n_eval,
                     "checkpoints": n_save, "throw_blocks": n_blocks, "total_trajectories": cfg.total_trajectories},
        "projected_run_s": out["startup_s"] + setup_s + compile_s + sum(n * out[f"{p}_s"] for p, n in steps)
                           + max(n_blocks - 1, 0) * out["throws_block_s"] + n_eval * out["evaluation_s"]
                           + n_save * save_s,
        **peak_memory()})
    return out
