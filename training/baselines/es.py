"""OpenAI-ES as brax 0.14.2's es.train runs it, with its state outside the call, so that an ES
cell saves its whole state after every epoch and a stopped cell resumes where it stopped.

brax's es.train keeps its training state (policy, Adam moments, observation statistics, RNG)
inside one Python call and offers no restore; an ES cell at Table I's 120k trajectories or an
extended ES curve can outlast a device call. This module runs brax's epoch unchanged in
substance: the same network (agents.es_networks), fitness shaping ORIGINAL, antithetic
perturbations of every parameter, brax's running observation statistics, optax Adam, and the
same splits of the same key, on one device (brax's shard_map over one device is the identity).
tests/test_baselines.py compares it with es.train itself.

What brax's loop also does and this one does not: its evaluator's episode-reward rollout at
each curve point (the strict-metric curve of eval/baselines.py replaces it, as for PPO).

The state is checkpointed under RUN/es_state/ (resumable.py) every `ESConfig.checkpoint_every`
epochs and at every curve point, with the curve's policies so far: a resumed cell's curve is the
uninterrupted cell's curve.
"""
from __future__ import annotations

import dataclasses
import functools

import flax
import jax
import jax.numpy as jnp
import optax

from training.baselines import resumable


@flax.struct.dataclass
class ESState:
    """brax es.train's TrainingState and the loop's key: everything the next epoch needs."""
    normalizer_params: object   # brax running_statistics.RunningStatisticsState
    optimizer_state: object     # optax Adam state of policy_params
    policy_params: object       # the policy network's params (the distribution's mean and std)
    num_env_steps: jax.Array    # [] int32 environment steps run (brax keeps a UInt64; 120k x 160 fits int32)
    key: jax.Array              # [2] uint32 the loop's key, as brax splits it: key, epoch_key = split(key)


@dataclasses.dataclass(frozen=True)
class Parts:
    """What one ES configuration compiles: the wrapped environment, the network, the optimizer
    and the jitted epoch (ESState -> (ESState, metrics))."""
    env: object
    network: object
    optimizer: object
    epoch: object


def parts(cfg) -> Parts:
    """brax es.train's setup for cfg (agents.BaselineConfig with method 'es'), built once per
    configuration in a process whatever its seed and run directory (the epoch compiles once)."""
    return _parts(resumable.seedless(cfg))


def keys(seed: int) -> tuple[jax.Array, jax.Array]:
    """(network key, the loop's first key) as es.train splits PRNGKey(seed) (raw uint32 [2])."""
    key, network_key, _eval_key, _rng_key = jax.random.split(jax.random.PRNGKey(seed), 4)
    return network_key, key


