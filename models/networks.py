"""The two networks, in normalized units: one control step and a whole sequence.

Both take per step `x [S, O]` (S = PolicyConfig.input_frames: 1 for the LSTM, the frame stack
for the MLP); their last layer has PolicyConfig.head_size outputs, read as a normalized action
[8] by models.heads. Training (a sequence) and rollouts (one step at
a time) call the same step function, so the two cannot drift apart.
"""
from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from models.config import PolicyConfig
from models.heads import head_action


class LSTMNet(nn.Module):
    """`layers` stacked LSTM cells and a linear head of `out` values (the paper's policy)."""
    hidden: int
    layers: int
    out: int

    @nn.compact
    def __call__(self, carry, x):
        new_carry = []
        for i in range(self.layers):
            c, x = nn.OptimizedLSTMCell(self.hidden, name=f"lstm{i}")(carry[i], x)
            new_carry.append(c)
        return tuple(new_carry), nn.Dense(self.out, name="head")(x)


class MLPNet(nn.Module):
    """`layers` ReLU layers of `hidden` units and a linear head of `out` values."""
    hidden: int
    layers: int
    out: int

    @nn.compact
    def __call__(self, x):
        for i in range(self.layers):
            x = nn.relu(nn.Dense(self.hidden, name=f"dense{i}")(x))
        return nn.Dense(self.out, name="head")(x)


def zero_carry(cfg: PolicyConfig):
    """The recurrent state at an episode start: per LSTM layer (c [H], h [H]); () for the MLP."""
    if cfg.kind != "lstm":
        return ()
    z = jnp.zeros(cfg.hidden, jnp.float32)
    return tuple((z, z) for _ in range(cfg.layers))


def _module(cfg: PolicyConfig) -> nn.Module:
    net = LSTMNet if cfg.kind == "lstm" else MLPNet
    return net(cfg.hidden, cfg.layers, cfg.head_size)


def init_net(key, cfg: PolicyConfig):
    """Fresh network parameters (a flax params dict) for one member."""
    x = jnp.zeros((cfg.input_frames, cfg.obs_size), jnp.float32)
    if cfg.kind == "lstm":
        return _module(cfg).init(key, zero_carry(cfg), x[0])
    return _module(cfg).init(key, x.reshape(-1))


def net_step_outputs(cfg: PolicyConfig, net_params, carry, x):
    """One control step: x [S, O] normalized -> (carry, the head's outputs [head_size])."""
    want = (cfg.input_frames, cfg.obs_size)
    if tuple(x.shape) != want:
        raise ValueError(f"net_step: input has shape {tuple(x.shape)}, expected {want} "
                         f"(frames, obs_size) for kind={cfg.kind!r}")
    if cfg.kind == "lstm":
        return _module(cfg).apply(net_params, carry, x[0])
    return carry, _module(cfg).apply(net_params, x.reshape(-1))


def net_step(cfg: PolicyConfig, net_params, carry, x):
    """One control step: x [S, O] normalized -> (carry, normalized action [8])."""
    carry, y = net_step_outputs(cfg, net_params, carry, x)
    return carry, head_action(cfg, y)


def net_sequence_outputs(cfg: PolicyConfig, net_params, xs):
    """A sequence from a zero state: xs [L, S, O] normalized -> the head's outputs [L, head_size].
    The same function as net_step_outputs applied step by step (tests/test_models.py), computed
    for training's speed: the LSTM layer by layer."""
    if cfg.kind != "lstm":  # no state: every step independently
        return jax.vmap(lambda x: net_step_outputs(cfg, net_params, (), x)[1])(xs)
    return lstm_sequence(net_params, xs[:, 0])


def net_sequence(cfg: PolicyConfig, net_params, xs):
    """A sequence from a zero state: xs [L, S, O] normalized -> normalized actions [L, 8]."""
    return head_action(cfg, net_sequence_outputs(cfg, net_params, xs))


def gate_weights(cell: dict) -> tuple:
    """(input kernel [I, 4H], recurrent kernel [H, 4H], bias [4H]) of one flax OptimizedLSTMCell,
    gates in its order (i, f, g, o)."""
    cat = lambda name: jnp.concatenate([cell[f"{name}{g}"]["kernel"] for g in "ifgo"], -1)  # noqa: E731
    return cat("i"), cat("h"), jnp.concatenate([cell[f"h{g}"]["bias"] for g in "ifgo"], -1)


def lstm_sequence(net_params, x):
    """LSTMNet over a whole sequence, x [L, O] -> head outputs [L, D], layer by layer: a layer's input
    projection for all L steps is one matrix product outside its recurrence (the sequential scan
    keeps only h @ W_h), which is what a GPU does fast. The cell's arithmetic is flax's
    OptimizedLSTMCell's: z = (h W_h + b) + x W_i; c' = s(f) c + s(i) tanh(g); h' = s(o) tanh(c')."""
    p = net_params["params"]
    layer = 0
    while f"lstm{layer}" in p:
        w_i, w_h, b = gate_weights(p[f"lstm{layer}"])
        z_in = x @ w_i                                       # [L, 4H]
        zero = jnp.zeros(w_h.shape[0], x.dtype)

        def cell(carry, zi, w_h=w_h, b=b):
            c, h = carry
            i, f, g, o = jnp.split(h @ w_h + b + zi, 4, axis=-1)
            c = jax.nn.sigmoid(f) * c + jax.nn.sigmoid(i) * jnp.tanh(g)
            h = jax.nn.sigmoid(o) * jnp.tanh(c)
            return (c, h), h
        x = jax.lax.scan(cell, (zero, zero), z_in)[1]       # [L, H]
        layer += 1
    head = p["head"]
    return x @ head["kernel"] + head["bias"]
