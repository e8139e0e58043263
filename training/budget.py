"""Will a run fit? Device memory needed by a configuration, estimated before anything is
compiled, so an oversized cache, ensemble or batch is refused up front with the field to lower
instead of running out of memory minutes later."""
from __future__ import annotations

import os

import jax
import numpy as np

from training.runconfig import RunConfig

GiB = 1024 ** 3
FLOAT = 4
# Values stored per cached step: obs (13) + ball velocity (3) + action (8) + valid.
CACHE_STEP_VALUES = 13 + 3 + 8 + 1
# Optimizer-visible copies of the weights: params, Adam mu and nu, the moving average.
WEIGHT_COPIES = 4
# Bytes of MJX simulation state per episode: mjx.make_data on the scene is 10.1 kB (jax 0.10,
# mujoco-mjx 3.17); x6 headroom for the scan's carry, substep temporaries and per-step outputs.
MJX_EPISODE_BYTES = 64 * 1024


def device_bytes() -> int:
    """Memory of the default device: the accelerator's limit, or this machine's RAM on a CPU."""
    stats = jax.local_devices()[0].memory_stats() or {}
    if "bytes_limit" in stats:
        return int(stats["bytes_limit"])
    return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def weight_count(cfg: RunConfig) -> int:
    """Trainable values of one member (from the network's shapes, nothing allocated)."""
    from models.normalizer import identity_normalizer
    from models.policy import init_params
    shapes = jax.eval_shape(lambda: init_params(jax.random.PRNGKey(0), cfg.policy,
                                                identity_normalizer(cfg.policy.obs_size)).net)
    return int(sum(np.prod(x.shape) for x in jax.tree.leaves(shapes)))


def needs(cfg: RunConfig) -> dict[str, int]:
    """Estimated bytes per part of the run: {part: bytes}."""
    t = cfg.world.horizon
    tc, pc = cfg.train, cfg.policy
    act_per_window = tc.window * pc.input_frames * pc.obs_size + tc.window * pc.hidden * pc.layers * 8
    return {
        "cache (train.capacity x episode steps)": tc.capacity * t * CACHE_STEP_VALUES * FLOAT,
        "ensemble weights (train.members x network)": tc.members * weight_count(cfg) * WEIGHT_COPIES * FLOAT,
        "update batch (train.members x train.batch-size x train.window)":
            tc.members * tc.batch_size * act_per_window * FLOAT * 3,
        "practice rollouts (episodes-per-ssp)": cfg.episodes_per_ssp * (t * CACHE_STEP_VALUES * FLOAT
                                                                         + MJX_EPISODE_BYTES),
    }


def check_fits(cfg: RunConfig, available: int | None = None, fraction: float = 0.9, seeds: int = 1,
               devices: int = 1) -> dict[str, int]:
    """Raise ValueError naming the largest part if the estimate for `seeds` runs (lanes) of `cfg`
    on one device (every part grows linearly with them) exceeds `fraction` of its memory, with
    the lane count that fits (over `devices` devices, a block of lanes each); returns the
    estimate for all of them."""
    parts = {k: v * seeds for k, v in needs(cfg).items()}
    total, have = sum(parts.values()), available if available is not None else device_bytes()
    if total > fraction * have:
        name, big = max(parts.items(), key=lambda kv: kv[1])
        fit = int(fraction * have // (total / seeds))
        who = "this run needs" if seeds == 1 else f"--seeds {seeds} (runs in one program) need"
        if devices > 1:
            who = f"{seeds} lanes on each of {devices} devices need"
        more = "" if seeds == 1 else (f" or the seed count: {fit} lane(s) fit a device"
                                      + (f", {fit * devices} over the {devices} devices" if devices > 1 else ""))
        raise ValueError(f"{who} ~{total / GiB:.1f} GiB of device memory, {big / GiB:.1f} GiB of it for the "
                         f"{name}; the device has {have / GiB:.1f} GiB: lower those settings{more}")
    return parts


def episodes_that_fit(world, fraction: float = 0.5, available: int | None = None) -> int:
    """The most episodes of `world` one batch may simulate: `fraction` of the device's memory
    over an episode's simulation state and record."""
    per_episode = MJX_EPISODE_BYTES + world.horizon * CACHE_STEP_VALUES * FLOAT
    return int(fraction * (available if available is not None else device_bytes()) // per_episode)
