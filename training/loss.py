"""The imitation loss over valid steps: the MSE between commanded and predicted actions (the
paper's mean head), or the negative log-likelihood of the commanded actions (the mixture head;
models/heads.py)."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from models import cudnn_lstm
from models.config import PolicyConfig
from models.normalizer import normalize_actions
from models.heads import step_losses
from models.networks import net_sequence_outputs
from models.normalizer import normalize_obs
from models.policy import PolicyParams
from training.config import TrainConfig
from training.sampler import Batch


def masked_mse(pred, target, mask):
    """Scalar mean of (pred - target)^2 over the action dims of the steps where mask is set.

    pred, target [B, k, 8]; mask [B, k] bool. 0 if no step is valid.
    """
    if pred.shape != target.shape or pred.shape[:-1] != mask.shape:
        raise ValueError(f"masked_mse: pred {tuple(pred.shape)}, target {tuple(target.shape)} and "
                         f"mask {tuple(mask.shape)} must be [B, k, 8], [B, k, 8], [B, k]")
    w = jnp.asarray(mask, pred.dtype)[..., None]
    return jnp.sum(w * (pred - target) ** 2) / (jnp.maximum(w.sum(), 1.0) * pred.shape[-1])


def masked_mean(losses, mask):
    """Scalar mean of per-step losses [B, k] over the steps where mask [B, k] is set; 0 if none."""
    if losses.shape != mask.shape:
        raise ValueError(f"masked_mean: losses {tuple(losses.shape)} and mask {tuple(mask.shape)} must be [B, k]")
    w = jnp.asarray(mask, losses.dtype)
    return jnp.sum(w * losses) / jnp.maximum(w.sum(), 1.0)


def lstm_kernel(pcfg: PolicyConfig, tcfg: TrainConfig, lanes: int = 1) -> str:
    """The kernel the updates run the network with: "cudnn" or "scan" (TrainConfig.lstm_kernel
    resolved on this backend for a program of `lanes` lanes). cuDNN serves one member of one
    lane: mapped over several sets of weights it is slower than the vmapped scan and its looped
    gradients were wrong (docs/BENCHMARKS.md, "The updates' LSTM through cuDNN"), so "auto" takes
    the scan there and "cudnn" is refused. Raises ValueError for "cudnn" where it cannot run."""
    if pcfg.kind != "lstm":
        return "scan"
    one = tcfg.members == 1 and lanes == 1
    if tcfg.lstm_kernel == "cudnn":
        if not cudnn_lstm.available():
            raise ValueError(f"--train.lstm-kernel cudnn needs a CUDA GPU with JAX's cuDNN RNN kernels; this backend "
                             f"is {jax.default_backend()!r}; expected --train.lstm-kernel scan or auto")
        if not one:
            raise ValueError(f"--train.lstm-kernel cudnn runs one member of one lane; this program has "
                             f"--train.members {tcfg.members} and {lanes} lane(s); expected auto or scan")
        return "cudnn"
    if tcfg.lstm_kernel == "auto":
        return "cudnn" if one and tcfg.update_dtype == "float32" and cudnn_lstm.available() else "scan"
    return "scan"


def sequence_outputs(cfg: PolicyConfig, net, x, kernel: str = "scan"):
    """The network over a batch of windows from a zero state: x [B, k, S, O] normalized -> the
    head's outputs [B, k, D], through the scan or cuDNN (the same function)."""
    if kernel == "cudnn":
        return cudnn_lstm.cudnn_sequence_outputs(net, x[:, :, 0])
    return jax.vmap(lambda f: net_sequence_outputs(cfg, net, f))(x)


def policy_loss(cfg: PolicyConfig, params: PolicyParams, batch: Batch, dtype: str = "float32",
                kernel: str = "scan"):
    """Scalar loss of one member on a batch, in normalized action units (each joint has unit
    variance in the data, so metres of gantry and radians of wrist weigh alike).

    dtype: the network's arithmetic (TrainConfig.update_dtype). With bfloat16 the weights and the
    normalized inputs are cast for the products and the outputs cast back, so the loss, its
    gradient with respect to the float32 weights and the optimizer stay float32.
    kernel: "scan" or "cudnn" (lstm_kernel)."""
    dt = jnp.dtype(dtype)
    net = params.net if dt == jnp.float32 else jax.tree.map(lambda w: w.astype(dt), params.net)
    x = normalize_obs(params.norm, batch.frames).astype(dt)                        # [B, k, S, O]
    y = sequence_outputs(cfg, net, x, kernel).astype(jnp.float32)                  # [B, k, D]
    target = normalize_actions(params.norm, batch.actions)
    if cfg.head == "mean":      # the paper's loss, written as masked_mse (tests check it against a plain one)
        return masked_mse(y, target, batch.mask)
    return masked_mean(step_losses(cfg, y, target), batch.mask)
