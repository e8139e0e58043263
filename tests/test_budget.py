"""Runs that cannot fit are refused before anything is compiled, naming what to lower."""
import dataclasses

import pytest

from training import budget, runconfig
from training.trainer import Run


def test_the_cache_estimate_is_its_array_sizes():
    cfg = runconfig.preset("tiny")
    parts = budget.needs(cfg)
    cache = next(v for k, v in parts.items() if k.startswith("cache"))
    # obs [C, T, 13], ball_vel [C, T, 3], actions [C, T, 8] float32, valid [C, T] counted as 4 bytes
    assert cache == cfg.train.capacity * cfg.world.horizon * (13 + 3 + 8 + 1) * 4
    assert budget.check_fits(cfg) == parts


def test_an_oversized_cache_is_refused_before_any_work(tmp_path):
    cfg = runconfig.preset("tiny")
    big = dataclasses.replace(cfg, run_dir=str(tmp_path / "big"),
                              train=dataclasses.replace(cfg.train, capacity=50_000_000))
    with pytest.raises(ValueError, match=r"needs ~\d+\.\d GiB .* for the cache \(train.capacity"):
        Run(big, progress=False)
    assert not (tmp_path / "big").exists()


def test_config_bounds_name_the_field():
    cfg = runconfig.preset("tiny")
    with pytest.raises(ValueError, match=r"train.window=500 is longer than an episode \(160 control steps\)"):
        dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, window=500))
    with pytest.raises(ValueError, match="episodes_per_ssp=33 must be a multiple of train.members=2"):
        dataclasses.replace(cfg, episodes_per_ssp=33)
