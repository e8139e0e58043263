"""`ttmjx baseline METHOD`: the paper's Table I methods on one world, through the cells of
eval/table_cells.py (skip finished cells, atomic JSON results, the same table, curves and landing maps
as `ttmjx ablate`).

Methods (the table's variants):

    ppo, sac, es   brax's trainers on training/baselines/env.py (training/baselines/agents.py),
                   their policy saved as a GoalsEye checkpoint and evaluated by the same final
                   evaluation as every ablation cell (eval/table_cells.py: same goals, same throws)
    qtopt          QT-Opt on the same environment (training/baselines/qtopt.py); its policy, CEM
                   over a Q-function, is no GoalsEye checkpoint: its curve and its final
                   evaluation (the same goals and throws as every cell) are rolled out here, all
                   seeds in one batch (`in_process_scores`); it cannot be exported
    gcsl           this project's trainer from 0 demonstrations (practice only)
    lfp            this project's trainer on demonstrations alone, as many as the budget
                   (practice off; GoalsEye's gradient updates: the `practice` ablation's
                   lfp-equal-data)
    goalseye       this project's trainer as configured (the reference row)

All at the same trajectory budget. An RL cell saves its whole state (a replay buffer included)
at every curve point (training/baselines/resumable.py) and the same command resumes it; a
finished cell is skipped.

    OUT/runs/<method>-seed<s>/    the cell's run (RL: <method>_state/, timing.json; brax's
                                  methods also checkpoints/)
    OUT/results/<method>-seed<s>.json, OUT/table.md, curves.png, landings/, summary.json
"""
from __future__ import annotations

import dataclasses
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from eval import ablate
from eval import table_cells
from eval import tables
from eval.evaluate import uniform_runs
from training import overrides, runconfig
from ttmjx.world import files
from training.baselines import agents
from training.baselines.config import RewardConfig
from training.runconfig import RunConfig
from ttmjx.world.backends import Backend, resolve_backend

RL = agents.METHODS
METHODS = (*RL, "gcsl", "lfp", "goalseye")
SCALES = ("tiny", "full")

log = print


def goalseye_base(scale: str) -> RunConfig:
    """The GoalsEye configuration every method is compared with: tiny (tests), or full: the
    paper's "New Results" setting (frame stack of 8 x 16 values, MLP 2 x 1024), one member, at
    Table I's 120k trajectories (--trajectories to change)."""
    if scale == "tiny":
        return runconfig.tiny()
    if scale == "full":
        base = runconfig.paper_sim_new()
        return dataclasses.replace(base, total_trajectories=120_000,
                                   train=dataclasses.replace(base.train, members=1))
    raise ValueError(f"unknown scale {scale!r}; expected one of {SCALES}")


def tiny_rl() -> dict:
    """The RL settings of the tiny scale: 2 environments, batches of a few steps, 3 curve points
    where the budget divides into 2 epochs (CPU tests)."""
    return dict(ppo=agents.PPOConfig(num_envs=2, unroll_length=4, batch_size=2, num_minibatches=2,
                                     num_updates_per_batch=1, value_hidden=(16,)),
                sac=agents.SACConfig(num_envs=2, batch_size=8, grad_updates_per_step=1, min_replay_size=16,
                                     max_replay_size=4096),
                es=agents.ESConfig(population_size=1),
                qtopt=agents.QTOptConfig(num_envs=2, batch_size=8, grad_updates_per_step=1, min_replay_size=16,
                                         max_replay_size=4096, hidden=(16,), target_lag=3),
                num_evals=3, num_eval_envs=1, throw_pool=2)


