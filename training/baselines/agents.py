"""The RL baselines: PPO, SAC and ES on GoalEnv as brax 0.14.2's trainers run them, configured,
not rewritten in substance, and QT-Opt, which brax has not. ppo.py, sac.py and es.py run brax's
own epochs, from brax's pieces, with the state outside the call, so that a cell checkpoints every
epoch and resumes (resumable.py); tests compare each with brax's ppo.train / sac.train /
es.train. Their policy is saved as a GoalsEye checkpoint (training/checkpoint.py) so `ttmjx eval`
and `ttmjx export` read it unchanged. qtopt.py is QT-Opt on the same pieces and in SAC's loop;
its policy (CEM over a Q-function) is no GoalsEye MLP: eval/baselines.py evaluates it in-process
and it is not saved as a checkpoint (qtopt.py's docstring).

Configuration choices (the rest are brax's defaults):

* every policy is brax's MLP with ReLU (GoalsEye's MLPNet activation) of the run's
  PolicyConfig.hidden x layers, on brax's running observation normalization;
* `distribution_type='normal'` (PPO, SAC) and an ES network factory with brax's
  NormalDistribution instead of its fixed tanh-normal: the deterministic action is then the
  network's mean, a linear head, which is exactly GoalsEye's framestack policy (linear head ->
  denormalize -> env.command clips to the joint box). With tanh-normal the action would be
  squashed into [-1, 1], which the joint-box clipping already does (GoalEnv maps [-1, 1] onto
  the box), but the export would need a tanh layer GoalsEye's policies do not have;
* `wrap_env_fn=wrap_fresh`: brax's AutoResetWrapper replays each environment's first throw and
  goal forever (training/baselines/env.py);
* the trajectory budget N is N * horizon environment steps (GoalEnv's episodes are `horizon`
  steps long), run exactly or refused: brax rounds num_timesteps UP to whole evaluation epochs
  (PPO asked for 120,000 trajectories ran 143,360), so `schedule` chooses brax's num_timesteps
  and num_evals such that brax's own arithmetic (`brax_env_steps`, a copy of it) runs exactly N
  trajectories in epochs of equal length, and a budget that no whole number of the method's
  batches fills is refused with the nearest budgets that are. The GPU settings make Table I's
  120,000 exact for every method: PPO's batch is 4,000 episodes (4,000 environments x 160 steps), ES's 2 x 1,000;
* no brax evaluator: the strict-metric curve replaces its episode-reward rollout, which cost a
  compiled MJX episode and a sequential episode per point;
* learning-curve points where brax's trainers hand their policy out: PPO at 0 and after every
  epoch (its policy_params_fn), SAC and ES at 0 and after each epoch that reaches an evaluation
  step (their evaluator). The points are only collected during training (and saved with the
  state); eval/baselines.py scores them all in one batched rollout at the end;
* seeds: the seeds of a method as one program, their states stacked and the epoch vmapped
  (resumable.run_seeds); each method's epoch is built once per configuration whatever the seed
  (`parts`).

The conversion (`policy_params`): brax's policy MLP hidden_i -> MLPNet dense_i, its mean head ->
head; brax's observation normalization (x - m) / s per input value folded into the first layer
(W / s, b - (m / s) W), so the saved Normalizer is the identity on observations; actions
denormalized with act_mean = home, act_std = reach (GoalEnv's affine action map).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import linen

from models.normalizer import Normalizer
from models.policy import PolicyParams
from training import checkpoint
from training.baselines import resumable
from training.baselines.config import ESConfig, PPOConfig, QTOptConfig, RewardConfig, SACConfig  # noqa: F401 (re-exported)
from training.baselines.env import reach
from training.runconfig import RunConfig, to_json

BRAX_METHODS = ("ppo", "sac", "es")
"""brax's trainers: their policy is brax's MLP, converted into a GoalsEye checkpoint (policy_params)."""
METHODS = (*BRAX_METHODS, "qtopt")


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """One RL baseline run: the method, the GoalsEye RunConfig it is compared with (its world, the
    policy MLP size, trajectory budget, evaluation goals, seed and run directory), the reward and
    the method's settings."""
    method: Literal["ppo", "sac", "es", "qtopt"]
    run: RunConfig
    reward: RewardConfig = RewardConfig()
    ppo: PPOConfig = PPOConfig()
    sac: SACConfig = SACConfig()
    es: ESConfig = ESConfig()
    qtopt: QTOptConfig = QTOptConfig()
    num_evals: int = 5
    """Learning-curve points asked for, the one at 0 trajectories included (strict metric on
    run.eval_goals goals wherever brax hands its policy out). brax's epochs must divide the
    budget's training steps exactly, so the number run is schedule(cfg).num_evals: the divisor
    of the steps nearest num_evals - 1 (at most 4x it), plus one."""
    num_eval_envs: int = 128
    """brax's own evaluator (episode reward) environments (SAC, ES; PPO runs none)."""
    throw_pool: int = 16
    """Throws solved ahead per environment (training/baselines/env.py FreshAutoReset): one solve
    serves this many episodes."""

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {METHODS}")
        if self.run.policy.kind != "framestack":
            raise ValueError(f"RL baselines use an MLP on the frame stack: policy.kind={self.run.policy.kind!r}, "
                             f"expected 'framestack'")
        if self.num_evals < 1 or self.num_eval_envs < 1:
            raise ValueError(f"num_evals={self.num_evals} and num_eval_envs={self.num_eval_envs} must be >= 1")
        if self.throw_pool < 1:
            raise ValueError(f"throw_pool={self.throw_pool} must be >= 1")
        schedule(self)   # the budget: run exactly, or ValueError naming the nearest budgets

    def program_key(self) -> str:
        """What seeds trained as one program share (train_seeds): everything but the seed and
        the run directory."""
        import json
        return json.dumps({"method": self.method, **state_json(self), "seed": None}, sort_keys=True, default=str)

    @property
    def steps(self) -> int:
        """brax num_timesteps: exactly the environment steps brax runs (schedule(self))."""
        return schedule(self).num_timesteps


