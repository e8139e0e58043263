"""One run's directory: config.json, metrics.jsonl, Orbax checkpoints that resume exactly, the
demonstrations it started from and the robot logs it absorbed (docs/DATA.md).

`RunDir` is the bookkeeping of one run, whatever program trains it (training.trainer.Run trains
every run as a lane of a program over lanes; one seed is a batch of one). It makes the run's
starting state (the starting pool and freshly initialized members), restores the newest intact
checkpoint (refused if it computes differently), rewinds to an older one, and repairs a damaged
config.json from the checkpoint's own copy.
"""
from __future__ import annotations

import json
import os
import sys

import jax

from training import checkpoint, pool, runlog
from training.checkpoint import Checkpointed
from training.runconfig import BOOKKEEPING, RunConfig, from_json, to_json
from training.update import init_train_state
from ttmjx.tools.demos import renamed
from ttmjx.world import files
from ttmjx.world.backends import Backend

# Fields that may differ when resuming (they do not change the computation).
RESUME_MAY_CHANGE = {"run_dir", "data", "keep_checkpoints", "total_trajectories", "checkpoint_every",
                     "absorbed_data", "checkpoint_format", "cache_rows", "devices"}


def write_config(cfg: RunConfig):
    files.write_json(os.path.join(cfg.run_dir, "config.json"), to_json(cfg))


SEEDS_FILE = "seeds.json"   # in the directory of a batch of seeds (training.seeds): its seeds and run directories


def check_not_seed_parent(run_dir: str) -> None:
    """A single run cannot live in the directory of a batch of seeds (their runs are inside it)."""
    if os.path.exists(os.path.join(run_dir, SEEDS_FILE)):
        raise ValueError(f"{run_dir} holds a batch of seeds ({SEEDS_FILE}); train it with the same --seeds, "
                         f"or choose another --run-dir")


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


class RunDir:
    """One run's directory (cfg.run_dir): its config, metrics, checkpoints, demonstrations and
    resume, fresh or resumed. It computes nothing but the run's starting state: training.trainer.Run
    trains it as a lane of its program, on `device` (None: the default device), with `backend`'s
    physics; the run keeps its directory, log and checkpoints, whatever the program."""

    def __init__(self, cfg: RunConfig, backend: Backend, device=None, progress: bool = True, log=print):
        self.cfg, self.backend, self.progress, self.log = cfg, backend, progress, log
        self.device = device if device is not None else jax.local_devices()[0]   # where its state is built
        self.ckpt_dir = os.path.join(cfg.run_dir, "checkpoints")
        self.log_dir = cfg.run_dir
        self.metrics = runlog.MetricsLog(self.log_dir)
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
        """`ck` on this run's device (a resumed state is read onto the first one)."""
        return jax.device_put(ck, self.device)

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
        return ck._replace(cache=jax.device_put(cache, self.device), counters=ck.counters._replace(
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
        if why:
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
        if lost:
            print(f"[ttmjx] warning: {self.metrics.path}: {'missing' if not existed else 'incomplete'}; the rows of "
                  f"{len(lost)} of the {it} iterations before the checkpoint are lost (iterations "
                  f"{lost[0]}-{lost[-1]}; no checkpoint keeps them), so its learning curve starts after them",
                  file=sys.stderr, flush=True)
        return self.absorb_logs(ck) if cfg.data else ck