def method_config(method: str, scale: str, seed: int, run_dir: str, trajectories: int | None = None,
                  reward: RewardConfig = RewardConfig(), rl: dict | None = None, changed: dict | None = None):
    """The cell's configuration: a BaselineConfig (RL) or a RunConfig; ValueError naming the
    method and the problem. An RL cell runs exactly its budget: one that no whole number of the
    method's batches fills (or below one batch) is refused, naming the nearest budgets that are
    (agents.schedule). `rl`: RL settings replacing the scale's ({'ppo': PPOConfig(...)}).
    `changed`: {dotted field: value} set on the scale's GoalsEye base for every cell (the
    run-configuration flags, ablate.cell_overrides), before the method's own fields."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")
    base = ablate.replace_fields(ablate.cell_base(goalseye_base(scale), seed, run_dir, trajectories), changed or {})
    try:
        if method in RL:
            run = agents.run_config(method, base)
            settings = {**(tiny_rl() if scale == "tiny" else {"num_evals": 8}), **(rl or {})}
            return agents.BaselineConfig(method, run, reward=reward, **settings)
        own = {"gcsl": {"demos": 0, "pretrain_steps": 0, "preset": "gcsl"},
                     "lfp": {"practice": False, "demos": ablate.ALL_TRAJECTORIES,
                             "pretrain_steps": ablate.GOALSEYE_UPDATES, "preset": "lfp"},
                     "goalseye": {}}[method]
        cfg = ablate.apply(base, own)
        # GoalsEye's budget holds its demonstrations and at least one practice round (LFP's
        # updates are GoalsEye's, so the same); GCSL's one round: fewer trains the method on nothing.
        need = (cfg if method == "gcsl" else base).demos + base.episodes_per_ssp
        if base.total_trajectories < need:
            what = (f"one practice round of {base.episodes_per_ssp:,} episodes" if method == "gcsl" else
                    f"GoalsEye's {base.demos:,} demonstrations and one practice round of {base.episodes_per_ssp:,} "
                    f"episodes")
            raise ValueError(f"trajectory budget {base.total_trajectories:,} is less than {what}; the smallest "
                             f"budget is {need:,}")
        return cfg
    except (ValueError, TypeError) as e:
        raise ValueError(f"baseline {method} at scale {scale}: {e}") from None


def parse_methods(spec: str) -> list[str]:
    """'ppo', 'ppo,sac' or 'all' -> methods, each once, in METHODS order."""
    names = list(METHODS) if spec == "all" else [m.strip() for m in spec.split(",")]
    for m in names:
        if m not in METHODS:
            raise ValueError(f"unknown method {m!r}; expected 'all' or a comma-separated list of {', '.join(METHODS)}")
    return [m for m in METHODS if m in names]


def plan(methods: list[str], scale: str, seeds: int, out: str, trajectories: int | None = None,
         reward: RewardConfig = RewardConfig(), rl: dict | None = None, first_seed: int = 0,
         changed: dict | None = None) -> list[table_cells.Cell]:
    """The cells of seeds first_seed..first_seed+seeds-1 (seed-major), every configuration built
    and every finished result checked before anything is written."""
    entries = [(m, seed) for seed in range(first_seed, first_seed + seeds) for m in methods]
    return table_cells.planned_cells(
        out, entries, lambda m, seed, run_dir: method_config(m, scale, seed, run_dir, trajectories, reward, rl, changed))


# -- the RL trainer (the cells seam) ------------------------------------------------------------
def rl_trainer(cfg: agents.BaselineConfig, progress: bool = True) -> table_cells.Outcome:
    """rl_seeds of one cell (brax's loop unbatched)."""
    return rl_seeds([cfg], progress)[0]


def rl_seeds(cfgs: list, progress: bool = True) -> list[table_cells.Outcome]:
    """The method's loop for the seeds `cfgs` (one program: agents.train_seeds), a strict-metric
    curve point wherever brax hands its policy out (at 0 and after each of its epochs; x:
    brax's environment steps / horizon, which need not be whole inside SAC's run), each policy
    saved as a checkpoint of its run whose counter is the trajectories brax ran, then the
    cells' final evaluation of each.

    The curve's policies are kept during training (and with the checkpointed state) and scored
    together at the end, every point on the same goals and throws (key run.seed + 1) in one
    batched rollout per seed (`curve_metrics`): one episode's latency instead of one per point.
    Where the time went is written to RUN/timing.json (brax's epochs, the curve, the save, the
    final evaluation). Seeds whose stacked epoch would not fit in the device's memory train in
    groups that do (agents.seeds_per_program), one group after another. XLA's estimate is not
    the allocator's word: a group that still runs out of device memory is split in halves and
    run again (each seed's state is saved on its own at step 0, so the halves resume from it)."""
    def say(message: str) -> None:
        log(f"[baseline] {message}", file=sys.stderr)

    k = agents.seeds_per_program(cfgs[0], len(cfgs), log=say)
    outcomes, i = [], 0
    while i < len(cfgs):
        group = cfgs[i:i + k]
        try:
            outcomes += _rl_program(group, progress)
        except Exception as err:  # noqa: BLE001 (only an allocator's refusal is retried)
            if len(group) == 1 or not agents.out_of_memory(err):
                raise
            k = (len(group) + 1) // 2
            say(f"{cfgs[0].method}: {len(group)} seeds as one program ran out of device memory "
                f"({str(err).splitlines()[0][:160]}): trained {k} at a time")
            continue
        i += len(group)
    return outcomes


def _rl_program(cfgs: list, progress: bool) -> list[table_cells.Outcome]:
    """rl_seeds for seeds that train as one program."""
    cfg = cfgs[0]
    h = cfg.run.world.horizon
    points, timing = [[] for _ in cfgs], {}
    t0 = time.perf_counter()

    def on_policy(i: int, steps: int, p):
        """Keep the point; say at once how far the loop got and when (a cell cut short by a
        call's time limit still leaves its timing.json so far)."""
        points[i].append((steps, p))
        files.write_json(os.path.join(cfgs[i].run.run_dir, "timing.json"), timing)
        if progress and i == 0:
            log(f"[baseline] {cfg.method} {steps // h:,} trajectories trained ({steps:,} environment steps"
                f"{f', {len(cfgs)} seeds' if len(cfgs) > 1 else ''}) at {time.perf_counter() - t0:.1f} s",
                file=sys.stderr)

    finals = agents.train_seeds(cfgs, on_policy, timing=timing)
    backend = Backend(cfg.run.world, resolve_backend(cfg.run.backend))
    policies = [[p for _, p in pts] for pts in points]
    scores = (in_process_scores(cfgs, policies, finals, backend) if cfg.method not in agents.BRAX_METHODS
              else [checkpoint_scores(c, ps, f, backend) for c, ps, f in zip(cfgs, policies, finals)])
    outcomes = []
    for c, pts, (metrics, final, landings, seconds) in zip(cfgs, points, scores):
        curve = []
        for (steps, _), m in zip(pts, metrics):
            x = steps // h if steps % h == 0 else round(steps / h, 3)
            curve.append({"trajectories": x, "env_steps": steps, "updates": 0, "cache_size": 0, **m})
            if progress:
                log(f"[baseline] {c.method} seed {c.run.seed} {x:,} trajectories: "
                    f"<=30cm {m['within_30cm']:.1%} hit {m['hit_rate']:.1%}", file=sys.stderr)
        own = {**timing, **seconds, "env_steps": agents.schedule(c).num_timesteps, "seeds_in_program": len(cfgs)}
        files.write_json(os.path.join(c.run.run_dir, "timing.json"), own)
        outcomes.append(table_cells.Outcome(True, 0, final, curve, landings))
    return outcomes


def checkpoint_scores(cfg: agents.BaselineConfig, policies: list, final, backend: Backend):
    """(curve metrics, final metrics, landings, {part: seconds}) of one seed of brax's MLP
    methods: its curve's policies in one rollout (curve_metrics), its final policy saved as a
    GoalsEye checkpoint whose counter is the trajectories brax ran, then the cells' final
    evaluation of that checkpoint."""
    t = time.perf_counter()
    metrics = curve_metrics(cfg, policies, backend)
    seconds = {"curve_eval_s": round(time.perf_counter() - t, 3)}
    t = time.perf_counter()
    agents.save_policy(cfg, final, cfg.run.total_trajectories)     # what brax ran: schedule() is exact
    seconds["save_s"] = round(time.perf_counter() - t, 3)
    t = time.perf_counter()
    final_metrics, landings = table_cells.final_evaluation(cfg.run.run_dir)
    seconds["final_eval_s"] = round(time.perf_counter() - t, 3)
    return metrics, final_metrics, landings, seconds


def in_process_scores(cfgs: list, policies: list, finals: list, backend: Backend) -> list:
    """checkpoint_scores for a policy no GoalsEye checkpoint holds (QT-Opt's CEM over Q:
    qtopt.cem_policy), every seed's curve points and final policy in one rollout: each curve
    point on run.eval_goals goals and throws from key run.seed + 1, as curve_metrics; each final
    policy on those of table_cells.FINAL_EVAL_SEED, as table_cells.final_evaluation. Nothing is
    saved (the policies stay in RUN/qtopt_state/)."""
    from training.baselines import qtopt
    cfg, t = cfgs[0], time.perf_counter()
    runs = [(p, c.run.seed + 1) for c, ps in zip(cfgs, policies) for p in ps] + \
        [(f, table_cells.FINAL_EVAL_SEED) for f in finals]
    metrics, tr = policy_runs(cfg.run.world, qtopt.cem_policy(cfg), [p for p, _ in runs],
                              [jax.random.PRNGKey(k) for _, k in runs], backend, cfg.run.eval_goals)
    seconds = {"eval_s": round(time.perf_counter() - t, 3), "eval_runs": len(runs)}
    out, first = [], 0
    for i, ps in enumerate(policies):
        last = len(runs) - len(finals) + i
        landings = {"goal": np.asarray(tr.goal[last], np.float64).round(4).tolist(),
                    "landing": np.asarray(tr.landing[last], np.float64).round(4).tolist(),
                    "hit": np.asarray(tr.hit[last], bool).tolist(),
                    "on_opponent": np.asarray(tr.on_opponent[last], bool).tolist()}
        out.append((metrics[first:first + len(ps)], metrics[last], landings, seconds))
        first += len(ps)
    return out


def policy_runs(world, policy, params: list, keys: list, backend: Backend, n_goals: int):
    """eval.evaluate.uniform_runs for any one-member Policy (uniform_runs builds its own from a
    PolicyConfig): run s plays policy with params[s] on the n_goals uniform goals and throws
    that uniform_runs draws for keys[s]. Returns ([goal_metrics] per run, Trajectories [S, n_goals]).
    tests/test_qtopt.py checks it against uniform_runs."""
    from eval.evaluate import goal_metrics, split_lanes, uniform_plan
    from ttmjx.world import thrower
    stacked = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(a) for a in x]), *params)
    goals, k_run = uniform_plan(world, jnp.stack(keys), n_goals)
    k_throw, k_roll = split_lanes(k_run)
    throws = jax.vmap(lambda k: thrower.sample_throws(k, world, n_goals))(k_throw)
    tr = backend.rollout(policy, stacked, k_roll, throws, goals)
    return [goal_metrics(tr.landing[s], goals[s], tr.hit[s], tr.on_opponent[s]) for s in range(len(goals))], tr


