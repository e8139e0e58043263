"""PPO, SAC and ES from brax's own trainers on GoalEnv, configured, not rewritten; their policy
saved as a GoalsEye checkpoint (training/checkpoint.py) so `ttmjx eval` and `ttmjx export` read
it unchanged.

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
  steps long), checked against one batch of the method before anything runs.

The conversion (`policy_params`): brax's policy MLP hidden_i -> MLPNet dense_i, its mean head ->
head; brax's observation normalization (x - m) / s per input value folded into the first layer
(W / s, b - (m / s) W), so the saved Normalizer is the identity on observations; actions
denormalized with act_mean = home, act_std = reach (GoalEnv's affine action map).
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import linen

from models.normalizer import Normalizer
from models.policy import PolicyParams
from training import checkpoint
from training.baselines.config import RewardConfig
from training.baselines.env import GoalEnv, reach, wrap_fresh
from training.runconfig import RunConfig, to_json

METHODS = ("ppo", "sac", "es")


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """brax.training.agents.ppo.train arguments (Playground-like values for MJX tasks)."""
    num_envs: int = 4096
    unroll_length: int = 20
    batch_size: int = 1024
    num_minibatches: int = 32
    num_updates_per_batch: int = 4
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-2
    discounting: float = 0.99
    clipping_epsilon: float = 0.2
    init_noise_std: float = 0.5
    value_hidden: tuple = (256, 256, 256)


@dataclasses.dataclass(frozen=True)
class SACConfig:
    """brax.training.agents.sac.train arguments."""
    num_envs: int = 256
    batch_size: int = 512
    grad_updates_per_step: int = 8
    min_replay_size: int = 65_536
    max_replay_size: int = 2_000_000
    learning_rate: float = 3e-4
    discounting: float = 0.99
    q_hidden: tuple = (256, 256)


@dataclasses.dataclass(frozen=True)
class ESConfig:
    """brax.training.agents.es.train arguments (2 * population_size episodes per update)."""
    population_size: int = 1024
    perturbation_std: float = 0.02
    learning_rate: float = 0.01
    init_noise_std: float = 0.05
    """Std of the actions ES samples in its rollouts (brax ES acts stochastically); also perturbed."""


@dataclasses.dataclass(frozen=True)
class BaselineConfig:
    """One RL baseline run: the method, the GoalsEye RunConfig it is compared with (its world, the
    policy MLP size, trajectory budget, evaluation goals, seed and run directory), the reward and
    the method's brax settings."""
    method: Literal["ppo", "sac", "es"]
    run: RunConfig
    reward: RewardConfig = RewardConfig()
    ppo: PPOConfig = PPOConfig()
    sac: SACConfig = SACConfig()
    es: ESConfig = ESConfig()
    num_evals: int = 5
    """Learning-curve points (strict metric on run.eval_goals goals where the trainer reports its policy)."""
    num_eval_envs: int = 128
    """brax's own evaluator (episode reward) environments."""

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"unknown method {self.method!r}; expected one of {METHODS}")
        if self.run.policy.kind != "framestack":
            raise ValueError(f"RL baselines use an MLP on the frame stack: policy.kind={self.run.policy.kind!r}, "
                             f"expected 'framestack'")
        if self.num_evals < 1 or self.num_eval_envs < 1:
            raise ValueError(f"num_evals={self.num_evals} and num_eval_envs={self.num_eval_envs} must be >= 1")
        need = batch_trajectories(self)
        if self.run.total_trajectories < need:
            raise ValueError(f"trajectory budget {self.run.total_trajectories} is below one batch of "
                             f"{self.method} ({need} trajectories)")

    @property
    def steps(self) -> int:
        """brax num_timesteps: the budget in environment steps (episodes are `horizon` steps)."""
        return self.run.total_trajectories * self.run.world.horizon


