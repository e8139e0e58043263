"""`ttmjx train`: typed dataclass config (tyro) on top of a preset.

    ttmjx train                                  # the default preset for this machine
    ttmjx train --preset paper-sim --seed 1
    ttmjx train --preset default --train.members 4 --total-trajectories 10000
    ttmjx train --run-dir runs/x --data robot_logs/   # resume run x with robot logs added
"""
from __future__ import annotations

import argparse
import dataclasses


def cmd_train(args):
    import tyro
    from ttmjx.cli import _print
    from training import runconfig
    from training.trainer import Run
    base = runconfig.preset(args.preset)
    rest = list(args.rest)
    cfg = tyro.cli(runconfig.RunConfig, default=base, args=rest, prog="ttmjx train")
    if "--run-dir" not in rest and "--run_dir" not in rest and cfg.seed != 0 and cfg.run_dir == base.run_dir:
        cfg = dataclasses.replace(cfg, run_dir=f"{base.run_dir}-seed{cfg.seed}")
    out = Run(cfg, progress=not args.json).run(max_iterations=args.max_iterations)
    _print(args, out, "\n".join(f"{k:24s} {v}" for k, v in out.items()))


def register(sub, common):
    from training.runconfig import PRESET_NAMES
    sp = sub.add_parser("train", help="GoalsEye training: demonstrations, GCBC, self-practice, evaluation",
                        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sp.add_argument("--preset", default="default", choices=PRESET_NAMES)
    sp.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    sp.add_argument("--max-iterations", type=int, default=None,
                    help="stop (with a checkpoint) after this many iterations; resume later")
    # Every other option is a RunConfig override for tyro, e.g. --seed 1 --train.members 4.
    sp.set_defaults(fn=cmd_train, rest=[])