def curve_metrics(cfg: agents.BaselineConfig, policies: list, backend: Backend) -> list[dict]:
    """Strict-metric goal_metrics of each policy (PolicyParams of one member) on run.eval_goals
    uniform goals from key run.seed + 1 (the same goals and throws for every point), all
    points in one rollout (eval.evaluate.uniform_runs): what evaluate_uniform gives for each."""
    if not policies:
        return []
    run = cfg.run
    stacked = jax.tree.map(lambda *x: jnp.stack([jnp.asarray(a) for a in x]), *policies)
    keys = jnp.stack([jax.random.PRNGKey(run.seed + 1)] * len(policies))
    return uniform_runs(run.world, run.policy, stacked, backend, keys, run.eval_goals)[0]


def trainer(cfg, progress: bool = True) -> table_cells.Outcome:
    """RL configurations to rl_trainer, RunConfigs to the GoalsEye trainer."""
    return rl_trainer(cfg, progress) if isinstance(cfg, agents.BaselineConfig) else table_cells.goalseye(cfg, progress)


def seeds_trainer(cfgs: list, progress: bool = True) -> list[table_cells.Outcome]:
    """The seeds of one method as one program: rl_seeds, or the GoalsEye trainer's batched seeds."""
    return rl_seeds(cfgs, progress) if isinstance(cfgs[0], agents.BaselineConfig) else table_cells.goalseye_seeds(cfgs, progress)


