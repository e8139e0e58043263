"""The LSTM over a batch of whole sequences through cuDNN (`jax.experimental.rnn.lstm`), for the
updates on a GPU.

An update runs the LSTM over 64 windows of 96 steps, forward and backward. As a `lax.scan`, that
is ~420 sequential loop iterations of small kernels (6,677 launches an update of paper-sim's 2x1024
LSTM, docs/BENCHMARKS.md), latency-bound on an H200. cuDNN runs each layer's recurrence in its own
kernels. The arithmetic is flax's OptimizedLSTMCell's, gates in the same order (i, f, g, o), so the
same parameters serve both paths: `cudnn_weights` packs them into cuDNN's flat layout (the layout
`jax.experimental.rnn.unpack_lstm_weights` reads; tests/test_models.py checks the packing against
JAX's own reference implementation, `rnn.lstm_ref`, on the CPU).

cuDNN's primitives have no batching rule, and the updates are vmapped over ensemble members and
over a table's lanes. `_unit_rule` gives them one for an axis of size 1 (one member of one lane:
the axis is dropped around one call). A larger axis is refused: looped over it (`lax.map`) the
calls were slower than the vmapped scan and their gradients were wrong (docs/BENCHMARKS.md), so
training.loss.lstm_kernel takes the scan there.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax.experimental import rnn
from jax.interpreters import batching

from models.networks import gate_weights


def available() -> bool:
    """Whether this JAX can lower the cuDNN LSTM (a CUDA backend with its RNN kernels)."""
    return rnn.gpu_rnn is not None and jax.default_backend() == "gpu"


def lstm_layers(p: dict) -> int:
    """The number of stacked cells `lstm0`, `lstm1`, ... in an LSTMNet's params["params"]."""
    n = 0
    while f"lstm{n}" in p:
        n += 1
    return n


def cudnn_weights(p: dict) -> jax.Array:
    """An LSTMNet's cells (params["params"]) as cuDNN's flat weight vector [P]: every layer's
    W_ih [4H, I] then W_hh [4H, H], then every layer's b_ih [4H] then b_hh [4H]. flax's cell has
    one bias; it goes to b_ih and b_hh is zero (its gradient is dropped)."""
    mats, biases = [], []
    for layer in range(lstm_layers(p)):
        w_i, w_h, b = gate_weights(p[f"lstm{layer}"])          # [I, 4H], [H, 4H], [4H]
        mats += [w_i.T.ravel(), w_h.T.ravel()]
        biases += [b, jnp.zeros_like(b)]
    return jnp.concatenate(mats + biases)


def cudnn_sequence_outputs(net_params, x):
    """LSTMNet over a batch of sequences from a zero state, x [B, L, I] normalized -> the head's
    outputs [B, L, D]; the same function as models.networks.lstm_sequence per sequence."""
    p = net_params["params"]
    layers, hidden = lstm_layers(p), p["lstm0"]["hi"]["kernel"].shape[0]
    batch, length, width = x.shape
    zero = jnp.zeros((layers, batch, hidden), x.dtype)
    y, _, _ = rnn.lstm(x, zero, zero, cudnn_weights(p), jnp.full((batch,), length, jnp.int32),
                       input_size=width, hidden_size=hidden, num_layers=layers, dropout=0.0,
                       bidirectional=False)
    return y @ p["head"]["kernel"] + p["head"]["bias"]


def _unit_rule(primitive):
    """A batching rule for a mapped axis of size 1: the axis dropped, one call, the axis put back."""
    def rule(args, dims, **params):
        size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)      # None: not mapped
        if size != 1:
            raise NotImplementedError(f"{primitive.name} mapped over {size} sets of operands: cuDNN's LSTM serves "
                                      f"one member of one lane (training.loss.lstm_kernel picks the scan otherwise)")
        outs = primitive.bind(*[a if d is None else jnp.squeeze(a, d) for a, d in zip(args, dims)], **params)
        return [o[None] for o in outs], [0] * len(outs)
    return rule


for _p in (rnn.rnn_fwd_p, rnn.rnn_bwd_p):
    if _p not in batching.fancy_primitive_batchers:     # JAX may come to have its own
        batching.primitive_batchers[_p] = _unit_rule(_p)
