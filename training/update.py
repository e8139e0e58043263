"""Optimizer updates of a whole ensemble in one jit-compiled, vmapped step.

Every member samples its own windows from the one shared cache (its own key) and takes its
own Adam step; no Python loop over members. These are one run's functions: the trainer vmaps
them over its lanes (training.practice), and each device computes the lanes of its block.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from models.config import PolicyConfig
from models.normalizer import Normalizer
from models.policy import PolicyParams, ensemble_size, init_ensemble
from training.cache import Cache
from training.config import TrainConfig
from training.loss import lstm_kernel, policy_loss
from training.sampler import sample_subsequences


class TrainState(NamedTuple):
    params: PolicyParams    # leaves [N, ...] the weights the optimizer steps
    opt_state: Any          # optax state of params.net, leaves [N, ...]
    step: jnp.ndarray       # [] int32 updates taken
    ema: PolicyParams       # leaves [N, ...] exponential moving average of params: the policy
                            # that acts (practice, evaluation, export); = params if ema_decay = 0


def acting_params(state: TrainState) -> PolicyParams:
    """The parameters that play: the moving average (equal to `params` when ema_decay = 0)."""
    return state.ema


class Knobs(NamedTuple):
    """The TrainConfig settings an ablation varies between the lanes of one program, as data
    (training.seeds): each is a Python float for one run (constants in its program, as written in
    its config) or an array [L] over the lanes of a batch (vmapped with them). `ema_rate` is
    1 - ema_decay computed on the host in double precision, so that a lane's float32 arithmetic is
    the same as that of the run alone."""
    learning_rate: Any
    ema_decay: Any
    ema_rate: Any
    action_noise: Any     # b of practice's held action noise (training.practice)
    demo_fraction: Any    # the demonstrations' share of each batch (training.sampler)


def knobs_of(tcfg: TrainConfig) -> Knobs:
    """One run's knobs: its config's values, as Python floats."""
    return Knobs(float(tcfg.learning_rate), float(tcfg.ema_decay), 1.0 - float(tcfg.ema_decay),
                 float(tcfg.action_noise), float(tcfg.demo_fraction))


def lane_knobs(tcfgs) -> Knobs:
    """The knobs of several runs as float32 arrays [L] (one per lane)."""
    ks = [knobs_of(t) for t in tcfgs]
    return Knobs(*(jnp.asarray(np.array(v, np.float32)) for v in zip(*ks)))


def updated_ema(decay, ema: PolicyParams, params: PolicyParams, rate=None) -> PolicyParams:
    """ema <- decay * ema + (1 - decay) * params (the normalizer is shared, never averaged);
    `rate` is 1 - decay when decay is a lane's array (Knobs.ema_rate).

    A small-batch imitation loss is noisy: the landing point is sensitive to the stroke's timing,
    and single Adam iterates swing by 15-20 points of success from one evaluation to the next
    (docs/RESULTS.md); the average over the last ~1 / (1 - decay) steps does not."""
    if isinstance(decay, float) and decay == 0.0:
        return params
    rate = 1.0 - decay if rate is None else rate
    net = jax.tree.map(lambda a, p: decay * a + rate * p, ema.net, params.net)
    return params._replace(net=net)


def optimizer(tcfg: TrainConfig, learning_rate=None) -> optax.GradientTransformation:
    """Global-norm clipping then Adam (at `learning_rate`, a lane's value, or the config's)."""
    lr = tcfg.learning_rate if learning_rate is None else learning_rate
    return optax.chain(optax.clip_by_global_norm(tcfg.grad_clip), optax.adam(lr))


def init_train_state(key, pcfg: PolicyConfig, tcfg: TrainConfig, norm: Normalizer) -> TrainState:
    """`tcfg.members` freshly initialized members sharing the normalizer."""
    params = init_ensemble(key, pcfg, norm, tcfg.members)
    return TrainState(params, jax.vmap(optimizer(tcfg).init)(params.net), jnp.int32(0), params)


def member_update(pcfg: PolicyConfig, tcfg: TrainConfig, params: PolicyParams, opt_state, cache: Cache, key,
                  learning_rate=None, demo_fraction=None):
    """One member: sample a batch, one optimizer step -> (params, opt_state, loss []).
    learning_rate, demo_fraction: a lane's (Knobs), None: the config's."""
    f = tcfg.demo_fraction if demo_fraction is None else demo_fraction
    batch = sample_subsequences(key, cache, tcfg.window, tcfg.batch_size, pcfg.input_frames, pcfg.obs_size, f,
                                tcfg.balance)
    loss, grads = jax.value_and_grad(
        lambda net: policy_loss(pcfg, params._replace(net=net), batch, tcfg.update_dtype,
                                lstm_kernel(pcfg, tcfg)))(params.net)
    updates, opt_state = optimizer(tcfg, learning_rate).update(grads, opt_state, params.net)
    return params._replace(net=optax.apply_updates(params.net, updates)), opt_state, loss


def _ensemble_update(pcfg, tcfg, state: TrainState, cache: Cache, key, knobs: Knobs | None = None):
    kn = knobs_of(tcfg) if knobs is None else knobs
    keys = jax.random.split(key, ensemble_size(state.params))
    update = jax.vmap(lambda p, o, k: member_update(pcfg, tcfg, p, o, cache, k, kn.learning_rate, kn.demo_fraction))
    params, opt_state, loss = update(state.params, state.opt_state, keys)
    ema = updated_ema(kn.ema_decay, state.ema, params, kn.ema_rate)
    return TrainState(params, opt_state, state.step + 1, ema), loss


def make_train_step(pcfg: PolicyConfig, tcfg: TrainConfig):
    """jit-compiled `train_step(state, cache, key) -> (state, loss [N])`: one update per member."""
    return jax.jit(lambda state, cache, key: _ensemble_update(pcfg, tcfg, state, cache, key))


def train_loop_fn(pcfg: PolicyConfig, tcfg: TrainConfig, num_steps: int):
    """The pure `train_loop(state, cache, key, knobs=None) -> (state, loss [num_steps, N])`:
    `num_steps` updates as one scan (vmapped over lanes by the trainer, or inside a practice
    round); `knobs` (Knobs) a lane's settings, None: the config's."""
    def loop(state, cache, key, knobs=None):
        body = lambda s, k: _ensemble_update(pcfg, tcfg, s, cache, k, knobs)  # noqa: E731
        return jax.lax.scan(body, state, jax.random.split(key, num_steps))
    return loop


def make_train_loop(pcfg: PolicyConfig, tcfg: TrainConfig, num_steps: int):
    """jit-compiled `train_loop(state, cache, key) -> (state, loss [num_steps, N])`: `num_steps`
    updates of one run in one call (a scan)."""
    return jax.jit(train_loop_fn(pcfg, tcfg, num_steps))
