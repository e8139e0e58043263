"""`ttmjx eval BATCH`: a batch of seeds (`ttmjx train --seeds N`) evaluated seed by seed, with the
mean and spread over the seeds (training/seeds.py seed_spread), each seed scored exactly as
`ttmjx eval BATCH --seed-index K` scores it (eval/evaluate.py evaluate_checkpoint)."""
from __future__ import annotations

from training.seeds import seed_run_dirs, seed_spread


def evaluate_seeds(run: str, goals: str, per_goal: int, distribution: str | None, backend: str | None, seed: int,
                   member: int | None, step: int | None, out: str | None = None) -> dict | None:
    """{'run', 'seeds', eval_<metric>_mean / _std, 'runs': [{'run_dir', eval_<metric>...}]}, or None
    when `run` is no batch of seeds. ValueError for `out` (each seed's records would collide:
    evaluate one with --seed-index)."""
    from eval.evaluate import evaluate_checkpoint
    dirs = seed_run_dirs(run)
    if dirs is None:
        return None
    if out:
        raise ValueError(f"--out with {run} (a batch of {len(dirs)} seeds): choose one with --seed-index")
    runs = [{"run_dir": d, **{f"eval_{k}": v for k, v in evaluate_checkpoint(
        d, goals, per_goal, distribution, backend, seed, member, step).items() if isinstance(v, (int, float))}}
        for d in dirs]
    return {"run": run, "seeds": len(dirs), **seed_spread(runs), "runs": runs}
