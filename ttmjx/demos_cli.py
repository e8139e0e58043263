"""`ttmjx demos` and `ttmjx plot-landings`."""
from __future__ import annotations


def cmd_demos(args):
    from ttmjx.tools import demos
    from ttmjx.cli import _print, _world
    out = demos.make_dataset(_world(args), args.source, args.n, args.seed, args.out, args.backend,
                             progress=not args.json)
    _print(args, out, "\n".join(f"{k:12s} {v:.3f}" if isinstance(v, float) else f"{k:12s} {v}"
                                for k, v in out.items()) + f"\nwrote {args.out}")


def cmd_plot(args):
    from ttmjx.tools import demos
    from ttmjx.cli import _print
    path = demos.plot_landings(args.dir, args.out)
    _print(args, {"plot": path}, f"wrote {path}")


def register(sub, common):
    sp = sub.add_parser("demos", help="collect bootstrap demonstrations into a dataset directory")
    common(sp)
    sp.add_argument("--source", choices=("scripted", "es"), default="scripted")
    sp.add_argument("--n", type=int, default=1000)
    sp.add_argument("--seed", type=int, default=0)
    sp.add_argument("--out", required=True, help="new dataset directory (never overwritten)")
    sp.add_argument("--backend", choices=("c", "mjx"), default="c")
    sp.set_defaults(fn=cmd_demos)

    sp = sub.add_parser("plot-landings", help="draw a dataset's landing points over the table (PNG)")
    sp.add_argument("dir")
    sp.add_argument("--out", default=None, help="PNG path (default DIR/landings.png)")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(fn=cmd_plot)
