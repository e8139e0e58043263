"""QT-Opt (Kalashnikov et al. 2018, "QT-Opt: Scalable Deep Reinforcement Learning for Vision-Based
Robotic Manipulation") on GoalEnv, in JAX on the pieces the other RL rows use: the same wrapped
environment and reward (env.py), brax's UniformSamplingQueue replay buffer (resumable.seeds_queue,
as SAC's), brax's running observation statistics, brax's Q network and gradient step, optax Adam,
and SAC's loop (sac.py): a replay prefill, then epochs of actor steps each followed by gradient
steps, the whole state (replay buffer included) checkpointed at every curve point (resumable.py),
seeds stacked and vmapped as one program. No maintained JAX QT-Opt exists (TF-Agents' is
TensorFlow); this is ours, written from the paper. Settings and their sources: QTOptConfig
(training/baselines/config.py).

The method, per QT-Opt:

* Q(s, a): brax's make_q_network with one critic: an MLP (QTOptConfig.hidden, ReLU) on brax's
  normalized observation [k * O] (GoalEnv's frame stack) concatenated with the action [8] in
  GoalEnv's units, the box [-1, 1]^8 (joint targets home + a * reach).
* argmax_a Q(s, a) by the cross-entropy method (`cem`): cem_population actions per iteration,
  the first drawn uniformly from the box (QT-Opt does not say how it starts; the box is the
  whole action space, nothing in it preferred), each later one from the per-dimension Gaussian
  fitted to the previous iteration's cem_elites best, clipped to the box; the best action
  scored is the argmax.
* collecting (and the replay prefill): epsilon-greedy, a uniformly random action in the box with
  probability epsilon, else CEM's argmax of the current Q.
* the Bellman target, clipped double Q-learning as QT-Opt's: y = r + gamma (1 - done)
  min(Qbar1(s', a*), Qbar2(s', a*)), a* CEM's argmax of Qbar1 at s'; Qbar1 is Polyak-averaged
  (target_tau per gradient step), Qbar2 a copy of Q refreshed every target_lag gradient steps
  (so at most that many steps old).
* the loss: 0.5 (Q(s, a) - y)^2, the transitions brax marks truncated left out, as brax's SAC
  critic. QT-Opt's cross-entropy loss needs Q in [0, 1] from its binary grasp reward;
  RewardConfig's reward is shaped and signed.

What the loop hands out at a curve point is (observation statistics, Q parameters) (`QParams`),
played by `cem_policy`: CEM's argmax at every control step, no exploration. That is not a
GoalsEye MLP, so it is not saved as a GoalsEye checkpoint: eval/baselines.py scores its curve
and its final evaluation in-process on the goals and throws every cell uses, and `ttmjx eval` /
`ttmjx export` refuse a QT-Opt run with one line (`check_exportable`).
"""
from __future__ import annotations

import dataclasses
import functools
import os
from typing import Callable, NamedTuple

import flax
import jax
import jax.numpy as jnp
import optax

from training.baselines import resumable

ACTION_SIZE = 8   # GoalEnv.action_size: the 8 joint targets


class QParams(NamedTuple):
    """QT-Opt's policy as eval/baselines.py plays it (cem_policy)."""
    normalizer: object        # brax running_statistics.RunningStatisticsState of the observation [k * O]
    q: object                 # the Q network's parameters


@flax.struct.dataclass
class TrainingState:
    """The learner's state (QT-Opt's Q, its two target networks, Adam, the observation statistics)."""
    optimizer_state: object
    q_params: object
    target_params: object     # Qbar1: Polyak-averaged
    lagged_params: object     # Qbar2: Q as it was at the last refresh (every target_lag gradient steps)
    normalizer_params: object
    env_steps: jax.Array      # [] int32 environment steps run (120k x 160 = 19.2M fits)
    gradient_steps: jax.Array  # [] int32


@flax.struct.dataclass
class QTOptState:
    """Everything the loop carries from one epoch to the next."""
    training: TrainingState
    env: object               # the wrapped environments' state (brax State), [num_envs, ...]
    buffer: object            # the replay buffer's state (data, positions, its key)
    key: jax.Array            # [2] uint32: epoch_key, key = split(key) per epoch


@dataclasses.dataclass(frozen=True)
class Parts:
    env: object
    network: object           # brax FeedForwardNetwork: apply(normalizer, params, obs [..., O], action [..., 8]) -> [..., 1]
    optimizer: object
    replay_buffer: object
    prefill: object           # jitted: QTOptState -> QTOptState
    epoch: object             # jitted: QTOptState -> (QTOptState, metrics)
    prefill_steps: int        # environment steps of the prefill
    unit: int                 # environment steps per epoch