# brax PPO at --scale tiny on 2 CPU cores (measured): ~57 environment steps/s over the 5 seeds of a
# program, compile aside; taken as proportional to the cores. On a GPU: docs/BENCHMARKS.md.
CPU_STEPS_PER_S_PER_CORE = 57 / 2


def cpu_estimate(cells: list, results_dir: str, scale: str, platform: str | None = None,
                 cores: int | None = None) -> str | None:
    """One line stating, before an RL cell starts on the CPU, the environment steps still to run
    and the time they take there, and pointing to the GPU; None on an accelerator or with no RL
    cell to run (finished cells are skipped)."""
    platform = platform or jax.default_backend()
    todo = [c for c in cells if isinstance(c.config, agents.BaselineConfig)
            and not os.path.exists(table_cells.result_path(results_dir, c))]
    if platform != "cpu" or not todo:
        return None
    cores = cores or os.cpu_count() or 1
    steps = sum(agents.schedule(c.config).num_timesteps for c in todo)
    rate = CPU_STEPS_PER_S_PER_CORE * cores
    seconds = steps / rate
    when = f"{seconds / 3600:.1f} h" if seconds >= 5400 else f"{max(1, round(seconds / 60))} min"
    return (f"[baseline {scale}] on the CPU: {len(todo)} RL cell(s), {steps:,} environment steps to run, about "
            f"{when} at ~{rate:.0f} steps/s ({cores} cores; brax PPO measured ~57 steps/s on 2); a GPU runs "
            f"them at tens of thousands of steps/s (docs/BENCHMARKS.md): run it there, or Ctrl-C now and the "
            f"same command resumes")


