"""The GoalsEye run: demonstrations -> relabeled cache -> GCBC pretraining (the LFP point) ->
self-supervised practice rounds -> evaluation, with checkpoints that resume exactly.

`Run` composes the parts, each in its own module: the starting data (training.pool), the
updates and practice rounds (training.practice), the evaluation it is GIVEN (a function, so
training never imports eval), the log (training.runlog) and the checkpoints (training.checkpoint).
The run's devices (training.mesh, cfg.devices) are laid out before anything is compiled; the
state is placed on them when it is made or restored, whatever the devices that saved it.

Every random draw of iteration i comes from fold_in(seed key, i), and the state is saved at
iteration boundaries, so a run killed at any point and resumed ends with the same parameters,
bit for bit, as an uninterrupted one (on a CPU, where the arithmetic is deterministic).
"""
from __future__ import annotations

import json
import math
import os
import sys
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from training import budget, checkpoint, mesh, pool, runlog
from training.checkpoint import Checkpointed, Counters
from training.practice import Practice, stats_row
from training.runconfig import BOOKKEEPING, RunConfig, from_json, to_json
from training.update import acting_params, init_train_state
from ttmjx.commandline import install_stop_signals, restore_signals
from ttmjx.tools.demos import renamed
from ttmjx.world import files
from ttmjx.world.backends import Backend, resolve_backend

# evaluate(params, backend, key) -> {"within_30cm": ..., ...}: eval.evaluate.training_evaluation
Evaluate = Callable[..., dict]

# Fields that may differ when resuming (they do not change the computation).
RESUME_MAY_CHANGE = {"run_dir", "data", "keep_checkpoints", "total_trajectories", "checkpoint_every",
                     "absorbed_data", "checkpoint_format", "cache_rows", "devices"}


# -- schedule -------------------------------------------------------------------------------
def pretrain_iterations(cfg: RunConfig) -> int:
    return math.ceil(cfg.pretrain_steps / cfg.steps_between_ssp) if cfg.pretrain_steps else 0


def practice_iterations(cfg: RunConfig) -> int:
    """Practice rounds until total_trajectories (demonstrations + practice) are reached; with
    practice off (LFP) the same number of train-only rounds, so step counts match."""
    return max(0, math.ceil((cfg.total_trajectories - cfg.demos) / cfg.episodes_per_ssp))


def round_episodes(cfg: RunConfig, it: int) -> int:
    """Practice episodes iteration `it` adds to the run's trajectories: episodes_per_ssp, except
    in the last round, which adds what is left of total_trajectories, so the budget is met
    exactly (120,000 means 120,000); 0 outside practice."""
    k = it - pretrain_iterations(cfg)
    if not cfg.practice or k < 0 or k >= practice_iterations(cfg):
        return 0
    return min(cfg.episodes_per_ssp, cfg.total_trajectories - cfg.demos - k * cfg.episodes_per_ssp)


def total_iterations(cfg: RunConfig) -> int:
    return pretrain_iterations(cfg) + practice_iterations(cfg)


def is_checkpoint_iteration(cfg: RunConfig, it: int, stop_at: int) -> bool:
    """Save after iteration `it`: every checkpoint_every iterations and at the last one run."""
    return (it + 1) % cfg.checkpoint_every == 0 or it + 1 == stop_at


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


def phase(cfg: RunConfig, it: int) -> str:
    n_pre = pretrain_iterations(cfg)
    if it < n_pre:
        return "pretrain"
    return "practice" if cfg.practice else "lfp"


def write_config(cfg: RunConfig):
    files.write_json(os.path.join(cfg.run_dir, "config.json"), to_json(cfg))


SEEDS_FILE = "seeds.json"   # in the directory of a batch of seeds (training.seeds): its seeds and run directories


