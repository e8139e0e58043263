"""Return rate of the tests' recorded tiny run on N narrow throws (tests/test_trainer.py's
learning test, on more throws): how far float rounding on this processor moves its outcome.

    python scripts/dev/tiny_return_rate.py RUN_DIR DEMO_DIR [--n 1024]

RUN_DIR and DEMO_DIR: the session fixtures `recorded_tiny_run` and `oracle_demos` of a test run
(e.g. /tmp/pytest-of-$USER/pytest-current/recorded_tiny_run0 and .../oracle_demos0)."""
import argparse
import os
import sys

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "tests"))
from recorded import tiny_recorded  # noqa: E402

from eval.evaluate import rollout_goals_one  # noqa: E402
from training import checkpoint  # noqa: E402
from training.trainer import Run  # noqa: E402
from training.update import acting_params  # noqa: E402
from ttmjx.world.env import uniform_goals  # noqa: E402

p = argparse.ArgumentParser()
p.add_argument("run_dir")
p.add_argument("demo_dir")
p.add_argument("--n", type=int, default=1024)
a = p.parse_args()
cfg = tiny_recorded(a.demo_dir, "/tmp/tiny_return_rate_start")
run = Run(cfg, progress=False)
for name, params in (("untrained", run.runs[0].initial().state.params),
                     ("trained", acting_params(checkpoint.load_checkpoint(a.run_dir).ck.state))):
    goals = np.asarray(uniform_goals(jax.random.PRNGKey(31), a.n, cfg.world.table))
    tr = rollout_goals_one(cfg.world, cfg.policy, params, run.backend, jax.random.PRNGKey(32), goals,
                           members=cfg.train.members)
    print(f"{name}: returned {np.mean(tr.on_opponent):.1%} of {a.n} narrow throws", flush=True)