# -- the budget in brax's units -----------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class Schedule:
    """How brax runs a trajectory budget: the arguments and what they consume."""
    num_timesteps: int
    """brax num_timesteps; brax runs exactly this many environment steps."""
    num_evals: int
    """brax num_evals: an evaluation at 0, then one after each of num_evals - 1 equal epochs."""
    trajectories: int
    """num_timesteps / horizon: the trajectories consumed (<= the budget)."""
    units: int
    """Training steps (PPO: one batch; SAC, QT-Opt: one actor step of every environment) or ES
    epochs, after SAC's or QT-Opt's replay prefill."""


def _units(cfg: BaselineConfig) -> tuple[int, int]:
    """(prefill, unit): brax's environment steps before training (SAC's replay prefill, rounded
    up to whole actor steps as brax does; QT-Opt's loop is SAC's) and per training step / ES
    epoch."""
    h = cfg.run.world.horizon
    if cfg.method == "ppo":   # ppo/train.py: env_step_per_training_step (action_repeat 1)
        p = cfg.ppo
        return 0, p.batch_size * p.unroll_length * p.num_minibatches
    if cfg.method in ("sac", "qtopt"):   # sac/train.py: num_prefill_env_steps, env_steps_per_actor_step
        s = cfg.sac if cfg.method == "sac" else cfg.qtopt
        return -(-s.min_replay_size // s.num_envs) * s.num_envs, s.num_envs
    return 0, 2 * cfg.es.population_size * h   # es/train.py: 2 * population episodes of h steps


def brax_env_steps(cfg: BaselineConfig, num_timesteps: int, num_evals: int) -> int:
    """The environment steps brax 0.14.2's trainer for cfg.method runs when called with
    (num_timesteps, num_evals), from its own arithmetic (action_repeat 1, one device):

        ppo/train.py  num_training_steps_per_epoch = ceil(T / (max(E - 1, 1) * unit)); runs
                      max(E - 1, 1) epochs of it (num_resets_per_eval 0)
        sac/train.py  prefill, then max(E - 1, 1) epochs of ceil((T - prefill) / (max(E - 1, 1)
                      * num_envs)) actor steps
        es/train.py   whole epochs of 2 * population_size episodes while steps < T (an episode
                      is `horizon` steps: RewardConfig.end_at_landing False)
        qtopt.py      as sac/train.py (its loop)"""
    prefill, unit = _units(cfg)
    epochs = max(num_evals - 1, 1)
    if cfg.method == "es":
        return -(-num_timesteps // unit) * unit
    return prefill + epochs * -(-(num_timesteps - prefill) // (epochs * unit)) * unit


def _valid_units(cfg: BaselineConfig) -> tuple[int, int]:
    """(first, period): the unit counts n >= 1 with (prefill + n * unit) a whole number of
    episodes are first, first + period, ...; ValueError if there are none."""
    h = cfg.run.world.horizon
    prefill, unit = _units(cfg)
    period = h // math.gcd(unit, h)
    first = next((n for n in range(1, period + 1) if (prefill + n * unit) % h == 0), None)
    if first is None:
        raise ValueError(f"{cfg.method}: no number of its batches of {unit} environment steps after a prefill "
                         f"of {prefill} is a whole number of {h}-step trajectories; change its batch settings")
    return first, period


def _epochs(units: int, target: int) -> int:
    """The divisor of `units` (epochs of equal length) nearest `target` in ratio (ties: the
    larger), at most 4 x target."""
    divisors = [d for d in range(1, min(units, 4 * target) + 1) if units % d == 0]
    return min(divisors, key=lambda d: (abs(math.log(d / target)), -d))


def _environments(cfg: BaselineConfig) -> int:
    """Environments brax steps side by side (ES: none; its episodes are whole by construction): a
    budget below this many trajectories ends before any of them has played one whole episode."""
    return {"ppo": cfg.ppo.num_envs, "sac": cfg.sac.num_envs, "qtopt": cfg.qtopt.num_envs}.get(cfg.method, 1)


def exact_budgets(cfg: BaselineConfig, trajectories: int) -> tuple[int | None, int]:
    """(largest, smallest): the budgets brax runs exactly that are <= and >= `trajectories`
    (None: none below). A budget is exact when prefill + k * unit environment steps, k a whole
    number of the method's batches (>= 1), are that many whole trajectories, and at least one
    whole episode of each of its environments (fewer trains on no episode's end: `ttmjx baseline
    ppo --scale tiny --trajectories 1` ran each of its 2 environments for half an episode)."""
    h = cfg.run.world.horizon
    prefill, unit = _units(cfg)
    first, period = _valid_units(cfg)
    step = period * unit // h                     # trajectories between two exact budgets
    lowest = (prefill + first * unit) // h
    envs = _environments(cfg)                     # and each environment plays a whole episode
    if lowest < envs:
        lowest += -(-(envs - lowest) // step) * step
    if trajectories < lowest:
        return None, lowest
    below = lowest + (trajectories - lowest) // step * step
    return below, below if below == trajectories else below + step


def schedule(cfg: BaselineConfig, trajectories: int | None = None) -> Schedule:
    """brax's (num_timesteps, num_evals) for a budget (default: cfg.run.total_trajectories) that
    brax runs exactly, in the number of equal epochs nearest cfg.num_evals - 1 that divides it.
    ValueError naming the nearest exact budgets for any other budget (below one batch too)."""
    n = cfg.run.total_trajectories if trajectories is None else trajectories
    h = cfg.run.world.horizon
    prefill, unit = _units(cfg)
    below, above = exact_budgets(cfg, n)
    what = {"ppo": f"training steps of {unit // h:,} trajectories",
            "sac": f"a replay prefill of {prefill:,} steps, then actor steps of {unit:,} environment steps",
            "es": f"updates of {unit // h:,} episodes",
            "qtopt": f"a replay prefill of {prefill:,} steps, then actor steps of {unit:,} environment steps"}[cfg.method]
    if below is None and n * h >= prefill + _valid_units(cfg)[0] * unit:
        envs = _environments(cfg)
        raise ValueError(f"trajectory budget {n:,} ends before any of {cfg.method}'s {envs:,} environments has "
                         f"played one whole {h}-step episode ({n * h // envs:,} steps each); the smallest "
                         f"budget is {above:,}")
    if below is None:
        raise ValueError(f"trajectory budget {n:,} is below one batch of {cfg.method} ({what}); "
                         f"the smallest budget is {above:,}")
    if below != n:
        raise ValueError(f"trajectory budget {n:,} cannot be run exactly by {cfg.method} ({what}); "
                         f"the nearest budgets are {below:,} and {above:,}")
    units = (n * h - prefill) // unit
    epochs = _epochs(units, max(cfg.num_evals - 1, 1))
    steps = prefill + units * unit
    assert steps == n * h and brax_env_steps(cfg, steps, epochs + 1) == steps
    return Schedule(num_timesteps=steps, num_evals=epochs + 1, trajectories=n, units=units)


def batch_trajectories(cfg: BaselineConfig) -> int:
    """Trajectories of one batch (one update) of the method: the smallest budget that trains."""
    prefill, unit = _units(cfg)
    return (prefill + _valid_units(cfg)[0] * unit) // cfg.run.world.horizon


# -- brax networks -----------------------------------------------------------------------------
def _hidden(cfg: BaselineConfig) -> tuple:
    return (cfg.run.policy.hidden,) * cfg.run.policy.layers


def ppo_networks(cfg: BaselineConfig):
    from brax.training.agents.ppo import networks
    return functools.partial(networks.make_ppo_networks, policy_hidden_layer_sizes=_hidden(cfg),
                             value_hidden_layer_sizes=cfg.ppo.value_hidden, activation=linen.relu,
                             distribution_type="normal", init_noise_std=cfg.ppo.init_noise_std)


def sac_networks(cfg: BaselineConfig):
    from brax.training.agents.sac import networks
    # One hidden_layer_sizes for the policy and the Q networks in brax (SACConfig's docstring).
    return functools.partial(networks.make_sac_networks, hidden_layer_sizes=_hidden(cfg),
                             activation=linen.relu, distribution_type="normal")


def es_networks(cfg: BaselineConfig):
    """brax's make_es_networks with a NormalDistribution (its own is fixed to tanh-normal)."""
    from brax.training import distribution, networks
    from brax.training.agents.es.networks import ESNetworks
    from brax.training.types import identity_observation_preprocessor

    def make(observation_size, action_size, preprocess_observations_fn=identity_observation_preprocessor):
        policy = networks.make_policy_network(action_size, observation_size,
                                              preprocess_observations_fn=preprocess_observations_fn,
                                              hidden_layer_sizes=_hidden(cfg), activation=linen.relu,
                                              distribution_type="normal", init_noise_std=cfg.es.init_noise_std)
        return ESNetworks(policy_network=policy,
                          parametric_action_distribution=distribution.NormalDistribution(event_size=action_size))
    return make


# -- training ----------------------------------------------------------------------------------
def _method(name: str):
    from training.baselines import es, ppo, qtopt, sac
    return {"ppo": ppo, "sac": sac, "es": es, "qtopt": qtopt}[name]


def device_bytes_limit() -> int | None:
    """The memory of the accelerator the seeds train on (training.budget.device_bytes); None on
    a CPU, where all seeds train together in the host's memory."""
    from training import budget
    return None if jax.default_backend() == "cpu" else budget.device_bytes()


def program_memory(cfg: BaselineConfig, n: int):
    """XLA's compiled memory analysis of the method's epoch for n seeds stacked (compiled here,
    not run): its argument_, output_ and temp_size_in_bytes."""
    sched = schedule(cfg)
    method = _method(cfg.method)
    # the method's parts are built (and cached) here, outside eval_shape's trace, never inside it
    program = method.schedule(cfg, sched.num_timesteps, sched.num_evals, seeds=True).loop.program
    one = jax.eval_shape(lambda: method.initial_state(cfg, sched.num_timesteps, sched.num_evals))
    stacked = jax.tree.map(lambda x: jax.ShapeDtypeStruct((n,) + x.shape, x.dtype), one)
    return program.lower(stacked).compile().memory_analysis()


def program_bytes(cfg: BaselineConfig, n: int) -> int:
    """Device memory of the method's epoch for n seeds stacked: arguments, outputs, temporaries."""
    m = program_memory(cfg, n)
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes)


def seeds_per_program(cfg: BaselineConfig, n: int, log=None) -> int:
    """How many of n seeds one program trains at once: all of them where their stacked epoch
    fits in 90% of the device's memory (device_bytes_limit; always on a CPU), else as many as
    fit in proportion (the epoch's memory grows with the seeds stacked), at least 1."""
    limit = device_bytes_limit() if n > 1 else None
    if limit is None:
        return n
    need = program_bytes(cfg, n)
    if need <= 0.9 * limit:
        return n
    k = max(1, min(n - 1, int(0.9 * limit * n // need)))
    if log is not None:
        log(f"{cfg.method}: {n} seeds as one program need {need / 2**30:.1f} GiB of device memory "
            f"(this device holds {limit / 2**30:.1f} GiB): trained {k} at a time")
    return k


def out_of_memory(err: BaseException) -> bool:
    """Whether err is XLA's refusal to allocate device memory (RESOURCE_EXHAUSTED)."""
    return isinstance(err, jax.errors.JaxRuntimeError) and "RESOURCE_EXHAUSTED" in str(err)


def train(cfg: BaselineConfig, on_policy=None, progress=None, timing: dict | None = None):
    """Run the method's loop (ppo.py, sac.py, es.py: brax's epochs; qtopt.py; the state
    checkpointed under RUN/<method>_state/ and resumed from there) on schedule(cfg); returns the
    final policy (handed_out: PolicyParams, or QT-Opt's QParams).

    on_policy(env_steps, policy) is called at every learning-curve point (brax's: step 0
    and the end of each of its epochs; env_steps is brax's own count, the last one exactly
    schedule(cfg).num_timesteps; a resumed run replays the points before its checkpoint);
    progress(env_steps, metrics) gets the epoch's training metrics. `timing`, a dict, receives
    where the time went: `points` [(env_steps, seconds since the call)] and `epochs`, brax's
    training/sps and training/walltime per epoch (the first epoch of a call includes compiling
    it; SAC's first includes its replay prefill)."""
    return train_seeds([cfg], None if on_policy is None else lambda i, s, p: on_policy(s, p), progress, timing)[0]


def train_seeds(cfgs: list[BaselineConfig], on_policy=None, progress=None, timing: dict | None = None) -> list:
    """train() for configurations that differ only in seed and run directory, as one program
    (their states stacked, the epoch vmapped: resumable.run_seeds); one configuration runs
    unbatched, as brax does. on_policy(i, env_steps, policy) for seed i. Returns the final policy
    of each (handed_out)."""
    timing = {} if timing is None else timing
    cfg, n = cfgs[0], len(cfgs)
    for c in cfgs[1:]:
        if resumable.seedless(c) != resumable.seedless(cfg):
            raise ValueError(f"seeds trained together must differ only in seed and run directory: "
                             f"{c.run.run_dir!r} differs from {cfg.run.run_dir!r} in more")
    t0 = time.perf_counter()
    sched = schedule(cfg)
    steps_seen = [[] for _ in cfgs]
    timing.update(points=[], epochs=[])

    def point(i, step, normalizer, policy):
        steps_seen[i].append(int(step))
        if i == 0:
            timing["points"].append((int(step), round(time.perf_counter() - t0, 3)))
        if on_policy is not None:
            on_policy(i, int(step), handed_out(cfg, normalizer, policy))

    method = _method(cfg.method)
    fresh = [functools.partial(method.initial_state, c, sched.num_timesteps, sched.num_evals) for c in cfgs]
    if n == 1:
        loop = method.schedule(cfg, sched.num_timesteps, sched.num_evals)
        state = resumable.run(loop, resumable.state_dir(cfg.run.run_dir, cfg.method), state_json(cfg), fresh[0],
                              sched.num_timesteps, functools.partial(point, 0), progress, timing)
        finals = [loop.loop.acting(state)]
    else:
        loop = method.schedule(cfg, sched.num_timesteps, sched.num_evals, seeds=True)
        state = resumable.run_seeds(loop, [resumable.state_dir(c.run.run_dir, c.method) for c in cfgs],
                                    [state_json(c) for c in cfgs], fresh, sched.num_timesteps, point, progress, timing)
        normalizer, policy = loop.loop.acting(state)
        finals = [jax.tree.map(lambda x: x[i], (normalizer, policy)) for i in range(n)]
    for seen in steps_seen:
        ran = seen[-1] if seen else None
        if ran != sched.num_timesteps and not cfg.reward.end_at_landing:
            # (end_at_landing: ES counts the steps of episodes that ended early as none)
            raise RuntimeError(f"{cfg.method} ran {ran} environment steps; schedule() expected "
                               f"{sched.num_timesteps} (has brax's arithmetic changed? see brax_env_steps)")
    timing["train_s"] = round(time.perf_counter() - t0, 3)
    return [handed_out(cfg, *f) for f in finals]


def state_json(cfg: BaselineConfig) -> dict:
    """What a state checkpoint of an RL cell must agree with to be resumed: the method's
    settings, the seed, the world, the reward, the policy size and the budget."""
    import json
    run = to_json(cfg.run)
    settings = json.loads(json.dumps(dataclasses.asdict(getattr(cfg, cfg.method))))   # as saved: lists, not tuples
    return {"method": cfg.method, cfg.method: settings, "reward": dataclasses.asdict(cfg.reward),
            "throw_pool": cfg.throw_pool, "num_evals": cfg.num_evals,
            **{k: run[k] for k in ("seed", "world", "policy", "total_trajectories")}}


def handed_out(cfg: BaselineConfig, normalizer, params):
    """The policy a loop hands out, as the evaluation plays it: brax's MLP methods' as a GoalsEye
    framestack PolicyParams (policy_params); QT-Opt's as its (statistics, Q) (qtopt.QParams,
    played by qtopt.cem_policy)."""
    if cfg.method == "qtopt":
        from training.baselines.qtopt import QParams
        return QParams(normalizer, params)
    return policy_params(cfg, normalizer, params)


def policy_params(cfg: BaselineConfig, normalizer, brax_policy) -> PolicyParams:
    """brax's (running statistics, policy params) -> GoalsEye framestack PolicyParams (one member)."""
    p = brax_policy["params"]
    mlp = p["MLP_0"]
    layers = cfg.run.policy.layers
    mean, std = np.asarray(normalizer.mean, np.float32), np.asarray(normalizer.std, np.float32)
    net = {}
    for i in range(layers):
        w, b = np.asarray(mlp[f"hidden_{i}"]["kernel"]), np.asarray(mlp[f"hidden_{i}"]["bias"])
        if i == 0:   # (x - m) / s @ W + b  ==  x @ (W / s) + (b - (m / s) @ W)
            w, b = w / std[:, None], b - (mean / std) @ w
        net[f"dense{i}"] = {"kernel": jnp.asarray(w, jnp.float32), "bias": jnp.asarray(b, jnp.float32)}
    net["head"] = {"kernel": jnp.asarray(p["Dense_0"]["kernel"], jnp.float32),
                   "bias": jnp.asarray(p["Dense_0"]["bias"], jnp.float32)}
    o, w = cfg.run.world.obs_size, cfg.run.world
    norm = Normalizer(jnp.zeros(o), jnp.ones(o), jnp.asarray(w.robot.home, jnp.float32), jnp.asarray(reach(w)))
    return PolicyParams({"params": net}, norm)


def save_policy(cfg: BaselineConfig, params: PolicyParams, trajectories: int, step: int = 1) -> str:
    """Write `params` as a GoalsEye checkpoint of cfg.run (one member; the optimizer state and
    the cache are the template's, empty) under cfg.run.run_dir/checkpoints; returns the directory.
    brax's MLP methods only: QT-Opt's policy is no MLP (qtopt.check_exportable)."""
    import os
    if cfg.method not in BRAX_METHODS:
        raise ValueError(f"{cfg.method}'s policy is not an MLP: it has no GoalsEye checkpoint")
    tmpl = checkpoint.template(cfg.run)
    one = jax.tree.map(lambda x: jnp.asarray(x)[None], params)
    state = tmpl.state._replace(params=one, ema=one)
    ck = tmpl._replace(state=state, key=jax.random.key_data(jax.random.PRNGKey(cfg.run.seed)),
                       counters=checkpoint.Counters(jnp.int32(1), jnp.int32(trajectories), jnp.int32(0)))
    d = os.path.join(cfg.run.run_dir, "checkpoints")
    checkpoint.save(d, step, ck, {**to_json(cfg.run), "absorbed_data": []}, keep=cfg.run.keep_checkpoints)
    return d


def run_config(method: str, base: RunConfig) -> RunConfig:
    """The RunConfig a baseline checkpoint is saved with: the base's world, policy (one member),
    budget and evaluation; preset names the method; the cache minimal (it stays empty)."""
    return dataclasses.replace(base, preset=f"baseline-{method}", demos=0, pretrain_steps=0, practice=True,
                               episodes_per_ssp=1, train=dataclasses.replace(base.train, members=1, capacity=1))


def timed_train(cfg: BaselineConfig, on_policy=None, progress=None):
    """train() and its wall time in seconds."""
    t0 = time.perf_counter()
    out = train(cfg, on_policy, progress)
    return out, time.perf_counter() - t0
