"""`ttmjx eval BATCH`: a batch of seeds (`ttmjx train --seeds N`) evaluated as the lanes of one
rollout (eval/evaluate.py evaluate_checkpoints), with the mean and spread over the seeds
(training/seeds.py seed_spread), each seed scored exactly as `ttmjx eval BATCH --seed-index K`
scores it."""
from __future__ import annotations

from training.seeds import seed_run_dirs, seed_spread


def evaluate_seeds(run: str, goals: str, per_goal: int, distribution: str | None, backend: str | None, seed: int,
                   member: int | None, step: int | None, out: str | None = None) -> dict | None:
    """{'run', 'seeds', eval_<metric>_mean / _std, 'runs': [{'run_dir', eval_<metric>...}]}, or None
    when `run` is no batch of seeds. ValueError for `out` (each seed's records would collide:
    evaluate one with --seed-index)."""
    from eval.evaluate import evaluate_checkpoints
    dirs = seed_run_dirs(run)
    if dirs is None:
        return None
    if out:
        raise ValueError(f"--out with {run} (a batch of {len(dirs)} seeds): choose one with --seed-index")
    scores = evaluate_checkpoints(dirs, goals, per_goal, distribution, backend, seed, member, step)
    runs = [{"run_dir": d, **{f"eval_{k}": v for k, v in m.items() if isinstance(v, (int, float))}}
            for d, m in zip(dirs, scores, strict=True)]
    return {"run": run, "seeds": len(dirs), **seed_spread(runs), "runs": runs}
