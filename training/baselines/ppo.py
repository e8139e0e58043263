"""PPO as brax 0.14.2's ppo.train runs it with this project's settings, with its state outside the
call, so that a PPO cell saves its whole state after every epoch and a stopped cell resumes.

brax's ppo.train keeps its optimizer state, the environments' state and its RNG inside one call
(`restore_params` brings back only the weights and the observation statistics). This module
runs brax's training epoch for the settings agents._train passes it (PPOConfig; brax's
defaults elsewhere: GAE 0.95, advantages normalized, value loss 0.5, no gradient clipping, no
learning-rate schedule, no resets between epochs), from brax's own pieces: its networks
(agents.ppo_networks), ppo_losses.compute_ppo_loss, acting.generate_unroll, running_statistics
and optax Adam, with the same splits of the same key, on one device (brax's pmap over one
device, its pmean over one member, are identities). tests/test_baselines.py compares it with
ppo.train itself.

The state (brax's TrainingState, the environments' state, the loop's key) is checkpointed under
RUN/ppo_state/ at every curve point (resumable.py), with the curve's policies so far.
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
class PPOState:
    """Everything brax's PPO loop carries from one epoch to the next."""
    training: object          # brax ppo TrainingState: optimizer_state, params, normalizer_params, env_steps
    env: object               # the wrapped environments' state (brax State), [num_envs, ...]
    key: jax.Array            # [2] uint32 brax's local_key: epoch_key, local_key = split(local_key)


@dataclasses.dataclass(frozen=True)
class Parts:
    env: object
    network: object
    optimizer: object
    epoch: object
    unit: int                 # environment steps per epoch


def parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    """brax ppo.train's setup for cfg (agents.BaselineConfig, method 'ppo') and a schedule, built
    once per configuration in a process whatever its seed and run directory."""
    return _parts(resumable.seedless(cfg),
                  num_timesteps, num_evals)


def keys(seed: int):
    """(policy key, value key, environment key, the loop's first key) as ppo.train splits
    PRNGKey(seed) on process 0."""
    global_key, local_key = jax.random.split(jax.random.PRNGKey(seed))
    local_key = jax.random.fold_in(local_key, 0)
    local_key, key_env, _eval_key = jax.random.split(local_key, 3)
    key_policy, key_value = jax.random.split(global_key)
    return key_policy, key_value, key_env, local_key


