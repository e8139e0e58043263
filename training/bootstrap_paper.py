"""The paper's bootstrap procedure ("Building up the initial bootstrap dataset"), built with this
trainer:

1. ES: a standard ES policy trained fully in simulation until it returns balls
   (ttmjx/tools/es.py: a contact phase, then a return phase). It is narrow: its returns land in
   one region of the opponent's half.
2. narrow data: its rollouts, 4 of the 8 joints perturbed per episode (demos.Perturbation),
   relabelled with where each ball landed (the trainer relabels every demonstration).
3. shift: relabelled goal-conditioned imitation of them (GCBC) and self-practice with the
   goals set "higher up the table": uniform from the narrow landings' median depth to the far
   end line, across the band their landings cover (`shift_box`).
4. expand: self-practice continues with goals over the whole opponent's half.
5. the final demonstrations: 3.6k episodes of that policy, goals uniform over the half, 4 of
   the 8 joints perturbed (ttmjx/tools/bootstrap.py plays it; demos source `paper`).

Stages 3 and 4 are ONE run (`training.trainer.Run`, a batch of one lane: its checkpoints,
metrics and resume): the stage-4 run is the stage-3 run resumed with a larger `total_trajectories`; the only piece
replaced is where practice draws its goals (`GoalBoxPractice`, a `training.practice.Practice`
whose goal draw is a box). Nothing here was tuned against a GoalsEye learning result: the
sizes come from the CPU budget and the stages' own landing coverage and return rates
(docs/DATA.md, "Bootstrap sources").
"""
from __future__ import annotations

import dataclasses
import json
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from models.config import PolicyConfig
from training.checkpoint import load_checkpoint
from training.config import TrainConfig
from training.practice import Practice, RoundParts
from training.runconfig import RunConfig
from training.trainer import Run
from training.update import acting_params
from ttmjx.tools import bootstrap, demos, es
from ttmjx.world import files, record
from ttmjx.world.config import CELL_TRAINING, IDEAL, World, to_dict

# Below these the procedure cannot be what it claims (checked before anything runs).
MIN_NARROW_RETURNS = 100       # narrow demonstrations that land on the opponent's half
MIN_ES_EPISODES = 20_000       # ES episodes (generations x population x throws) per phase


@dataclasses.dataclass(frozen=True)
class Procedure:
    """Sizes of the procedure. The defaults are sized for a CPU run (timings: docs/RESULTS.md,
    "The paper's bootstrap procedure on any-ball throws")."""
    narrow: int = 1000
    """ES episodes gathered (4 joints perturbed): the imitation data of stage 3."""
    shift: int = 1500
    """Practice episodes with goals up the table (stage 3)."""
    expand: int = 2000
    """Practice episodes with goals over the whole half (stage 4)."""
    final: int = 3600
    """Demonstrations gathered at the end (the paper's 3.6k)."""
    pretrain_steps: int = 1500
    """GCBC steps on the narrow data before practice."""
    steps_per_round: int = 100
    episodes_per_round: int = 100
    es_generations: tuple = (134, 330)
    """ES generations of the contact and the return phase (a rebuild from scratch; the shipped
    weights' runs: 134 and 330, each stopped by its time limit)."""
    es_population: int = 48
    es_throws: int = 8
    es_time_limit_s: float | None = None
    """Wall-clock cap of each ES phase (None: none)."""
    es_pool: int = 2048
    """Throws sampled once per ES phase, each generation's drawn from them; and held-out ones."""
    es_val: int = 64
    seed: int = 0

    def check(self, rebuild_es: bool, flags: dict | None = None) -> None:
        """ValueError, one line with the numbers, when the sizes cannot do what the procedure says;
        `flags` names a field as the command line sets it ({'final': '--n'})."""
        flags = flags or {}
        if self.narrow * 0.3 < MIN_NARROW_RETURNS:
            raise ValueError(f"narrow={self.narrow} ES episodes give too few returns to imitate: at least "
                             f"{int(np.ceil(MIN_NARROW_RETURNS / 0.3))} are needed")
        for name in ("shift", "expand", "final"):
            if getattr(self, name) < self.episodes_per_round:
                said = f"{flags[name]} {getattr(self, name)}" if name in flags else f"{name}={getattr(self, name)}"
                raise ValueError(f"{said}: the {name} stage's {getattr(self, name)} episodes are less than one "
                                 f"practice round of the procedure ({self.episodes_per_round}); expected at least "
                                 f"{self.episodes_per_round}")
        if rebuild_es:
            for phase, gens in zip(("contact", "return"), self.es_generations):
                n = gens * self.es_population * self.es_throws
                if n < MIN_ES_EPISODES:
                    raise ValueError(f"{flags.get('es_generations', 'es_generations')} "
                                     f"{' '.join(map(str, self.es_generations))}: ES {phase} phase: {gens} "
                                     f"generations x {self.es_population} x {self.es_throws} throws = {n} "
                                     f"episodes, too few to converge "
                                     f"(at least {MIN_ES_EPISODES})")