def run(methods: list[str], scale: str, seeds: int, out: str, trajectories: int | None = None,
        reward: RewardConfig = RewardConfig(), progress: bool = True, command: str = "", rl: dict | None = None,
        first_seed: int = 0, changed: dict | None = None) -> dict:
    """Train the cells that are not finished, then rebuild the table from every finished result
    (those of other seeds in `out` too: machines that ran other seeds add to one table)."""
    cells = plan(methods, scale, seeds, out, trajectories, reward, rl, first_seed, changed)
    estimate = cpu_estimate(cells, os.path.join(out, "results"), scale)
    if estimate:
        log(estimate, file=sys.stderr)
    stopped = table_cells.run_cells(cells, os.path.join(out, "results"), trainer, progress, f"baseline {scale}",
                                    log=lambda m: log(m, file=sys.stderr), batch=seeds_trainer)
    return table_cells.finish(cells, out, stopped, lambda: build_report(scale, out, command))


def rl_settings(**configs) -> dict:
    """{method: its settings} of the RL methods whose settings differ from the defaults
    (`ppo=PPOConfig(...)`, ...): what replaces the scale's."""
    return {name: c for name, c in configs.items() if c != type(c)()}


def command_line(method: str, scale: str, seeds: int, seed: int, trajectories: int | None, out: str | None,
                 changed: dict) -> str:
    """The `ttmjx baseline` command that rebuilds this table (summary.json's 'command'), in a
    fixed order: the methods, --scale, --seeds, --seed, --trajectories, --out, then the
    run-configuration flags (field order); the reward's and RL methods' settings are in each
    result's config."""
    return " ".join(["ttmjx baseline", method, "--scale", scale, "--seeds", str(seeds)]
                    + (["--seed", str(seed)] if seed else [])
                    + (["--trajectories", str(trajectories)] if trajectories else [])
                    + (["--out", out] if out else []) + overrides.flags_of(changed))


def build_report(scale: str, out: str, command: str = "") -> dict:
    """table.md, curves.png, landings/*.png and summary.json from the finished results in `out`."""
    results = ablate.load_results(out)
    if not results:
        raise ValueError(f"no finished cells in {os.path.join(out, 'results')}; run `ttmjx baseline` first")
    budgets = sorted({(r["config"].get("run") or r["config"])["total_trajectories"] for r in results})
    header = {"ablation": "baselines", "scale": scale, "command": command,
              "title": f"baselines ({scale})",
              "subtitle": f"GoalsEye against the paper's Table I baselines (RL through brax, GCSL, LFP) at "
                          f"{'/'.join(f'{t:,}' for t in budgets)} trajectories per cell. Final evaluation of each "
                          f"cell: uniform goals, seed {table_cells.FINAL_EVAL_SEED} (the same goals and throws for "
                          f"every cell)."}
    return tables.write_report(out, results, list(METHODS), header)
