"""SAC as brax 0.14.2's sac.train runs it with this project's settings, with its state outside the
call, so that a SAC cell saves its whole state (replay buffer included) after every epoch and a
stopped cell resumes.

brax's sac.train keeps its optimizer states, target networks, replay buffer, environments and
RNG inside one call (`restore_checkpoint_path` brings back only the policy and the observation
statistics). This module runs brax's replay prefill and training epoch for the settings
agents._train passes it (SACConfig; brax's defaults elsewhere: tau 0.005, reward scaling 1,
alpha learned with Adam at 3e-4), from brax's own pieces: its networks (agents.sac_networks),
sac_losses.make_losses, gradients.gradient_update_fn, acting.actor_step, the
UniformSamplingQueue replay buffer, running_statistics and optax Adam, with the same splits of
the same key, on one device (brax's pmap over one device is the identity). tests/test_baselines.py
compares it with sac.train itself.

The state is checkpointed under RUN/sac_state/ at every curve point (resumable.py). The replay
buffer is most of it: max_replay_size transitions of 2 x observation + action + 3 values
(SACConfig's 2,000,000 x 267 float32 is ~2.1 GB per checkpoint at the GPU settings; two are kept).
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
class SACState:
    """Everything brax's SAC loop carries from one epoch to the next."""
    training: object          # brax sac TrainingState
    env: object               # the wrapped environments' state (brax State), [num_envs, ...]
    buffer: object            # the replay buffer's state (data, positions, its key)
    key: jax.Array            # [2] uint32 brax's local_key: epoch_key, local_key = split(local_key)


@dataclasses.dataclass(frozen=True)
class Parts:
    env: object
    network: object
    optimizers: tuple         # (alpha, policy, q)
    replay_buffer: object
    prefill: object           # jitted: SACState -> SACState (brax's replay prefill)
    epoch: object             # jitted: SACState -> (SACState, metrics)
    prefill_steps: int        # environment steps of the prefill
    unit: int                 # environment steps per epoch


def parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    """brax sac.train's setup for cfg (agents.BaselineConfig, method 'sac') and a schedule, built
    once per configuration in a process whatever its seed and run directory."""
    return _parts(resumable.seedless(cfg),
                  num_timesteps, num_evals)


def keys(seed: int):
    """(network key, replay buffer key, environment key, the loop's first key) as sac.train
    splits PRNGKey(seed) on process 0."""
    rng, _ = jax.random.split(jax.random.PRNGKey(seed))
    global_key, local_key = jax.random.split(rng)
    local_key = jax.random.fold_in(local_key, 0)
    local_key, rb_key, env_key, _eval_key = jax.random.split(local_key, 4)
    return global_key, rb_key, env_key, local_key


_seeds_queue = resumable.seeds_queue   # (moved: QT-Opt's loop shares it)