def check_not_seed_parent(run_dir: str) -> None:
    """A single run cannot live in the directory of a batch of seeds (their runs are inside it)."""
    if os.path.exists(os.path.join(run_dir, SEEDS_FILE)):
        raise ValueError(f"{run_dir} holds a batch of seeds ({SEEDS_FILE}); train it with the same --seeds, "
                         f"or choose another --run-dir")


class NonFiniteError(RuntimeError):
    """Training produced a non-finite loss or parameters: the run stops, nothing is saved."""


@jax.jit
def finite_flags(loss, params, ema):
    """[3] bool: loss, parameters and moving average all finite (one compiled reduction)."""
    return jnp.stack([jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(t)]))
                      for t in (loss, params, ema)])


def check_finite(state, loss, it: int, last_saved: int):
    """Raise NonFiniteError if the loss [N] or any parameter of `state` is NaN or infinite."""
    ok = np.asarray(finite_flags(loss, state.params.net, state.ema.net))
    bad = [name for name, fine in zip(("loss", "parameters", "moving average"), ok) if not fine]
    if bad:
        raise NonFiniteError(f"iteration {it}: non-finite {' and '.join(bad)} (learning rate too high, or "
                             f"non-finite data?); stopped without saving: the last good checkpoint is "
                             f"iteration {last_saved}")


# -- the run -------------------------------------------------------------------------------
def check_same_config(cfg: RunConfig, saved: dict) -> None:
    """ValueError if `saved` (a run directory's config) computes differently from `cfg`: the
    run in cfg.run_dir cannot be resumed with it."""
    mine = to_json(cfg)
    if "demo_source" in saved:   # an old name ("scripted") means today's "oracle"
        saved = {**saved, "demo_source": renamed(saved["demo_source"])}
    try:   # fields added since the run was saved read as their defaults, which compute as before
        saved = {**saved, **to_json(from_json(saved))}
    except (TypeError, KeyError, ValueError):
        pass
    diff = {k for k in set(saved) | set(mine) if saved and saved.get(k) != mine.get(k) and k not in RESUME_MAY_CHANGE}
    if diff:
        raise ValueError(f"{cfg.run_dir} holds a run with a different config (fields {sorted(diff)}); "
                         f"resume with the same config or choose a new run_dir")


class DamagedRun(RuntimeError):
    """A file of a run directory being resumed that is there but unreadable (exit 1: a fault of
    the disk or of whatever wrote it, not of the command)."""