# -- CEM ---------------------------------------------------------------------------------------
def cem(score: Callable, key, action_size: int, iterations: int, population: int, elites: int):
    """argmax of `score` over the action box [-1, 1]^A by the cross-entropy method, for ONE state
    (vmap it over a batch). score: actions [P, A] -> values [P]. The first population is uniform
    on the box, each later one drawn from the Gaussian (per dimension) fitted to the previous
    population's `elites` best and clipped to the box.

    Returns (action [A], value []): the best of every action scored; and (mean [A], std [A]):
    the Gaussian fitted to the last population's elites, CEM's own estimate of where the maximum
    is and how sure it is (tests/test_qtopt.py holds it to that)."""
    def fit(actions, values):
        e = actions[jax.lax.top_k(values, elites)[1]]
        return jnp.mean(e, 0), jnp.std(e, 0)

    def keep_best(actions, values, best):
        i = jnp.argmax(values)
        better = values[i] > best[1]
        return jnp.where(better, actions[i], best[0]), jnp.where(better, values[i], best[1])

    def iteration(carry, k):
        actions, values, best = carry
        mean, std = fit(actions, values)
        actions = jnp.clip(mean + std * jax.random.normal(k, actions.shape), -1.0, 1.0)
        values = score(actions)
        return (actions, values, keep_best(actions, values, best)), None

    k_first, k_rest = jax.random.split(key)
    actions = jax.random.uniform(k_first, (population, action_size), minval=-1.0, maxval=1.0)
    values = score(actions)
    first = (actions[jnp.argmax(values)], jnp.max(values))
    (actions, values, best), _ = jax.lax.scan(iteration, (actions, values, first),
                                              jax.random.split(k_rest, iterations - 1))
    return best, fit(actions, values)


def q_values(network, normalizer, params, obs, actions):
    """Q(obs, a) of ONE observation [O] for actions [P, A] -> [P]."""
    return network.apply(normalizer, params, jnp.broadcast_to(obs, (actions.shape[0],) + obs.shape), actions)[:, 0]


def argmax_actions(network, q, normalizer, params, obs, key):
    """CEM's argmax of Q for a batch: obs [N, O] -> (actions [N, 8], their Q [N]). q: QTOptConfig."""
    def one(o, k):
        best, _ = cem(functools.partial(q_values, network, normalizer, params, o), k, ACTION_SIZE,
                      q.cem_iterations, q.cem_population, q.cem_elites)
        return best
    return jax.vmap(one)(obs, jax.random.split(key, obs.shape[0]))


# -- the loop ----------------------------------------------------------------------------------
def q_network(cfg):
    """brax's Q network for cfg (agents.BaselineConfig, method 'qtopt') on its observation size
    (GoalEnv.observation_size: the frame stack, flattened), with brax's observation normalization."""
    from brax.training.acme import running_statistics
    from brax.training.networks import make_q_network
    from flax import linen
    w = cfg.run.world
    return make_q_network(w.frame_stack * w.obs_size, ACTION_SIZE,
                          preprocess_observations_fn=running_statistics.normalize,
                          hidden_layer_sizes=tuple(cfg.qtopt.hidden), activation=linen.relu, n_critics=1)


def parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    """The loop's pieces for cfg and a schedule, built once per configuration in a process
    whatever its seed and run directory."""
    return _parts(resumable.seedless(cfg), num_timesteps, num_evals)


def keys(seed: int):
    """(Q network key, replay buffer key, environment key, the loop's first key): raw uint32 keys
    split from PRNGKey(seed)."""
    return tuple(jax.random.split(jax.random.PRNGKey(seed), 4))