@functools.lru_cache(maxsize=4)
def _parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    from brax.training import acting, gradients, replay_buffers
    from brax.training.acme import running_statistics
    from brax.training.agents.sac import losses as sac_losses
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.types import Transition

    from training.baselines import agents
    from training.baselines.env import GoalEnv, wrap_fresh
    s, h = cfg.sac, cfg.run.world.horizon
    prefill_actor_steps = -(-s.min_replay_size // s.num_envs)
    prefill_steps = prefill_actor_steps * s.num_envs
    steps_per_epoch = -(-(num_timesteps - prefill_steps) // (max(num_evals - 1, 1) * s.num_envs))
    env = wrap_fresh(GoalEnv(cfg.run.world, cfg.reward), episode_length=h, action_repeat=1, pool=cfg.throw_pool)
    obs_size, action_size = env.observation_size, env.action_size
    network = agents.sac_networks(cfg)(observation_size=obs_size, action_size=action_size,
                                       preprocess_observations_fn=running_statistics.normalize)
    make_policy = sac_networks.make_inference_fn(network)
    alpha_opt, policy_opt, q_opt = optax.adam(3e-4), optax.adam(s.learning_rate), optax.adam(s.learning_rate)
    dummy_obs = jnp.zeros((obs_size,))
    dummy = Transition(observation=dummy_obs, action=jnp.zeros((action_size,)), reward=0.0, discount=0.0,
                       next_observation=dummy_obs, extras={"state_extras": {"truncation": 0.0}, "policy_extras": {}})
    buffer = _seeds_queue(replay_buffers)(max_replay_size=s.max_replay_size, dummy_data_sample=dummy,
                                          sample_batch_size=s.batch_size * s.grad_updates_per_step)
    alpha_loss, critic_loss, actor_loss = sac_losses.make_losses(sac_network=network, reward_scaling=1.0,
                                                                 discounting=s.discounting, action_size=action_size)
    alpha_update = gradients.gradient_update_fn(alpha_loss, alpha_opt, pmap_axis_name=None)
    critic_update = gradients.gradient_update_fn(critic_loss, q_opt, pmap_axis_name=None)
    actor_update = gradients.gradient_update_fn(actor_loss, policy_opt, pmap_axis_name=None)
    tau = 0.005

    def sgd_step(carry, transitions):
        ts, key = carry
        key, key_alpha, key_critic, key_actor = jax.random.split(key, 4)
        a_loss, alpha_params, alpha_state = alpha_update(ts.alpha_params, ts.policy_params, ts.normalizer_params,
                                                         transitions, key_alpha, optimizer_state=ts.alpha_optimizer_state)
        alpha = jnp.exp(ts.alpha_params)
        c_loss, q_params, q_state = critic_update(ts.q_params, ts.policy_params, ts.normalizer_params,
                                                  ts.target_q_params, alpha, transitions, key_critic,
                                                  optimizer_state=ts.q_optimizer_state)
        p_loss, policy_params, policy_state = actor_update(ts.policy_params, ts.normalizer_params, ts.q_params,
                                                           alpha, transitions, key_actor,
                                                           optimizer_state=ts.policy_optimizer_state)
        target = jax.tree.map(lambda x, y: x * (1 - tau) + y * tau, ts.target_q_params, q_params)
        metrics = {"critic_loss": c_loss, "actor_loss": p_loss, "alpha_loss": a_loss, "alpha": jnp.exp(alpha_params)}
        ts = ts.replace(policy_optimizer_state=policy_state, policy_params=policy_params, q_optimizer_state=q_state,
                        q_params=q_params, target_q_params=target, gradient_steps=ts.gradient_steps + 1,
                        alpha_optimizer_state=alpha_state, alpha_params=alpha_params)
        return (ts, key), metrics

    def experience(ts, env_state, buffer_state, key):
        policy = make_policy((ts.normalizer_params, ts.policy_params))
        env_state, transitions = acting.actor_step(env, env_state, policy, key, extra_fields=("truncation",))
        norm = running_statistics.update(ts.normalizer_params, transitions.observation)
        ts = ts.replace(normalizer_params=norm, env_steps=ts.env_steps + s.num_envs)
        return ts, env_state, buffer.insert(buffer_state, transitions)

    def training_step(ts, env_state, buffer_state, key):
        experience_key, training_key = jax.random.split(key)
        ts, env_state, buffer_state = experience(ts, env_state, buffer_state, experience_key)
        buffer_state, transitions = buffer.sample(buffer_state)
        transitions = jax.tree.map(lambda x: jnp.reshape(x, (s.grad_updates_per_step, -1) + x.shape[1:]), transitions)
        (ts, _), metrics = jax.lax.scan(sgd_step, (ts, training_key), transitions)
        metrics["buffer_current_size"] = buffer.size(buffer_state)
        return ts, env_state, buffer_state, metrics

    @jax.jit
    def prefill(st: SACState) -> SACState:
        prefill_key, local_key = jax.random.split(st.key)

        def f(carry, _):
            ts, env_state, buffer_state, key = carry
            key, new_key = jax.random.split(key)
            ts, env_state, buffer_state = experience(ts, env_state, buffer_state, key)
            return (ts, env_state, buffer_state, new_key), ()
        ts, env_state, buffer_state, _ = jax.lax.scan(
            f, (st.training, st.env, st.buffer, jax.random.split(prefill_key, 1)[0]), (),
            length=prefill_actor_steps)[0]
        return SACState(ts, env_state, buffer_state, local_key)

    @jax.jit
    def epoch(st: SACState):
        epoch_key, local_key = jax.random.split(st.key)

        def f(carry, _):
            ts, env_state, buffer_state, k = carry
            k, new_key = jax.random.split(k)
            ts, env_state, buffer_state, metrics = training_step(ts, env_state, buffer_state, k)
            return (ts, env_state, buffer_state, new_key), metrics
        (ts, env_state, buffer_state, _), metrics = jax.lax.scan(
            f, (st.training, st.env, st.buffer, jax.random.split(epoch_key, 1)[0]), (), length=steps_per_epoch)
        return SACState(ts, env_state, buffer_state, local_key), jax.tree.map(jnp.mean, metrics)

    return Parts(env, network, (alpha_opt, policy_opt, q_opt), buffer, prefill, epoch, prefill_steps,
                 steps_per_epoch * s.num_envs)


def initial_state(cfg, num_timesteps: int, num_evals: int) -> SACState:
    """brax sac.train's initial TrainingState, environments and empty replay buffer (same keys),
    before the prefill: step 0."""
    from brax.training import types
    from brax.training.acme import running_statistics, specs
    from brax.training.agents.sac.train import TrainingState
    pt = parts(cfg, num_timesteps, num_evals)
    alpha_opt, policy_opt, q_opt = pt.optimizers
    global_key, rb_key, env_key, local_key = keys(cfg.run.seed)
    key_policy, key_q = jax.random.split(global_key)
    log_alpha = jnp.asarray(0.0, dtype=jnp.float32)
    policy_params = pt.network.policy_network.init(key_policy)
    q_params = pt.network.q_network.init(key_q)
    ts = TrainingState(policy_optimizer_state=policy_opt.init(policy_params), policy_params=policy_params,
                       q_optimizer_state=q_opt.init(q_params), q_params=q_params, target_q_params=q_params,
                       gradient_steps=types.UInt64(hi=0, lo=0), env_steps=types.UInt64(hi=0, lo=0),
                       alpha_optimizer_state=alpha_opt.init(log_alpha), alpha_params=log_alpha,
                       normalizer_params=running_statistics.init_state(
                           specs.Array((pt.env.observation_size,), jnp.dtype("float32"))))
    env_state = jax.jit(pt.env.reset)(jax.random.split(env_key, cfg.sac.num_envs))
    buffer_state = jax.jit(pt.replay_buffer.init)(jax.random.split(rb_key, 1)[0])
    strong = jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), (ts, env_state, buffer_state))
    return SACState(*strong, local_key)


def schedule(cfg, num_timesteps: int, num_evals: int, seeds: bool = False) -> resumable.Schedule:
    """The loop (vmapped over stacked seeds if `seeds`; its first epoch is brax's replay prefill
    and first training epoch) and brax's curve points: 0 when num_evals > 1, then after every
    epoch, where brax's evaluator scores its policy."""
    pt = parts(cfg, num_timesteps, num_evals)
    prefill, epoch = (resumable.over_seeds(pt.prefill), resumable.over_seeds(pt.epoch)) if seeds else (pt.prefill, pt.epoch)

    def steps(st):
        return resumable.first_int(st.training.env_steps, seeds)

    def first_prefilled(st):
        return epoch(prefill(st) if steps(st) == 0 else st)
    loop = resumable.Loop(epoch=first_prefilled, steps=steps,
                          acting=lambda st: (st.training.normalizer_params, st.training.policy_params), unit=pt.unit,
                          program=epoch)
    return resumable.Schedule(loop, [pt.prefill_steps + pt.unit * (i + 1) for i in range(max(num_evals - 1, 1))],
                              num_evals > 1)
