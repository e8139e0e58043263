"""The training loop, written once: a run is a function of (config, keys) over a leading lane
axis, as PureJaxRL's `make_train(config)` vmapped over keys. One seed is a batch of one lane.

`Run(cfgs, evaluate)` trains L runs (lanes) that share one program: they differ in their seed, in
the settings an ablation varies as data (training.seeds.LANE_KNOBS: practice on or off, learning
rate, moving average, the practice noise's scale, the demonstrations' share of a batch; Knobs in
training.update) and, with the same schedule, in the demonstrations they start from
(training.seeds.program_key). Every array of their state (weights, optimizer states, moving
averages, caches, keys, counters) is stacked on a leading [L] axis, and each compiled piece of
training (the practice round, the update loop, the throw sampler, the evaluation rollout) is the
one-run piece vmapped over that axis (training.practice, Backend.rollout). Lane k is the
same experiment as that run alone: the same demonstrations, throws, goals, initial weights and
random draws (tests/test_seeds.py, tests/test_lanes.py). A lane that does not practise plays each
round and keeps nothing, so it trains as LFP's train-only rounds do.

Each run keeps its own directory (training.rundir.RunDir: config.json, metrics.jsonl, curves,
Orbax checkpoints), so `ttmjx eval`, `ttmjx export` and a resume treat every lane's directory
like any run's. A batch of seeds also writes its directory's `seeds.json`:

    RUN/seeds.json        {"seeds": [s0, s1, ...], "run_dirs": ["seed<s0>", ...]}
    RUN/seed<s>/          one run per seed

The lanes are laid over the devices (training.mesh.lane_layout: a `lane` mesh axis, every local
device unless cfg.devices says fewer): each device computes a block of lanes (jit's partitioner
splits the lane axis; training.practice.over_lanes), nothing passes between lanes, and a lane
count the devices do not divide is padded with copies of the last lane, computed and never
written. With several processes (one per host, started by a launcher: training.mesh.launcher_process),
each trains its own block of lanes on its own devices (training.mesh.process_lanes): lanes share
nothing, so no array spans processes.

Every random draw of iteration i comes from fold_in(lane key, i), and the state is saved at
iteration boundaries, so a run killed at any point and resumed ends with the same parameters, bit
for bit, as an uninterrupted one (on a CPU, where the arithmetic is deterministic).
"""
from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from training import budget, mesh, pool, runlog
from training.checkpoint import Checkpointed, Counters
from training.practice import Practice, stats_row
from training.rundir import SEEDS_FILE, RunDir, check_not_seed_parent
from training.runconfig import RunConfig
from training.schedule import (is_checkpoint_iteration, is_eval_iteration, phase, round_episodes,
                               total_iterations)
from training.seeds import check_one_batch, mean_row, seed_slice, seed_spread, stacked
from training.loss import lstm_kernel
from training.update import acting_params, lane_knobs
from ttmjx.commandline import install_stop_signals, restore_signals
from ttmjx.world import files
from ttmjx.world.backends import Backend, resolve_backend

# evaluate(params [L, ...], backend, keys [L]) -> [metrics per lane]
Evaluate = Callable[..., list]
# the lanes' configs -> their Evaluate: eval.evaluate.training_evaluation (training never imports eval)
Evaluation = Callable[[list[RunConfig]], Evaluate]
# Lanes whose checkpoints are written at once (each save's compression is multi-threaded too).
SAVE_THREADS = 8


class NonFiniteError(RuntimeError):
    """Training produced a non-finite loss or parameters: the run stops, nothing is saved."""


@jax.jit
def finite_flags(loss, params, ema):
    """[3] bool: loss, parameters and moving average all finite (one compiled reduction)."""
    return jnp.stack([jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree.leaves(t)]))
                      for t in (loss, params, ema)])