@functools.lru_cache(maxsize=4)
def _parts(cfg, num_timesteps: int, num_evals: int) -> Parts:
    from brax.training import acting, gradients, replay_buffers
    from brax.training.acme import running_statistics
    from brax.training.types import Transition

    from training.baselines.env import GoalEnv, wrap_fresh
    q, h = cfg.qtopt, cfg.run.world.horizon
    prefill_actor_steps = -(-q.min_replay_size // q.num_envs)
    prefill_steps = prefill_actor_steps * q.num_envs
    steps_per_epoch = -(-(num_timesteps - prefill_steps) // (max(num_evals - 1, 1) * q.num_envs))
    env = wrap_fresh(GoalEnv(cfg.run.world, cfg.reward), episode_length=h, action_repeat=1, pool=cfg.throw_pool)
    network = q_network(cfg)
    optimizer = optax.adam(q.learning_rate)
    dummy_obs = jnp.zeros((env.observation_size,))
    dummy = Transition(observation=dummy_obs, action=jnp.zeros((ACTION_SIZE,)), reward=0.0, discount=0.0,
                       next_observation=dummy_obs, extras={"state_extras": {"truncation": 0.0}, "policy_extras": {}})
    buffer = resumable.seeds_queue(replay_buffers)(max_replay_size=q.max_replay_size, dummy_data_sample=dummy,
                                                   sample_batch_size=q.batch_size * q.grad_updates_per_step)

    def collecting(ts):
        """brax's Policy (obs [N, O], key) -> (actions [N, 8], extras): epsilon-greedy on CEM's argmax."""
        def policy(obs, key):
            k_cem, k_explore, k_random = jax.random.split(key, 3)
            greedy, _ = argmax_actions(network, q, ts.normalizer_params, ts.q_params, obs, k_cem)
            random = jax.random.uniform(k_random, greedy.shape, minval=-1.0, maxval=1.0)
            explore = jax.random.uniform(k_explore, (obs.shape[0], 1)) < q.epsilon
            return jnp.where(explore, random, greedy), {}
        return policy

    def loss(q_params, normalizer, target_params, lagged_params, tr, key):
        """The squared Bellman error on a batch, and the mean target."""
        a_next, v1 = argmax_actions(network, q, normalizer, target_params, tr.next_observation, key)
        v2 = network.apply(normalizer, lagged_params, tr.next_observation, a_next)[:, 0]
        y = jax.lax.stop_gradient(tr.reward + tr.discount * q.discounting * jnp.minimum(v1, v2))
        error = (network.apply(normalizer, q_params, tr.observation, tr.action)[:, 0] - y) \
            * (1 - tr.extras["state_extras"]["truncation"])
        return 0.5 * jnp.mean(jnp.square(error)), {"target_mean": jnp.mean(y)}

    update = gradients.gradient_update_fn(loss, optimizer, pmap_axis_name=None, has_aux=True)

    def sgd_step(carry, transitions):
        ts, key = carry
        key, key_loss = jax.random.split(key)
        (q_loss, aux), q_params, opt = update(ts.q_params, ts.normalizer_params, ts.target_params,
                                              ts.lagged_params, transitions, key_loss,
                                              optimizer_state=ts.optimizer_state)
        steps = ts.gradient_steps + 1
        target = jax.tree.map(lambda t, p: t * (1 - q.target_tau) + p * q.target_tau, ts.target_params, q_params)
        lagged = jax.tree.map(lambda old, p: jnp.where(steps % q.target_lag == 0, p, old), ts.lagged_params, q_params)
        ts = ts.replace(optimizer_state=opt, q_params=q_params, target_params=target, lagged_params=lagged,
                        gradient_steps=steps)
        return (ts, key), {"q_loss": q_loss, **aux}

    def experience(ts, env_state, buffer_state, key):
        env_state, transitions = acting.actor_step(env, env_state, collecting(ts), key, extra_fields=("truncation",))
        norm = running_statistics.update(ts.normalizer_params, transitions.observation)
        ts = ts.replace(normalizer_params=norm, env_steps=ts.env_steps + q.num_envs)
        return ts, env_state, buffer.insert(buffer_state, transitions)

    def training_step(ts, env_state, buffer_state, key):
        experience_key, training_key = jax.random.split(key)
        ts, env_state, buffer_state = experience(ts, env_state, buffer_state, experience_key)
        buffer_state, transitions = buffer.sample(buffer_state)
        transitions = jax.tree.map(lambda x: jnp.reshape(x, (q.grad_updates_per_step, -1) + x.shape[1:]), transitions)
        (ts, _), metrics = jax.lax.scan(sgd_step, (ts, training_key), transitions)
        metrics["buffer_current_size"] = buffer.size(buffer_state)
        return ts, env_state, buffer_state, metrics

    @jax.jit
    def prefill(st: QTOptState) -> QTOptState:
        prefill_key, key = jax.random.split(st.key)

        def f(carry, k):
            ts, env_state, buffer_state = carry
            return experience(ts, env_state, buffer_state, k), ()
        (ts, env_state, buffer_state), _ = jax.lax.scan(f, (st.training, st.env, st.buffer),
                                                        jax.random.split(prefill_key, prefill_actor_steps))
        return QTOptState(ts, env_state, buffer_state, key)

    @jax.jit
    def epoch(st: QTOptState):
        epoch_key, key = jax.random.split(st.key)

        def f(carry, k):
            ts, env_state, buffer_state = carry
            ts, env_state, buffer_state, metrics = training_step(ts, env_state, buffer_state, k)
            return (ts, env_state, buffer_state), metrics
        (ts, env_state, buffer_state), metrics = jax.lax.scan(f, (st.training, st.env, st.buffer),
                                                              jax.random.split(epoch_key, steps_per_epoch))
        return QTOptState(ts, env_state, buffer_state, key), jax.tree.map(jnp.mean, metrics)

    return Parts(env, network, optimizer, buffer, prefill, epoch, prefill_steps, steps_per_epoch * q.num_envs)


def initial_state(cfg, num_timesteps: int, num_evals: int) -> QTOptState:
    """The Q network (both targets equal to it), Adam, empty observation statistics, the
    environments and the empty replay buffer: step 0, before the prefill."""
    from brax.training.acme import running_statistics, specs
    pt = parts(cfg, num_timesteps, num_evals)
    key_q, key_buffer, key_env, key_loop = keys(cfg.run.seed)
    q_params = pt.network.init(key_q)
    ts = TrainingState(optimizer_state=pt.optimizer.init(q_params), q_params=q_params, target_params=q_params,
                       lagged_params=q_params,
                       normalizer_params=running_statistics.init_state(
                           specs.Array((pt.env.observation_size,), jnp.dtype("float32"))),
                       env_steps=jnp.int32(0), gradient_steps=jnp.int32(0))
    env_state = jax.jit(pt.env.reset)(jax.random.split(key_env, cfg.qtopt.num_envs))
    buffer_state = jax.jit(pt.replay_buffer.init)(key_buffer)
    strong = jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), (ts, env_state, buffer_state))
    return QTOptState(*strong, key_loop)