def batch_trajectories(cfg: BaselineConfig) -> int:
    """Trajectories of one batch (one update) of the method: the smallest budget that trains."""
    h = cfg.run.world.horizon
    if cfg.method == "ppo":
        p = cfg.ppo
        return -(-p.batch_size * p.num_minibatches * p.unroll_length // h)
    if cfg.method == "sac":
        s = cfg.sac
        return -(-(s.min_replay_size + s.num_envs) // h)
    return 2 * cfg.es.population_size


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
    # One hidden_layer_sizes for the policy and the Q networks in brax: the policy's size wins.
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
def _replicated(x, devices):
    """What jax.device_put_replicated did: x with a leading axis over `devices`, one copy on each."""
    return jax.tree.map(lambda a: jnp.stack([jnp.asarray(a)] * len(devices)), x)


def brax_compat():
    """The one patch: brax 0.14.2's PPO and SAC call jax.device_put_replicated, which JAX 0.10
    removed (it raises AttributeError). Installed for the trainer's call only, as what it did: a
    copy per device along a new leading axis (brax pmaps over that axis)."""
    import contextlib

    @contextlib.contextmanager
    def patched():
        try:
            jax.device_put_replicated
            yield
            return
        except AttributeError:
            pass
        jax.device_put_replicated = _replicated
        try:
            yield
        finally:
            del jax.device_put_replicated
    return patched()


def train(cfg: BaselineConfig, on_policy=None, progress=None):
    """Run brax's trainer; returns (PolicyParams of the final policy, curve rows).

    on_policy(env_steps, PolicyParams) is called where the trainer hands its policy out (PPO: at
    every evaluation point; SAC and ES: at the end only); progress(env_steps, metrics) gets
    brax's own metrics (its evaluator's episode reward)."""
    with brax_compat():
        return _train(cfg, on_policy, progress)


def _train(cfg: BaselineConfig, on_policy=None, progress=None):
    env = GoalEnv(cfg.run.world, cfg.reward)
    h = cfg.run.world.horizon
    common = dict(environment=env, num_timesteps=cfg.steps, episode_length=h, wrap_env_fn=wrap_fresh,
                  normalize_observations=True, seed=cfg.run.seed, num_evals=cfg.num_evals,
                  num_eval_envs=cfg.num_eval_envs, deterministic_eval=True,
                  progress_fn=progress or (lambda *a: None))
    if cfg.method == "ppo":
        from brax.training.agents.ppo import train as ppo
        p = cfg.ppo

        def params_fn(step, make_policy, params):
            if on_policy is not None:
                on_policy(int(step), policy_params(cfg, params[0], params[1]))
        _, params, _ = ppo.train(**common, num_envs=p.num_envs, unroll_length=p.unroll_length,
                                 batch_size=p.batch_size, num_minibatches=p.num_minibatches,
                                 num_updates_per_batch=p.num_updates_per_batch, learning_rate=p.learning_rate,
                                 entropy_cost=p.entropy_cost, discounting=p.discounting,
                                 clipping_epsilon=p.clipping_epsilon, network_factory=ppo_networks(cfg),
                                 policy_params_fn=params_fn, run_evals=cfg.num_evals > 1)
    elif cfg.method == "sac":
        from brax.training.agents.sac import train as sac
        s = cfg.sac
        _, params, _ = sac.train(**common, num_envs=s.num_envs, batch_size=s.batch_size,
                                 grad_updates_per_step=s.grad_updates_per_step, min_replay_size=s.min_replay_size,
                                 max_replay_size=s.max_replay_size, learning_rate=s.learning_rate,
                                 discounting=s.discounting, network_factory=sac_networks(cfg))
    else:
        from brax.training.agents.es import train as es
        e = cfg.es
        _, params, _ = es.train(**common, population_size=e.population_size, perturbation_std=e.perturbation_std,
                                learning_rate=e.learning_rate, network_factory=es_networks(cfg))
    final = policy_params(cfg, params[0], params[1])
    if on_policy is not None and cfg.method != "ppo":
        on_policy(cfg.steps, final)
    return final


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
    the cache are the template's, empty) under cfg.run.run_dir/checkpoints; returns the directory."""
    import os
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