def default_world() -> World:
    """The world the shipped weights were built in: the main job's (narrow throws, the cell's
    timing randomized per episode)."""
    return World(timing=CELL_TRAINING).with_throws("narrow")


def stage_config(world: World, proc: Procedure, narrow_dir: str, run_dir: str, total: int) -> RunConfig:
    """The small trainer configuration of stages 3 and 4 (the CPU main job's network)."""
    return RunConfig(
        preset="bootstrap-paper", world=world,
        policy=PolicyConfig(kind="framestack", hidden=256, layers=2, obs_size=13, frame_stack=world.frame_stack),
        train=TrainConfig(window=96, batch_size=32, learning_rate=3e-4, members=1, capacity=16384,
                          action_noise=0.0, ema_decay=0.995),
        demos=proc.narrow, demo_source="es", demo_dir=narrow_dir, pretrain_steps=proc.pretrain_steps,
        steps_between_ssp=proc.steps_per_round, episodes_per_ssp=proc.episodes_per_round,
        total_trajectories=total, eval_every=10**9, seed=proc.seed, backend="c", run_dir=run_dir,
        keep_checkpoints=1, checkpoint_every=5)


class GoalBoxPractice(Practice):
    """Practice whose goals are uniform over a box ((x0, x1), (y0, y1)) (m, table frame)
    instead of the whole half: the shift stage's goals "higher up the table"."""

    def __init__(self, *args, box, **kw):
        self.box = tuple(tuple(float(v) for v in b) for b in box)
        super().__init__(*args, **kw)

    def _pure_parts(self, rollout) -> RoundParts:
        parts = super()._pure_parts(rollout)
        (x0, x1), (y0, y1) = self.box
        m = self.episodes

        def goals(key):
            u = jax.random.uniform(key, (m, 2))
            return jnp.stack([x0 + (x1 - x0) * u[:, 0], y0 + (y1 - y0) * u[:, 1]], 1)
        return parts._replace(goals=goals)


def shift_box(traj: record.Trajectories, world: World) -> tuple:
    """Goals "higher up the table" than the narrow landings: x from their median depth to the
    far end line (5 cm inside), y over the band their landings cover (5th-95th percentile,
    widened by 10 cm each side, within the table)."""
    on = np.asarray(traj.on_opponent, bool)
    land = np.asarray(traj.landing)[on]
    t = world.table
    x0 = float(np.median(land[:, 0]))
    y0, y1 = np.percentile(land[:, 1], [5, 95])
    y0, y1 = max(float(y0) - 0.1, -t.half_width + 0.05), min(float(y1) + 0.1, t.half_width - 0.05)
    return (x0, t.half_length - 0.05), (y0, y1)


def whole_half(world: World) -> tuple:
    return (0.0, world.table.half_length), (-world.table.half_width, world.table.half_width)


def practise(cfg: RunConfig, box, progress: bool, log) -> dict:
    """Run (or resume) the stage run to cfg.total_trajectories with practice goals in `box`."""
    run = Run(cfg, None, progress=progress, log=log, practice=GoalBoxPractice, box=box)
    return run.run()


