"""Is resume exact on this machine's backend? Train the `tiny` preset uninterrupted and again
stopped after K iterations then resumed; print the largest parameter difference and the
metric rows that differ, as one JSON line.

    python scripts/resume_check.py [--backend mjx] [--stop-after 3] [--out DIR]
"""
import argparse
import dataclasses
import json
import os
import tempfile

import jax
import numpy as np

from eval.evaluate import training_evaluation
from training import checkpoint, runconfig
from training.trainer import Run
from ttmjx.tools import demos
from ttmjx.world import record


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--backend", default="auto", choices=("auto", "c", "mjx"))
    p.add_argument("--stop-after", type=int, default=3)
    p.add_argument("--out", default=None)
    a = p.parse_args()
    root = a.out or tempfile.mkdtemp(prefix="resume_check_")
    cfg0 = runconfig.tiny()
    demo_dir = os.path.join(root, "demos")
    record.save(demo_dir, demos.collect(cfg0.world, "oracle", cfg0.demos, seed=5), {"source": "oracle"})
    base = dataclasses.replace(cfg0, backend=a.backend, demo_dir=demo_dir)
    full, split = (dataclasses.replace(base, run_dir=os.path.join(root, n)) for n in ("full", "split"))
    Run(full, evaluate=training_evaluation(full), progress=False).run()
    Run(split, evaluate=training_evaluation(split), progress=False).run(max_iterations=a.stop_after)
    Run(split, evaluate=training_evaluation(split), progress=False).run()
    x, y = (jax.tree.leaves(checkpoint.load_checkpoint(r.run_dir).ck.state.params) for r in (full, split))
    diff = max(float(np.max(np.abs(np.asarray(u, np.float64) - np.asarray(v, np.float64)))) for u, v in zip(x, y))
    rows = [[json.loads(line) for line in open(os.path.join(r.run_dir, "metrics.jsonl"))] for r in (full, split)]
    differ = [r1["iteration"] for r1, r2 in zip(*rows)
              if {k: v for k, v in r1.items() if k != "seconds"} != {k: v for k, v in r2.items() if k != "seconds"}]
    print(json.dumps({"backend": jax.default_backend(), "run_backend": a.backend, "stop_after": a.stop_after,
                      "max_abs_param_diff": diff, "rows_that_differ": differ,
                      "final_eval_full": {k: v for k, v in rows[0][-1].items() if k.startswith("eval_")},
                      "final_eval_split": {k: v for k, v in rows[1][-1].items() if k.startswith("eval_")}}))


if __name__ == "__main__":
    main()