@functools.lru_cache(maxsize=4)
def _parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    from brax.training import acting
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import losses as ppo_losses
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo.train import TrainingState

    from training.baselines import agents
    from training.baselines.env import GoalEnv, wrap_fresh
    p, h = cfg.ppo, cfg.run.world.horizon
    env_steps_per_training_step = p.batch_size * p.unroll_length * p.num_minibatches
    steps_per_epoch = -(-num_timesteps // (max(num_evals - 1, 1) * env_steps_per_training_step))
    env = wrap_fresh(GoalEnv(cfg.run.world, cfg.reward), episode_length=h, action_repeat=1, pool=cfg.throw_pool)
    network = agents.ppo_networks(cfg)(env.observation_size, env.action_size,
                                       preprocess_observations_fn=running_statistics.normalize)
    make_policy = ppo_networks.make_inference_fn(network)
    optimizer = optax.adam(learning_rate=p.learning_rate)
    loss_fn = functools.partial(ppo_losses.compute_ppo_loss, ppo_network=network, entropy_cost=p.entropy_cost,
                                discounting=p.discounting, clipping_epsilon=p.clipping_epsilon)
    grad_fn = jax.value_and_grad(loss_fn, has_aux=True)

    def minibatch_step(carry, data, normalizer_params):
        opt, params, key = carry
        key, key_loss = jax.random.split(key)
        (_, metrics), grads = grad_fn(params, normalizer_params, data, key_loss)
        updates, opt = optimizer.update(grads, opt)
        metrics["learning_rate"] = jnp.array(p.learning_rate)
        return (opt, optax.apply_updates(params, updates), key), metrics

    def sgd_step(carry, _, data, normalizer_params):
        opt, params, key = carry
        key, key_perm, key_grad = jax.random.split(key, 3)
        shuffled = jax.tree.map(lambda x: jax.random.permutation(key_perm, x).reshape(
            (p.num_minibatches, -1) + x.shape[1:]), data)
        (opt, params, _), metrics = jax.lax.scan(
            functools.partial(minibatch_step, normalizer_params=normalizer_params), (opt, params, key_grad),
            shuffled, length=p.num_minibatches)
        return (opt, params, key), metrics

    def training_step(carry, _):
        ts, state, key = carry
        key_sgd, key_unroll, new_key = jax.random.split(key, 3)
        policy = make_policy((ts.normalizer_params, ts.params.policy, ts.params.value))

        def unroll(c, _):
            s, k = c
            k, next_k = jax.random.split(k)
            s, data = acting.generate_unroll(env, s, policy, k, p.unroll_length,
                                             extra_fields=("truncation", "episode_metrics", "episode_done"))
            return (s, next_k), data
        (state, _), data = jax.lax.scan(unroll, (state, key_unroll), (),
                                        length=p.batch_size * p.num_minibatches // p.num_envs)
        data = jax.tree.map(lambda x: jnp.swapaxes(x, 1, 2), data)
        data = jax.tree.map(lambda x: jnp.reshape(x, (-1,) + x.shape[2:]), data)
        normalizer_params = running_statistics.update(ts.normalizer_params, data.observation)
        (opt, params, _), metrics = jax.lax.scan(
            functools.partial(sgd_step, data=data, normalizer_params=normalizer_params),
            (ts.optimizer_state, ts.params, key_sgd), (), length=p.num_updates_per_batch)
        ts = TrainingState(optimizer_state=opt, params=params, normalizer_params=normalizer_params,
                           env_steps=ts.env_steps + env_steps_per_training_step)
        return (ts, state, new_key), metrics

    @jax.jit
    def epoch(s: PPOState):
        epoch_key, local_key = jax.random.split(s.key)
        (ts, env_state, _), metrics = jax.lax.scan(
            training_step, (s.training, s.env, jax.random.split(epoch_key, 1)[0]), (), length=steps_per_epoch)
        return PPOState(ts, env_state, local_key), jax.tree.map(jnp.mean, metrics)

    return Parts(env, network, optimizer, epoch, steps_per_epoch * env_steps_per_training_step)


def initial_state(cfg, num_timesteps: int, num_evals: int) -> PPOState:
    """brax ppo.train's initial TrainingState and environments (same keys), step 0."""
    from brax.training import types
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.ppo import losses as ppo_losses
    from brax.training.agents.ppo.train import TrainingState
    pt = parts(cfg, num_timesteps, num_evals)
    key_policy, key_value, key_env, local_key = keys(cfg.run.seed)
    params = ppo_losses.PPONetworkParams(policy=pt.network.policy_network.init(key_policy),
                                         value=pt.network.value_network.init(key_value))
    ts = TrainingState(optimizer_state=pt.optimizer.init(params), params=params,
                       normalizer_params=running_statistics.init_state(
                           specs.Array((pt.env.observation_size,), jnp.dtype("float32"))),
                       env_steps=types.UInt64(hi=0, lo=0))
    env_state = jax.jit(pt.env.reset)(jax.random.split(key_env, cfg.ppo.num_envs))
    strong = jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), (ts, env_state))
    return PPOState(*strong, local_key)


def schedule(cfg, num_timesteps: int, num_evals: int, seeds: bool = False) -> resumable.Schedule:
    """The loop (its epoch vmapped over stacked seeds if `seeds`) and brax's curve points: 0 and
    after every epoch (its policy_params_fn)."""
    pt = parts(cfg, num_timesteps, num_evals)
    epoch = resumable.over_seeds(pt.epoch) if seeds else pt.epoch
    loop = resumable.Loop(epoch=epoch, steps=lambda s: resumable.first_int(s.training.env_steps, seeds),
                          acting=lambda s: (s.training.normalizer_params, s.training.params.policy), unit=pt.unit,
                          program=epoch)
    return resumable.Schedule(loop, [pt.unit * (i + 1) for i in range(max(num_evals - 1, 1))], True)