def stage_rows(run_dir: str, lo: int, hi: int) -> dict:
    """Mean practice statistics of the rounds whose trajectory count lies in (lo, hi]."""
    rows = [json.loads(line) for line in open(os.path.join(run_dir, "metrics.jsonl")) if line.strip()]
    rows = [r for r in rows if r.get("phase") == "practice" and lo < r["trajectories"] <= hi]
    keys = ("practice_hit_rate", "practice_on_table_rate", "practice_within_30cm")
    first, last = rows[: max(1, len(rows) // 4)], rows[-max(1, len(rows) // 4):]
    return {"rounds": len(rows), **{f"first_{k}": float(np.mean([r[k] for r in first])) for k in keys},
            **{f"last_{k}": float(np.mean([r[k] for r in last])) for k in keys}}


def tensors_of(params) -> dict:
    """A frame-stack MLP's PolicyParams (leaves [N, ...]) as the named arrays of
    tools/bootstrap.py's weights file."""
    net = params.net["params"]
    tensors = {f"{name}/{leaf}": np.asarray(net[name][leaf], np.float32) for name in net for leaf in ("kernel", "bias")}
    n = tensors["head/bias"].shape[0]
    for field, value in params.norm._asdict().items():
        value = np.asarray(value, np.float32)
        tensors[f"norm/{field}"] = np.broadcast_to(value, (n,) + value.shape[-1:]).copy()
    return tensors


def export_weights(run_dir: str, out_dir: str, meta: dict) -> str:
    """The run's acting (moving-average) policy as bootstrap weights (tools/bootstrap.py)."""
    loaded = load_checkpoint(os.path.join(run_dir, "checkpoints"))
    pcfg = loaded.cfg.policy
    return bootstrap.save_weights(out_dir, tensors_of(acting_params(loaded.ck.state)),
                                  {"layers": pcfg.layers, "hidden": pcfg.hidden, "frame_stack": pcfg.frame_stack,
                                   "obs_size": pcfg.obs_size, **meta})


def gather(world: World, source: str, n: int, seed: int, out: str, params_dir: str | None, progress: bool,
           pert: demos.Perturbation | None = demos.Perturbation()) -> dict:
    """Collect n episodes of a source into the dataset `out`; its summary."""
    t0 = time.perf_counter()
    traj = demos.collect(world, source, n, seed, progress=progress, params_dir=params_dir, pert=pert)
    seconds = time.perf_counter() - t0
    summ = demos.summary(traj, world)
    record.save(out, traj, {"source": source, "distribution": world.throws.name, "seed": seed, "backend": "c",
                            "code_version": demos.code_version(), "seconds": seconds,
                            **{k: v for k, v in summ.items() if k != "n"}, "world": to_dict(world)})
    return {**summ, "seconds": seconds}


def train_es(world: World, proc: Procedure, out_dir: str, progress: bool, log) -> dict:
    """Stage 1 from scratch: the contact phase, then the return phase from its weights, both in
    `world` with ideal timing (as the shipped weights: ttmjx/tools/assets/es_*.json)."""
    world = dataclasses.replace(world, timing=IDEAL)
    summary, init = {}, None
    for i, (phase, reward) in enumerate((("contact", es.CONTACT), ("return", es.RETURN))):
        t0 = time.perf_counter()
        path = os.path.join(out_dir, f"es_{phase}.npz")
        log(f"[bootstrap] ES {phase} phase: {proc.es_generations[i]} generations x {proc.es_population} "
            f"x {proc.es_throws} throws")
        params, hist = es.train_es(world, proc.es_generations[i], proc.es_population, proc.seed,
                                   progress=progress, throws_per_candidate=proc.es_throws,
                                   es=es.ESConfig(sigma=0.04, lr=0.01), init=init,
                                   time_limit_s=proc.es_time_limit_s, checkpoint=path, reward=reward,
                                   pool=proc.es_pool, val_throws=proc.es_val)
        init = jax.tree.map(np.asarray, params)
        val = [{k[4:]: v for k, v in h.items() if k.startswith("val_")} for h in hist if "val_return_rate" in h]
        summary[phase] = {"generations": len(hist), "seconds": time.perf_counter() - t0,
                          "validation": val[-1] if val else None}
    es.save_params(os.path.join(out_dir, es.WEIGHTS_NAME), init, {"phases": summary})
    return summary


def build(out_dir: str, world: World | None = None, proc: Procedure = Procedure(), rebuild_es: bool = False,
          progress: bool = True, log=print, narrow_source: str = "es") -> dict:
    """The whole procedure into `out_dir` (es_policy.npz when ES is rebuilt, narrow/ and final/
    datasets, run/ the stage run, paper_policy.safetensors + .json, procedure.json). Without
    `rebuild_es` the shipped ES weights are stage 1. Resumable: a finished part is not redone.
    narrow_source: the narrow stage's demonstrator (`es`, the paper's; tests pass `striker` to
    exercise the stages without ES)."""
    world = world or default_world()
    proc.check(rebuild_es)
    os.makedirs(out_dir, exist_ok=True)
    report = {"procedure": dataclasses.asdict(proc), "world": to_dict(world), "code_version": demos.code_version()}
    timer = {}
    t0 = time.perf_counter()
    es_dir = None
    if rebuild_es:
        if not os.path.exists(os.path.join(out_dir, es.WEIGHTS_NAME)):
            report["es"] = train_es(world, proc, out_dir, progress, log)
        es_dir = out_dir
    timer["es"] = time.perf_counter() - t0
    narrow_dir = os.path.join(out_dir, "narrow")
    t0 = time.perf_counter()
    if not os.path.exists(os.path.join(narrow_dir, "trajectories.npz")):
        log(f"[bootstrap] narrow data: {proc.narrow} ES episodes, 4 joints perturbed")
        gather(world, narrow_source, proc.narrow, proc.seed + 1, narrow_dir, es_dir, progress)
    narrow, _ = record.load(narrow_dir)
    report["narrow"] = demos.summary(narrow, world)
    if report["narrow"]["return_rate"] * proc.narrow < MIN_NARROW_RETURNS:
        raise ValueError(f"the ES policy returned {report['narrow']['return_rate']:.1%} of {proc.narrow} balls: "
                         f"fewer than {MIN_NARROW_RETURNS} to imitate; train ES longer")
    timer["narrow"] = time.perf_counter() - t0
    run_dir = os.path.join(out_dir, "run")
    box = shift_box(narrow, world)
    report["shift_box"] = box
    t0 = time.perf_counter()
    t_shift = proc.narrow + proc.shift
    log(f"[bootstrap] shift: GCBC, then practice toward goals x in [{box[0][0]:.2f}, {box[0][1]:.2f}], "
        f"y in [{box[1][0]:.2f}, {box[1][1]:.2f}] m")
    practise(stage_config(world, proc, narrow_dir, run_dir, t_shift), box, progress, log)
    report["shift"] = stage_rows(run_dir, proc.narrow, t_shift)
    timer["shift"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    t_expand = t_shift + proc.expand
    log("[bootstrap] expand: practice toward goals over the whole half")
    practise(stage_config(world, proc, narrow_dir, run_dir, t_expand), whole_half(world), progress, log)
    report["expand"] = stage_rows(run_dir, t_shift, t_expand)
    timer["expand"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    export_weights(run_dir, out_dir, {"built_by": "training.bootstrap_paper.build", "procedure": report["procedure"],
                                      "shift_box": box, "world": report["world"]})
    final_dir = os.path.join(out_dir, "final")
    if not os.path.exists(os.path.join(final_dir, "trajectories.npz")):
        log(f"[bootstrap] final demonstrations: {proc.final} episodes, goals over the half, 4 joints perturbed")
        gather(world, "paper", proc.final, proc.seed + 2, final_dir, out_dir, progress)
    report["final"] = demos.summary(record.load(final_dir)[0], world)
    timer["final"] = time.perf_counter() - t0
    # The paper's figure: the narrow policy itself (unperturbed) beside the final demonstrations.
    policy_dir = os.path.join(out_dir, "narrow_policy")
    if not os.path.exists(os.path.join(policy_dir, "trajectories.npz")):
        gather(world, narrow_source, min(proc.narrow, demos.NARROW_FIGURE_N), proc.seed + 3, policy_dir, es_dir,
               progress, pert=None)
    policy_traj = record.load(policy_dir)[0]
    report["narrow_policy"] = demos.summary(policy_traj, world)
    report["seconds"] = timer
    files.write_json(os.path.join(out_dir, "procedure.json"), report)
    demos.plot_bootstrap(policy_traj, record.load(final_dir)[0], world, os.path.join(out_dir, "bootstrap.png"))
    return report
