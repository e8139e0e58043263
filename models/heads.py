"""The network's last layer read as an action, and the imitation loss that trains it.

`mean` (the paper): the head's 8 outputs are the action, trained with the MSE, so at each input
the policy predicts the mean of the actions the data holds there. When the relabelled data
holds two strokes for one input (two timings that both land near the goal), that mean is a
third stroke that neither demonstration made.

`mixture`: K Gaussians with diagonal covariance over the 8 normalized actions, trained by the
negative log-likelihood of the data's action; the policy acts with the mean of the most
probable component, a stroke the data holds. Outputs per step [K (logits) + 8K (means) + 8K
(log standard deviations)].
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from models.config import ACTION_SIZE, PolicyConfig

# Standard deviations are kept in [e^-5, e^1] normalized units: a component that collapses
# onto one demonstration would otherwise drive the likelihood (and its gradient) to infinity.
LOG_STD_MIN, LOG_STD_MAX = -5.0, 1.0


def mixture_parts(cfg: PolicyConfig, y):
    """y [..., D] -> (log weights [..., K], means [..., K, 8], log stds [..., K, 8])."""
    k = cfg.components
    logits = y[..., :k]
    means = y[..., k:k + k * ACTION_SIZE].reshape(*y.shape[:-1], k, ACTION_SIZE)
    log_std = y[..., k + k * ACTION_SIZE:].reshape(*y.shape[:-1], k, ACTION_SIZE)
    return jax.nn.log_softmax(logits, -1), means, jnp.clip(log_std, LOG_STD_MIN, LOG_STD_MAX)


def head_action(cfg: PolicyConfig, y):
    """The head's outputs y [..., D] -> the normalized action [..., 8] the policy sends."""
    if cfg.head == "mean":
        return y
    log_w, means, _ = mixture_parts(cfg, y)
    best = jnp.argmax(log_w, -1)                                               # [...]
    return jnp.take_along_axis(means, best[..., None, None], -2)[..., 0, :]


def step_losses(cfg: PolicyConfig, y, target):
    """Per-step loss [...] of outputs y [..., D] against normalized actions target [..., 8]:
    the squared error averaged over the 8 values (mean), or the mixture's negative
    log-likelihood per action value (mixture: the same scale per value as the MSE's)."""
    if cfg.head == "mean":
        return jnp.mean((y - target) ** 2, -1)
    log_w, means, log_std = mixture_parts(cfg, y)
    z = (target[..., None, :] - means) * jnp.exp(-log_std)                     # [..., K, 8]
    log_p = jnp.sum(-0.5 * z ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi), -1)   # [..., K]
    return -jax.nn.logsumexp(log_w + log_p, -1) / ACTION_SIZE