class Run:
    """A training run in cfg.run_dir: fresh or resumed. `evaluate` (params, backend, key) -> dict
    is called at the evaluation iterations; None skips evaluation."""

    def __init__(self, cfg: RunConfig, evaluate: Evaluate | None = None, progress: bool = True, log=print,
                 shared: tuple[Backend, mesh.Layout] | None = None):
        """`shared` (backend, layout): this run is one seed of a training.seeds.SeedRuns, which
        computes for it; the run keeps its directory, log and checkpoints."""
        self.cfg, self.evaluate, self.progress, self.log = cfg, evaluate, progress, log
        if shared is None:
            check_not_seed_parent(cfg.run_dir)
            self.layout = mesh.make_layout(cfg)  # refuse what cannot be placed or fit before anything is compiled
            budget.check_fits(cfg)
            self.backend = Backend(cfg.world, resolve_backend(cfg.backend))
            self.practice = Practice(cfg.world, cfg.policy, cfg.train, self.backend,
                                     cfg.episodes_per_ssp, cfg.steps_between_ssp, self.layout)
        else:
            (self.backend, self.layout), self.practice = shared, None
        self.ckpt_dir = os.path.join(cfg.run_dir, "checkpoints")
        # With several processes, process 0 writes the run's log; the others keep their own
        # beside it (the same rows: one writer per file).
        self.log_dir = cfg.run_dir if mesh.is_primary() else os.path.join(cfg.run_dir, f"process{jax.process_index()}")
        self.metrics = runlog.MetricsLog(self.log_dir)
        self._stop = 0                   # the signal that asked the run to stop (0: none)
        self.saved_at = -1               # iteration of the newest checkpoint written or restored
        self._absorbed: list[str] = []   # robot log directories already in the cache (absolute)

    # -- data --------------------------------------------------------------------------------
    def initial(self) -> Checkpointed:
        """The state at iteration 0: the starting pool and freshly initialized members."""
        cfg = self.cfg
        key = jax.random.PRNGKey(cfg.seed)
        logs = pool.load_logs(cfg.data, cfg.world.horizon, cfg.world) if cfg.data else None
        self._absorbed = [os.path.abspath(d) for d in cfg.data]
        cache, norm, seen = pool.starting_pool(cfg, pool.load_demos(cfg, self.progress), logs, self.backend, key)
        state = init_train_state(jax.random.fold_in(key, 1), cfg.policy, cfg.train, norm)
        return self.place(Checkpointed(state, cache, key, checkpoint.zero_counters(seen)))

    def place(self, ck: Checkpointed) -> Checkpointed:
        """`ck` on this run's devices (checkpoint.sharding)."""
        return self.layout.put(ck, checkpoint.sharding(self.layout))

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
        logs = pool.load_logs(new, cfg.world.horizon, cfg.world)
        cache = pool.append_record(ck.cache, logs, cfg)
        self.log(f"[ttmjx] added {int(cache.count - ck.cache.count)} of {logs.size} logged episodes "
                 f"from {', '.join(new)} to the cache")
        self._absorbed += [os.path.abspath(d) for d in new]
        return ck._replace(cache=self.layout.put(cache, self.layout.replicated), counters=ck.counters._replace(
            trajectories=ck.counters.trajectories + logs.size))

    # -- checkpoints -------------------------------------------------------------------------
    def save(self, ck: Checkpointed):
        checkpoint.save(self.ckpt_dir, int(ck.counters.iteration), ck,
                        {**to_json(self.cfg), "absorbed_data": self._absorbed}, keep=self.cfg.keep_checkpoints)
        self.saved_at = int(ck.counters.iteration)

    def restore(self) -> Checkpointed | None:
        """The newest intact checkpoint of this run directory (None if there is none), refused
        if it was written with a configuration that computes differently. Damaged newer
        checkpoints are deleted (after that check) and redone."""
        if not checkpoint.steps(self.ckpt_dir):
            return None
        try:
            loaded = checkpoint.load_checkpoint(self.ckpt_dir, warn=self.log)
        except checkpoint.NoIntactCheckpoint as e:   # every save was interrupted or corrupted
            self.check_same_config(self.saved_config())
            self.log(f"[ttmjx] {e}; starting the run afresh")
            checkpoint.discard(self.ckpt_dir, e.skipped)
            return None
        self.check_same_config(loaded.meta)
        self.repair_config(loaded)
        checkpoint.discard(self.ckpt_dir, loaded.skipped)
        self._absorbed = list(loaded.meta.get("absorbed_data", []))
        self.saved_at = loaded.step
        return self.place(loaded.ck)   # restored on one device, whatever the devices that saved it

    def rewind(self, step: int) -> Checkpointed:
        """The state of this run's checkpoint `step` (older than its newest), its log cut back
        to it: so the seeds of a batch that a crash left one save apart start level again."""
        try:
            loaded = checkpoint.load_checkpoint(self.ckpt_dir, step)
        except FileNotFoundError as e:
            raise ValueError(f"{self.cfg.run_dir}: cannot go back to iteration {step}, where the other seeds of "
                             f"its batch are ({e}); raise keep_checkpoints or delete the batch's runs") from None
        self.metrics.truncate(step)
        self.saved_at = step
        return self.place(loaded.ck)

    def saved_config(self) -> dict:
        """The run directory's config.json ({} if it has none)."""
        path = os.path.join(self.cfg.run_dir, "config.json")
        if not os.path.exists(path):
            return {}
        try:
            with open(path) as f:
                saved = json.load(f)
        except ValueError as e:
            raise ValueError(f"{path}: not valid JSON ({e}); restore it, or delete it to resume with this "
                             f"command's config (the checkpoints carry their own)") from None
        if not isinstance(saved, dict):
            raise ValueError(f"{path}: not a JSON object; restore it or delete it")
        return saved

    def repair_config(self, loaded: checkpoint.Loaded) -> None:
        """A resumed run's config.json, missing, empty, invalid or at odds with the checkpoint
        it resumes from (in a field that changes the computation), is rewritten from the config
        saved inside that checkpoint, and said on stderr: never left broken."""
        path = os.path.join(self.cfg.run_dir, "config.json")
        intact = {k: v for k, v in loaded.meta.items() if k not in BOOKKEEPING}
        why = None
        if not os.path.exists(path):
            why = "missing"
        else:
            try:
                with open(path) as f:
                    saved = json.load(f)
            except (OSError, ValueError) as e:
                why = "empty" if os.path.getsize(path) == 0 else f"not valid JSON ({e})"
            else:
                if not isinstance(saved, dict):
                    why = f"not a JSON object (a {type(saved).__name__})"
                else:
                    diff = sorted(k for k in set(saved) | set(intact)
                                  if saved.get(k) != intact.get(k) and k not in RESUME_MAY_CHANGE)
                    why = f"at odds with the checkpoint in {', '.join(diff)}" if diff else None
        if why and mesh.is_primary():
            files.write_json(path, intact)
            print(f"[ttmjx] {path}: {why}; rewritten from the config saved in checkpoint {loaded.step}",
                  file=sys.stderr, flush=True)

    def check_demos(self) -> None:
        """A resumed run's own demonstrations (RUN/demos, collected at its start; its checkpoints
        hold them in the pool) read whole: a damaged file is a DamagedRun naming it, not left for
        a restart from scratch (or `ttmjx report`) to find."""
        from ttmjx.world import record
        path = os.path.join(self.cfg.run_dir, "demos")
        if self.cfg.demo_dir or not os.path.exists(os.path.join(path, "trajectories.npz")):
            return
        try:
            record.load(path)
        except record.RecordError as e:
            raise DamagedRun(f"{e}; this run's checkpoints hold its demonstrations: restore the file, or delete "
                             f"{path} and run the same command to resume without it") from None

    def check_same_config(self, saved: dict):
        """ValueError if `saved` (a run's config) computes differently from this run's."""
        check_same_config(self.cfg, saved)

    def start(self) -> Checkpointed:
        """A fresh run (config, initial state, empty log) or the resumed one."""
        cfg = self.cfg
        os.makedirs(self.log_dir, exist_ok=True)
        ck = self.restore()
        if ck is None:
            old_rows = self.metrics.rows()
            if old_rows:
                raise ValueError(f"{cfg.run_dir}: checkpoints/ holds no checkpoint but metrics.jsonl has "
                                 f"{len(old_rows)} rows of an earlier run; restore checkpoints/ or choose a new "
                                 f"--run-dir (the old metrics are kept, not overwritten)")
            if mesh.is_primary():
                write_config(cfg)
            ck = self.initial()
            self.save(ck)
            self.metrics.start()
            return ck
        self.check_demos()
        it = int(ck.counters.iteration)
        self.log(f"[ttmjx] resuming {cfg.run_dir} at iteration {it}")
        existed = os.path.exists(self.metrics.path)
        self.metrics.truncate(it)
        if self.metrics.torn:
            self.log(f"[ttmjx] {self.metrics.path}: its last line was cut short ({len(self.metrics.torn)} bytes, a crash "
                     f"mid-write) and is dropped; the rows up to the checkpoint are kept and the rest is redone")
        kept = {r.get("iteration") for r in self.metrics.rows()}
        lost = [i for i in range(it) if i not in kept]
        if lost and mesh.is_primary():
            print(f"[ttmjx] warning: {self.metrics.path}: {'missing' if not existed else 'incomplete'}; the rows of "
                  f"{len(lost)} of the {it} iterations before the checkpoint are lost (iterations "
                  f"{lost[0]}-{lost[-1]}; no checkpoint keeps them), so its learning curve starts after them",
                  file=sys.stderr, flush=True)
        return self.absorb_logs(ck) if cfg.data else ck

    # -- one iteration -----------------------------------------------------------------------
    def step(self, ck: Checkpointed, it: int) -> tuple[Checkpointed, dict]:
        """Iteration `it` (pretraining chunk, practice round or LFP round) -> (state, metrics row)."""
        cfg, t0 = self.cfg, _now()
        practise = phase(cfg, it) == "practice"
        # The keys derive from a host copy: uncommitted to any device, they go wherever the
        # computation that uses them runs (the mesh, or one device for the host physics).
        base = np.asarray(ck.key)
        throws = self.practice.round_throws(base, it) if practise else None
        new_traj = round_episodes(cfg, it)
        state, cache, loss, stats = self.practice.iteration(ck.state, ck.cache, jax.random.fold_in(base, it), throws,
                                                            new_traj)
        check_finite(state, loss, it, self.saved_at)
        counters = Counters(np.int32(it + 1), np.int32(int(ck.counters.trajectories) + new_traj),
                            np.int32(int(ck.counters.updates) + (cfg.steps_between_ssp if self.practice.train_loop else 0)))
        ck = Checkpointed(state, cache, ck.key, self.layout.put(counters, self.layout.replicated))
        row = {"iteration": it, "phase": phase(cfg, it), "trajectories": int(ck.counters.trajectories),
               "updates": int(ck.counters.updates), "cache_size": int(cache.size), "loss": float(np.mean(loss)),
               "seconds": _now() - t0}
        if stats is not None:
            row.update(stats_row(stats._asdict()))
        if self.evaluate is not None and is_eval_iteration(cfg, it):
            metrics = self.evaluate(self.layout.local(acting_params(state)), self.backend,
                                    jax.random.fold_in(base, 10**6 + it))
            row.update({f"eval_{k}": v for k, v in metrics.items()})
        return ck, row

    # -- the loop ----------------------------------------------------------------------------
    def run(self, max_iterations: int | None = None) -> dict:
        """Train to the end (or `max_iterations` more iterations); returns the last metrics."""
        cfg = self.cfg
        ck = self.start()
        n_tot = total_iterations(cfg)
        start = int(ck.counters.iteration)
        stop_at = n_tot if max_iterations is None else min(n_tot, start + max_iterations)
        total = cfg.total_trajectories if cfg.practice else max(cfg.demos, 1)
        bar = runlog.progress_bar(total, int(ck.counters.trajectories), self.progress)
        last = {}
        install_stop_signals(self)     # SIGINT/SIGTERM: this iteration finishes, saves, returns
        try:
            for it in range(start, stop_at):
                before = int(ck.counters.trajectories)
                ck, row = self.step(ck, it)
                last = row if any(k.startswith("eval_") for k in row) else last
                self.metrics.write(row)
                if is_checkpoint_iteration(cfg, it, stop_at) or self._stop:
                    self.save(ck)
                bar.update(int(ck.counters.trajectories) - before)
                bar.set_postfix_str(runlog.postfix(row))
                if self._stop:
                    self.log(f"[ttmjx] saved checkpoint at iteration {it + 1} in {self.ckpt_dir}")
                    break
        finally:
            bar.close()
            restore_signals(self)
            self.metrics.close()
        runlog.plot_curves(self.metrics.path, os.path.join(self.log_dir, "learning_curve.png"))
        return {"run_dir": cfg.run_dir, "iteration": int(ck.counters.iteration),
                "trajectories": int(ck.counters.trajectories), "finished": int(ck.counters.iteration) >= n_tot,
                "stopped_by_signal": self._stop,
                **{k: v for k, v in last.items() if k.startswith("eval_")}}


def _now() -> float:
    import time
    return time.perf_counter()
