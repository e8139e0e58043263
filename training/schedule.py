"""A run's schedule: its iterations (pretraining chunks, then practice or LFP rounds), the
trajectories each adds, and where it evaluates and saves. Pure functions of the config, shared by
the trainer, the benchmarks and the ablation planner."""
from __future__ import annotations

import math

from training.runconfig import RunConfig


def pretrain_iterations(cfg: RunConfig) -> int:
    return math.ceil(cfg.pretrain_steps / cfg.steps_between_ssp) if cfg.pretrain_steps else 0


def practice_iterations(cfg: RunConfig) -> int:
    """Practice rounds until total_trajectories (demonstrations + practice) are reached; with
    practice off (LFP) the same number of train-only rounds, so step counts match."""
    return max(0, math.ceil((cfg.total_trajectories - cfg.demos) / cfg.episodes_per_ssp))


def round_episodes(cfg: RunConfig, it: int) -> int:
    """Practice episodes iteration `it` adds to the run's trajectories: episodes_per_ssp, except
    in the last round, which adds what is left of total_trajectories, so the budget is met
    exactly (120,000 means 120,000); 0 outside practice."""
    k = it - pretrain_iterations(cfg)
    if not cfg.practice or k < 0 or k >= practice_iterations(cfg):
        return 0
    return min(cfg.episodes_per_ssp, cfg.total_trajectories - cfg.demos - k * cfg.episodes_per_ssp)


def total_iterations(cfg: RunConfig) -> int:
    return pretrain_iterations(cfg) + practice_iterations(cfg)


def is_checkpoint_iteration(cfg: RunConfig, it: int, stop_at: int) -> bool:
    """Save after iteration `it`: every checkpoint_every iterations and at the last one run."""
    return (it + 1) % cfg.checkpoint_every == 0 or it + 1 == stop_at


def is_eval_iteration(cfg: RunConfig, it: int) -> bool:
    """Evaluate after the last pretraining round (the LFP point), every eval_every trajectories
    of practice, and at the end."""
    n_pre, n_tot = pretrain_iterations(cfg), total_iterations(cfg)
    if it == n_pre - 1 or it == n_tot - 1:
        return True
    if it >= n_pre:
        done = (it - n_pre + 1) * cfg.episodes_per_ssp
        return done % cfg.eval_every < cfg.episodes_per_ssp
    return False


def phase(cfg: RunConfig, it: int) -> str:
    n_pre = pretrain_iterations(cfg)
    if it < n_pre:
        return "pretrain"
    return "practice" if cfg.practice else "lfp"