def schedule(cfg, num_timesteps: int, num_evals: int, seeds: bool = False) -> resumable.Schedule:
    """The loop (vmapped over stacked seeds if `seeds`; its first epoch runs the replay prefill
    first) and its curve points, where SAC's are: 0 when num_evals > 1, then after every epoch."""
    pt = parts(cfg, num_timesteps, num_evals)
    prefill, epoch = (resumable.over_seeds(pt.prefill), resumable.over_seeds(pt.epoch)) if seeds else (pt.prefill, pt.epoch)

    def steps(st):
        return resumable.first_int(st.training.env_steps, seeds)

    def first_prefilled(st):
        return epoch(prefill(st) if steps(st) == 0 else st)
    loop = resumable.Loop(epoch=first_prefilled, steps=steps,
                          acting=lambda st: (st.training.normalizer_params, st.training.q_params), unit=pt.unit,
                          program=epoch)
    return resumable.Schedule(loop, [pt.prefill_steps + pt.unit * (i + 1) for i in range(max(num_evals - 1, 1))],
                              num_evals > 1)


# -- the policy it hands out -------------------------------------------------------------------
def cem_policy(cfg):
    """QT-Opt's policy as a ttmjx Policy for the evaluation's rollouts (params: QParams): CEM's
    argmax of Q at every control step from the step's key, no exploration, mapped to joint
    targets as GoalEnv maps an action. One per configuration (compiled rollouts are cached by
    the policy they play)."""
    return _cem_policy(resumable.seedless(cfg))


@functools.lru_cache(maxsize=4)
def _cem_policy(cfg):
    from training.baselines.env import targets
    from ttmjx.world.env import Policy
    network, q, world = q_network(cfg), cfg.qtopt, cfg.run.world

    def apply(params: QParams, carry, obs, key):
        score = functools.partial(q_values, network, params.normalizer, params.q, obs.frames.reshape(-1))
        (action, _), _ = cem(score, key, ACTION_SIZE, q.cem_iterations, q.cem_population, q.cem_elites)
        return carry, targets(world, action)
    return Policy(init=lambda params, key: jnp.zeros(()), apply=apply)


def check_exportable(path: str) -> None:
    """ValueError if `path` is a QT-Opt baseline run: its policy is CEM over a Q-function, which a
    GoalsEye checkpoint (an MLP) cannot hold, so `ttmjx eval` and `ttmjx export` refuse it."""
    if os.path.isdir(resumable.state_dir(path, "qtopt")):
        raise ValueError(f"{path} is a QT-Opt baseline run: its policy is CEM over a Q-function, not a GoalsEye "
                         f"MLP, so there is no checkpoint to evaluate or export; `ttmjx baseline qtopt` evaluates "
                         f"it in-process (its table's results/qtopt-seed<S>.json)")
