"""`ttmjx` command line. Every subcommand that reports numbers takes --json and then prints one
JSON object as its last line."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time


def _print(args, obj: dict, text: str | None = None):
    if getattr(args, "json", False):
        print(json.dumps(obj))
    else:
        print(text if text is not None else json.dumps(obj, indent=2))


def _world(args):
    from ttmjx.world.config import World
    kw = {}
    if getattr(args, "control_hz", None):
        kw["control_hz"] = args.control_hz
    cfg = World(**kw)
    dist = getattr(args, "distribution", None)
    if dist:
        cfg = cfg.with_throws(dist, spin=bool(getattr(args, "spin", False)))
    return cfg


def cmd_throw(args):
    from ttmjx.world import thrower
    if args.n < 1:
        raise ValueError(f"--n must be >= 1, got {args.n}")
    rep = thrower.throw_report(_world(args), args.n, args.seed)
    errs = [((t["aim"][0] - t["bounce"][0]) ** 2 + (t["aim"][1] - t["bounce"][1]) ** 2) ** 0.5
            for t in rep["throws"]]
    _print(args, rep, f"{args.n} {args.distribution} throws; bounce error vs aim: max "
                      f"{100 * max(errs):.2f} cm, mean {100 * sum(errs) / len(errs):.2f} cm")


def cmd_bench(args):
    from ttmjx.tools import bench
    out = bench.bench(_world(args), args.backend, args.batch, args.threads)
    text = "\n".join(f"{k:32s} {v:,.1f}" if isinstance(v, float) else f"{k:32s} {v}" for k, v in out.items())
    _print(args, out, text)


def cmd_render(args):
    from ttmjx.tools import render
    path = render.render_throws(_world(args), args.out, args.n, args.seed, source=args.source)
    _print(args, {"video": path}, f"wrote {path}")


def cmd_sim(args):
    """A short simulation run: throws on the chosen backend with the scripted striker."""
    from ttmjx.tools import simrun
    out = simrun.run(_world(args), args.backend, args.n, args.seed)
    _print(args, out, "\n".join(f"{k:16s} {v}" for k, v in out.items()))


def build_parser() -> argparse.ArgumentParser:
    from ttmjx.world.config import CONTROL_RATES, THROW_DISTRIBUTIONS
    p = argparse.ArgumentParser(prog="ttmjx", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)

    def common(sp, dist=True):
        sp.add_argument("--json", action="store_true", help="print one JSON object as the last line")
        if dist:
            sp.add_argument("--distribution", default="narrow", choices=THROW_DISTRIBUTIONS)
            sp.add_argument("--spin", action="store_true", help="throws with spin (off by default, as in the paper)")
        sp.add_argument("--control-hz", type=int, choices=CONTROL_RATES, default=None)

    sp = sub.add_parser("throw", help="sample throws and simulate their first bounce")
    common(sp)
    sp.add_argument("--n", type=int, default=10)
    sp.add_argument("--seed", type=int, default=0)
    sp.set_defaults(fn=cmd_throw)

    sp = sub.add_parser("bench", help="physics throughput of a backend")
    common(sp)
    sp.add_argument("--backend", choices=("c", "mjx"), default="c")
    sp.add_argument("--batch", type=int, default=1024)
    sp.add_argument("--threads", type=int, default=None, help="C backend threads (default: all cores)")
    sp.set_defaults(fn=cmd_bench)

    sp = sub.add_parser("render", help="write a short video (GIF) of a few throws, headless")
    common(sp)
    sp.add_argument("--n", type=int, default=3)
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--source", choices=("scripted", "hold"), default="scripted")
    sp.add_argument("--out", default="throws.gif")
    sp.set_defaults(fn=cmd_render)

    sp = sub.add_parser("sim", help="a short simulation run that prints what it did")
    common(sp)
    sp.add_argument("--backend", choices=("c", "mjx"), default="c")
    sp.add_argument("--n", type=int, default=64)
    sp.add_argument("--seed", type=int, default=0)
    sp.set_defaults(fn=cmd_sim)

    for register in _extensions():
        register(sub, common)
    return p


def _extensions():
    """Subcommands defined by later stages of the pipeline (demos, train, eval, export, robot)."""
    regs = []
    for mod in ("ttmjx.demos_cli", "training.cli", "eval.cli", "deploy.cli"):
        try:
            m = __import__(mod, fromlist=["register"])
        except ModuleNotFoundError as e:
            if e.name and mod.startswith(e.name.split(".")[0]) and e.name in (mod, mod.rsplit(".", 1)[0]):
                continue
            raise
        if hasattr(m, "register"):
            regs.append(m.register)
    return regs


def enable_compile_cache():
    """JAX's persistent compilation cache: compiled rollouts and training steps are reused
    across runs (first compiles take tens of seconds on a CPU)."""
    import jax
    path = os.environ.get("TTMJX_JAX_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "ttmjx", "jax"))
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


def main(argv=None):
    enable_compile_cache()
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if hasattr(args, "rest"):  # typed config overrides for tyro (ttmjx train)
        args.rest = [a for a in list(args.rest) + unknown if a != "--"]
    elif unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    try:
        args.fn(args)
    except (ValueError, FileExistsError, FileNotFoundError) as e:
        print(f"ttmjx {args.cmd}: error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    main()
