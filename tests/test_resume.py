"""A run stopped and resumed ends where the uninterrupted run ends, bit for bit: its whole saved
state and every metrics row but the wall time, on each physics backend (MuJoCo C and MJX; on an
accelerator MJX runs there). tests/test_trainer.py checks the C backend's state in the fast set;
this is the check behind docs/RESULTS.md's resume table, on whatever machine runs it."""
import json
import os

import jax
import numpy as np
import pytest

from recorded import tiny_recorded

STOP_AFTER = 3        # iterations before the "kill": pretraining done, practice not yet


def trained(cfg, max_iterations=None) -> None:
    from eval.evaluate import training_evaluation
    from training.trainer import Run
    Run(cfg, evaluation=training_evaluation, progress=False).run(max_iterations=max_iterations)


def state_leaves(run_dir: str) -> list:
    from training import checkpoint
    return jax.tree.leaves(checkpoint.load_checkpoint(run_dir).ck)


def rows_without_time(run_dir: str) -> list[dict]:
    return [{k: v for k, v in json.loads(line).items() if k != "seconds"}
            for line in open(os.path.join(run_dir, "metrics.jsonl"))]


# MJX on a CPU: ~13 min for the two tiny runs on 2 cores (measured); it is run where MJX is the
# backend that trains, an accelerator.
MJX_HERE = pytest.mark.skipif(jax.default_backend() == "cpu", reason="MJX resume: run on a GPU (~13 min on a CPU)")


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["c", pytest.param("mjx", marks=MJX_HERE)])
def test_a_resumed_run_is_the_uninterrupted_run(backend, oracle_demos, recorded_tiny_run, tmp_path):
    if backend == "c" and jax.default_backend() == "cpu":
        full = str(recorded_tiny_run[0])      # the session's uninterrupted tiny run (backend auto: C here)
    else:
        full = str(tmp_path / "full")
        trained(tiny_recorded(oracle_demos, full, backend=backend))
    split = tiny_recorded(oracle_demos, tmp_path / "split", backend=backend)
    trained(split, max_iterations=STOP_AFTER)
    assert len(rows_without_time(split.run_dir)) == STOP_AFTER
    trained(split)                            # the same command again: resumed to the end
    for x, y in zip(state_leaves(full), state_leaves(split.run_dir), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert rows_without_time(split.run_dir) == rows_without_time(full)