@functools.lru_cache(maxsize=4)
def _parts(cfg) -> Parts:
    from brax.training.acme import running_statistics

    from training.baselines import agents
    from training.baselines.env import GoalEnv, wrap_fresh
    e, h = cfg.es, cfg.run.world.horizon
    num_envs = 2 * e.population_size
    env = wrap_fresh(GoalEnv(cfg.run.world, cfg.reward), episode_length=h, action_repeat=1, pool=cfg.throw_pool)
    network = agents.es_networks(cfg)(observation_size=env.observation_size, action_size=env.action_size,
                                      preprocess_observations_fn=running_statistics.normalize)
    optimizer = optax.adam(learning_rate=e.learning_rate)
    policy = jax.vmap(network.policy_network.apply, in_axes=(None, 0, 0))

    def run_step(carry, _):
        env_state, params, key, total, active, norm = carry
        key, key_sample = jax.random.split(key)
        actions = network.parametric_action_distribution.sample(policy(norm, params, env_state.obs), key_sample)
        nstate = env.step(env_state, actions)
        total = total + nstate.reward * active
        return (nstate, params, key, total, active * (1 - nstate.done), norm), (env_state.obs, active)

    def run_episode(norm, params, key):
        """[num_envs] returns, [h, num_envs, obs] observations, [h, num_envs] their weights."""
        key_scan, key_reset = jax.random.split(key)
        first = env.reset(jax.random.split(key_reset, num_envs))
        carry = (first, params, key_scan, first.reward, jnp.ones_like(first.reward), norm)
        (_, _, _, total, _, _), (obs, weights) = jax.lax.scan(run_step, carry, (), length=h)
        return total, obs, weights

    def delta(param, noise, weights):
        weights = jnp.reshape(weights, [e.population_size] + [1] * (noise.ndim - 1))
        return -(jnp.sum(noise * weights, axis=0) / e.population_size)   # l2coeff 0, as brax's default

    @jax.jit
    def epoch(state: ESState):
        key, epoch_key = jax.random.split(state.key)
        key_noise_eval = jax.random.split(epoch_key, 3)
        key_noise, key_eval = key_noise_eval[1], key_noise_eval[2]
        params = jax.tree.map(lambda x: jnp.repeat(x[None], e.population_size, axis=0), state.policy_params)
        leaves, treedef = jax.tree.flatten(params)
        keys = jax.random.split(key_noise, len(leaves))
        noise = jax.tree.unflatten(treedef, [jax.random.normal(k, x.shape, x.dtype) for k, x in zip(keys, leaves)])
        both = jax.tree.map(lambda p, n: jnp.concatenate([p + n * e.perturbation_std, p - n * e.perturbation_std]),
                            params, noise)
        scores, obs, weights = run_episode(state.normalizer_params, both, jax.random.split(key_eval, 1)[0])
        obs, weights = obs.reshape((-1,) + obs.shape[2:]), weights.reshape((-1,) + weights.shape[2:])
        norm = running_statistics.update(state.normalizer_params, obs, weights=weights)
        plus, minus = jnp.split(scores.reshape(-1), 2)
        step = jax.tree.map(functools.partial(delta, weights=plus - minus), state.policy_params, noise)
        updates, opt = optimizer.update(step, state.optimizer_state)
        policy_params = optax.apply_updates(state.policy_params, updates)
        metrics = {"params_norm": optax.global_norm(policy_params), "eval_scores_mean": jnp.mean(scores),
                   "eval_scores_std": jnp.std(scores)}
        return ESState(norm, opt, policy_params, state.num_env_steps + jnp.sum(weights, dtype=jnp.int32),
                       key), metrics

    return Parts(env, network, optimizer, epoch)


def initial_state(cfg, num_timesteps: int = 0, num_evals: int = 0) -> ESState:
    """brax es.train's initial TrainingState (same network key), step 0."""
    from brax.training.acme import running_statistics, specs
    p = parts(cfg)
    network_key, key = keys(cfg.run.seed)
    norm = running_statistics.init_state(specs.Array((p.env.observation_size,), jnp.dtype("float32")))
    params = p.network.policy_network.init(network_key)
    return ESState(norm, p.optimizer.init(params), params, jnp.int32(0), key)


def eval_steps(num_timesteps: int, num_evals: int) -> list[int]:
    """The environment-step thresholds after which brax's loop evaluates (it also evaluates at 0
    when num_evals > 1): next_eval_step and its successors, as es.train computes them."""
    after = max(num_evals - 1, 1)
    between = num_timesteps // after
    return [num_timesteps - (after - 1 - i) * between for i in range(after)]


def schedule(cfg, num_timesteps: int, num_evals: int, seeds: bool = False) -> resumable.Schedule:
    """The loop (its epoch vmapped over stacked seeds if `seeds`) and brax's curve points: 0 when
    num_evals > 1, then eval_steps."""
    epoch = parts(cfg).epoch
    epoch = resumable.over_seeds(epoch) if seeds else epoch
    loop = resumable.Loop(epoch=epoch, steps=lambda s: resumable.first_int(s.num_env_steps, seeds),
                          acting=lambda s: (s.normalizer_params, s.policy_params),
                          unit=2 * cfg.es.population_size * cfg.run.world.horizon, program=epoch)
    return resumable.Schedule(loop, eval_steps(num_timesteps, num_evals), num_evals > 1, cfg.es.checkpoint_every)
