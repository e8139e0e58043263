"""`ttmjx eval RUN_OR_CHECKPOINT --goals 200|five --json`."""
from __future__ import annotations

import os


def load_run(path: str, step: int | None = None):
    """(RunConfig, TrainState params) from a run directory or its checkpoints directory."""
    import jax
    from training import checkpoint, runconfig
    from training.trainer import Run
    ckpt = path if os.path.basename(os.path.normpath(path)) == "checkpoints" else os.path.join(path, "checkpoints")
    if not os.path.isdir(ckpt):
        raise FileNotFoundError(f"{path!r} is neither a run directory nor a checkpoints directory "
                                f"(no {ckpt})")
    cfg = runconfig.from_json(checkpoint.restore_config(ckpt, step))
    run = Run(cfg, progress=False)
    template = run.template()
    ck, _ = checkpoint.restore(ckpt, template, step)
    return cfg, ck, run


def cmd_eval(args):
    import dataclasses
    import jax
    from eval.evaluate import evaluate_five, evaluate_params
    from ttmjx.world.backends import Backend
    from ttmjx.cli import _print
    from training.runconfig import resolve_backend
    from training.update import acting_params
    cfg, ck, _ = load_run(args.run)
    world = cfg.world if not args.distribution else cfg.world.with_throws(args.distribution)
    be = Backend(world, resolve_backend(args.backend or cfg.backend))
    key = jax.random.PRNGKey(args.seed)
    members, params = cfg.train.members, acting_params(ck.state)
    if args.member is not None:
        from models.policy import member
        if not 0 <= args.member < members:
            raise ValueError(f"--member {args.member} is out of range: the run has {members} members")
        members, params = None, member(params, args.member)
    if args.goals == "five":
        out = evaluate_five(world, cfg.policy, params, be, key, args.per_goal, members)
    else:
        try:
            n = int(args.goals)
        except ValueError:
            raise ValueError(f"--goals must be a number of uniform goals or 'five', got {args.goals!r}")
        if n < 1:
            raise ValueError(f"--goals must be >= 1, got {n}")
        out = evaluate_params(world, cfg.policy, params, be, key, n, members)
    out = {**out, "distribution": world.throws.name, "trajectories": int(ck.counters.trajectories)}
    text = "\n".join(f"{k:14s} {v:.3f}" if isinstance(v, float) else f"{k:14s} {v}"
                     for k, v in out.items() if k != "per_goal")
    if "per_goal" in out:
        text += "\n" + "\n".join(f"goal {g}: <=30cm {m['within_30cm']:.0%} <=20cm {m['within_20cm']:.0%} "
                                 f"hit {m['hit_rate']:.0%}" for g, m in out["per_goal"].items())
    _print(args, out, text)


def register(sub, common):
    from ttmjx.world.config import THROW_DISTRIBUTIONS
    sp = sub.add_parser("eval", help="goal-reaching metrics of a run or checkpoint")
    sp.add_argument("run", help="run directory (or its checkpoints/ directory)")
    sp.add_argument("--distribution", choices=THROW_DISTRIBUTIONS, default=None,
                    help="throws (default: the run's)")
    sp.add_argument("--goals", default="200", help="number of uniform goals, or 'five' for goals A-E")
    sp.add_argument("--per-goal", type=int, default=40, help="attempts per goal with --goals five")
    sp.add_argument("--backend", choices=("c", "mjx"), default=None)
    sp.add_argument("--seed", type=int, default=1234)
    sp.add_argument("--member", type=int, default=None, help="evaluate one ensemble member alone")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(fn=cmd_eval)