class Run:
    """L runs of one program trained together over the lane layout's devices: `cfgs`, a list of
    configurations that differ only in what lanes may (training.seeds.check_one_batch), or one
    RunConfig (a batch of one). `evaluation(lane configs)` gives the evaluation, (params [L],
    backend, keys [L]) -> [metrics], called at the evaluation iterations; None skips evaluation.
    `parent` (optional): the batch's directory, where seeds.json is written. `practice`: the
    Practice class (a subclass changes where practice goals are drawn: training.bootstrap_paper)."""

    def __init__(self, cfgs: list[RunConfig] | RunConfig, evaluation: Evaluation | None = None, progress: bool = True,
                 log=print, parent: str | None = None, practice: type[Practice] = Practice, **practice_kw):
        self.single = isinstance(cfgs, RunConfig)
        every = [cfgs] if self.single else list(cfgs)
        check_one_batch(every)
        lstm_kernel(every[0].policy, every[0].train, len(every))   # refuses a kernel it cannot run, before any work
        if self.single and parent is None:
            check_not_seed_parent(every[0].run_dir)
        self.all_cfgs = every
        # with several processes, this process's block of lanes (the others train theirs)
        lo, hi = mesh.process_lanes(len(every))
        cfgs = every[lo:hi]
        cfg = self.cfg = cfgs[0]
        self.seeds, self.progress, self.log, self.parent = len(cfgs), progress, log, parent
        self.evaluate = evaluation(cfgs) if evaluation is not None else None
        self.layout = mesh.lane_layout(self.seeds, cfg.devices)
        self.devices = self.layout.mesh.size
        self.lanes = mesh.padded_lanes(self.seeds, self.devices)   # computed lanes, padding included
        # refused with the estimate before anything is compiled: each device holds its block of lanes
        budget.check_fits(cfg, seeds=self.lanes // self.devices, devices=self.devices)
        self.backend = Backend(cfg.world, resolve_backend(cfg.backend))
        # each lane's RunDir makes its own state on the device of its block, where `assemble`
        # stacks the block, so the lanes are never gathered on one device (a resumed lane is read
        # onto the first device, one at a time, then moved to its block's)
        self.per_device = self.lanes // self.devices
        self.runs = [RunDir(c, self.backend, self.device_of(i), progress, log) for i, c in enumerate(cfgs)]
        self.cfgs = cfgs + [cfgs[-1]] * (self.lanes - self.seeds)
        self.knobs = lane_knobs([c.train for c in self.cfgs])
        self.practice = practice(cfg.world, cfg.policy, cfg.train, self.backend, cfg.episodes_per_ssp,
                                 cfg.steps_between_ssp, self.layout, seeds=self.lanes,
                                 lane_noise=any(c.train.action_noise > 0 for c in cfgs), **practice_kw)
        self._stop = 0

    # -- state ----------------------------------------------------------------------------
    def start(self) -> Checkpointed:
        """Every lane fresh or resumed, stacked; lanes a crash left at different iterations are
        taken back to the oldest one's."""
        if self.parent and mesh.is_primary():
            os.makedirs(self.parent, exist_ok=True)
            files.write_json(os.path.join(self.parent, SEEDS_FILE),
                             {"seeds": [c.seed for c in self.all_cfgs],
                              "run_dirs": [os.path.relpath(c.run_dir, self.parent) for c in self.all_cfgs]})
        # the lanes that start afresh collect their demonstrations together, one rollout per chunk
        pool.collect_for_lanes([r.cfg for r in self.runs], self.progress, self.place, self.devices)
        cks = [r.start() for r in self.runs]
        its = [int(c.counters.iteration) for c in cks]
        low = min(its)
        cks = [c if i == low else r.rewind(low) for r, c, i in zip(self.runs, cks, its)]
        return self.assemble(cks)

    def device_of(self, lane: int):
        """The device that computes `lane` (lanes are laid in blocks of `per_device`)."""
        return self.layout.mesh.devices.flat[lane // self.per_device]

    def assemble(self, cks: list[Checkpointed]) -> Checkpointed:
        """The lanes' states, each on its block's device, -> one stacked tree [L, ...] split over
        the lane mesh (padded with copies of the last lane): each block is stacked on its own
        device, so setting up many lanes never gathers them all on one."""
        cks = cks + [cks[-1]] * (self.lanes - len(cks))
        blocks = []
        for d in range(self.devices):
            dev = self.layout.mesh.devices.flat[d]
            block = cks[d * self.per_device:(d + 1) * self.per_device]
            blocks.append(stacked([jax.device_put(c, dev) for c in block]))
        sharding = self.layout.lanes
        return jax.tree.map(lambda *xs: jax.make_array_from_single_device_arrays(
            (self.lanes,) + xs[0].shape[1:], sharding, list(xs)), *blocks)

    def place(self, tree):
        """A stacked tree [L, ...] split over the lane layout's devices, a block of lanes each."""
        return jax.device_put(tree, self.layout.lanes)

    def save(self, ck: Checkpointed):
        """Every lane's checkpoint in its own run directory, several at once: Orbax spends most
        of a save compressing the pool on the host (a paper-sim pool is 2 GiB), which threads do
        side by side."""
        with ThreadPoolExecutor(min(self.seeds, SAVE_THREADS)) as ex:
            list(ex.map(lambda s: self.runs[s].save(seed_slice(ck, s)), range(self.seeds)))

    # -- one iteration ----------------------------------------------------------------------
    def step(self, ck: Checkpointed, it: int) -> tuple[Checkpointed, list[dict]]:
        """Iteration `it` of every lane -> (state, one metrics row per real lane). If any lane
        practises, every lane plays the round; the others keep none of it (counted 0)."""
        cfg, t0 = self.cfg, time.perf_counter()
        practising = [phase(c, it) == "practice" for c in self.cfgs]
        base = np.asarray(ck.key)                                    # [L, 2], as each run's own key
        fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
        throws = self.practice.round_throws(base, it) if any(practising) else None
        new_traj = np.array([round_episodes(c, it) for c in self.cfgs], np.int32)
        state, cache, loss, stats = self.practice.iteration(ck.state, ck.cache, self.place(fold(base, it)), throws,
                                                            new_traj, self.knobs)
        self.check_finite(state, loss, it)
        new_upd = cfg.steps_between_ssp if self.practice.train_loop else 0
        c = ck.counters
        counters = self.place(Counters(c.iteration + 1, c.trajectories + new_traj, c.updates + new_upd))
        ck = Checkpointed(state, cache, ck.key, counters)
        loss, sizes = np.asarray(loss), np.asarray(cache.size)
        trajs, upds = np.asarray(counters.trajectories), np.asarray(counters.updates)
        rows = [{"iteration": it, "phase": phase(self.cfgs[s], it), "trajectories": int(trajs[s]),
                 "updates": int(upds[s]), "cache_size": int(sizes[s]), "loss": float(np.mean(loss[s])),
                 "seconds": time.perf_counter() - t0, "seeds_in_program": self.seeds} for s in range(self.seeds)]
        if stats is not None:
            host = {k: np.asarray(v) for k, v in stats._asdict().items()}
            for s, row in enumerate(rows):
                if practising[s]:
                    row.update(stats_row({k: v[s] for k, v in host.items()}))
        if self.evaluate is not None and is_eval_iteration(cfg, it):
            metrics = self.evaluate(acting_params(state), self.backend, fold(base, 10**6 + it))[:self.seeds]
            for row, m in zip(rows, metrics):
                row.update({f"eval_{k}": v for k, v in m.items()})
        return ck, rows

    def check_finite(self, state, loss, it: int):
        """NonFiniteError naming the lanes whose loss or parameters are not finite."""
        ok = np.asarray(jax.vmap(finite_flags)(loss, state.params.net, state.ema.net))[:self.seeds]   # [S, 3]
        bad = [(r, [n for n, f in zip(("loss", "parameters", "moving average"), fine) if not f])
               for r, fine in zip(self.runs, ok) if not fine.all()]
        if bad:
            what = "; ".join(f"seed {r.cfg.seed}: {' and '.join(names)}" for r, names in bad)
            raise NonFiniteError(f"iteration {it}: non-finite {what} (learning rate too high, or non-finite "
                                 f"data?); stopped without saving: the last good checkpoint is iteration "
                                 f"{self.runs[0].saved_at}")

    # -- the loop ----------------------------------------------------------------------------
    def run(self, max_iterations: int | None = None) -> dict:
        """Train every lane to the end (or `max_iterations` more iterations). One RunConfig: that
        run's result ({run_dir, iteration, trajectories, finished, stopped_by_signal, eval_*});
        a list: a summary with each lane's result under "runs"."""
        cfg = self.cfg
        ck = self.start()
        n_tot = total_iterations(cfg)
        start = int(ck.counters.iteration[0])
        stop_at = n_tot if max_iterations is None else min(n_tot, start + max_iterations)
        total = sum(c.total_trajectories if c.practice else max(c.demos, 1) for c in (r.cfg for r in self.runs))
        bar = runlog.progress_bar(total, int(np.sum(ck.counters.trajectories[:self.seeds])), self.progress)
        last: list[dict] = [{} for _ in self.runs]
        install_stop_signals(self)     # SIGINT/SIGTERM: this iteration finishes, saves, returns
        try:
            for it in range(start, stop_at):
                before = int(np.sum(ck.counters.trajectories[:self.seeds]))
                ck, rows = self.step(ck, it)
                for s, (r, row) in enumerate(zip(self.runs, rows)):
                    r.metrics.write(row)
                    if any(k.startswith("eval_") for k in row):
                        last[s] = row
                if is_checkpoint_iteration(cfg, it, stop_at) or self._stop:
                    self.save(ck)
                bar.update(int(np.sum(ck.counters.trajectories[:self.seeds])) - before)
                bar.set_postfix_str(runlog.postfix(mean_row(rows)))
                if self._stop:
                    where = self.runs[0].ckpt_dir if self.single else f"the run directories of {self.seeds} lanes"
                    self.log(f"[ttmjx] saved checkpoint at iteration {it + 1} in {where}")
                    break
        finally:
            bar.close()
            restore_signals(self)
            for r in self.runs:
                r.metrics.close()
        for r in self.runs:
            runlog.plot_curves(r.metrics.path, os.path.join(r.log_dir, "learning_curve.png"))
        it = int(ck.counters.iteration[0])
        runs = [{"run_dir": r.cfg.run_dir, "seed": r.cfg.seed, "iteration": it,
                 "trajectories": int(ck.counters.trajectories[s]), "finished": it >= n_tot,
                 "stopped_by_signal": self._stop,
                 **{k: v for k, v in last[s].items() if k.startswith("eval_")}} for s, r in enumerate(self.runs)]
        if self.single:
            return {k: v for k, v in runs[0].items() if k != "seed"}
        return {"run_dir": self.parent or os.path.commonpath([r.cfg.run_dir for r in self.runs]),
                "seeds": [r.cfg.seed for r in self.runs], "iteration": it,
                "trajectories": int(np.max(ck.counters.trajectories[:self.seeds])), "finished": it >= n_tot,
                "stopped_by_signal": self._stop, **seed_spread(runs), "runs": runs}
