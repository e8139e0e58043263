"""The imitation loss: MSE between commanded and predicted actions over valid steps."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from models.config import PolicyConfig
from models.normalizer import normalize_actions
from models.policy import PolicyParams, predict_sequence
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


def policy_loss(cfg: PolicyConfig, params: PolicyParams, batch: Batch):
    """Scalar loss of one member on a batch, in normalized action units (each joint has unit
    variance in the data, so metres of gantry and radians of wrist weigh alike)."""
    pred = jax.vmap(lambda f: predict_sequence(cfg, params, f))(batch.frames)   # [B, k, 8]
    return masked_mse(pred, normalize_actions(params.norm, batch.actions), batch.mask)
