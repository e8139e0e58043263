"""Bootstrap demonstrations: non-goal-directed hits collected in the world, one dataset format.

Sources: `scripted` (ttmjx/tools/striker.py, the default) and `es` (an evolution-strategies policy,
ttmjx/tools/es.py). The goal in the observations is a placeholder (zeros): demonstrations are not
goal-directed; the trainer relabels them with where each ball landed.
"""
from __future__ import annotations

import subprocess
import sys
import time

import jax
import numpy as np

from ttmjx.world import backends, record, thrower
from ttmjx.world.config import World, opponent_half

SOURCES = ("scripted", "es")
COVERAGE_GRID = (6, 4)  # cells along the table's length (x) and width (y) of the opponent's half


def coverage(landing, on_opponent, table, grid=COVERAGE_GRID) -> float:
    """Fraction of the cells of a grid over the opponent's half that receive a landing.
    landing [B, 2], on_opponent [B] bool."""
    (x0, x1), (y0, y1) = opponent_half(table)
    pts = np.asarray(landing)[np.asarray(on_opponent, bool)]
    if len(pts) == 0:
        return 0.0
    ix = np.clip(((pts[:, 0] - x0) / (x1 - x0) * grid[0]).astype(int), 0, grid[0] - 1)
    iy = np.clip(((pts[:, 1] - y0) / (y1 - y0) * grid[1]).astype(int), 0, grid[1] - 1)
    return len(set(zip(ix.tolist(), iy.tolist()))) / (grid[0] * grid[1])


def summary(traj: record.Trajectories, cfg: World) -> dict:
    """{"n", "hit_rate", "return_rate", "coverage"} of a record."""
    return {"n": traj.size, "hit_rate": float(np.mean(traj.hit)),
            "return_rate": float(np.mean(traj.on_opponent)),
            "coverage": coverage(traj.landing, traj.on_opponent, cfg.table)}


def source_policy(cfg: World, source: str, params_dir: str | None = None):
    """(Policy, params) of a demonstration source."""
    if source == "scripted":
        from ttmjx.tools import striker
        return striker.striker_policy(cfg, striker.imitable()), None
    if source == "es":
        from ttmjx.tools import es
        return es.load_policy(cfg, params_dir)
    raise ValueError(f"unknown demonstration source {source!r}; expected one of {SOURCES}")


def collect(cfg: World, source: str, n: int, seed: int, backend: str = "c", chunk: int | None = None,
            progress: bool = False, params_dir: str | None = None) -> record.Trajectories:
    """n demonstrations in chunks on `backend`; [n, T, ...] record."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    policy, params = source_policy(cfg, source, params_dir)
    be = backends.Backend(cfg, backend)
    # MJX wants large batches (thousands of throws in flight); the C backend smaller chunks
    # so progress shows and memory stays small.
    chunk = chunk or (16384 if backend == "mjx" else 500)
    key = jax.random.PRNGKey(seed)
    parts = []
    bar = _bar(n, progress)
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        k_throw, k_roll = jax.random.split(jax.random.fold_in(key, start))
        th = thrower.sample_throws(k_throw, cfg, m)
        parts.append(jax.tree.map(np.asarray, be.rollout(policy, params, k_roll, th, np.zeros((m, 2), np.float32))))
        bar.update(m)
    bar.close()
    return record.concat(parts)


def _bar(n, on):
    from tqdm import tqdm
    return tqdm(total=n, unit="throw", disable=not on, file=sys.stderr)


def code_version() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=__file__.rsplit("/", 3)[0], timeout=5).stdout.strip() or "unknown"
    except Exception:
        return "unknown"


def make_dataset(cfg: World, source: str, n: int, seed: int, out: str, backend: str = "c",
                 progress: bool = True) -> dict:
    """Collect and write a dataset to `out` (refuses to overwrite); returns the JSON summary."""
    import os
    from ttmjx.world.config import to_dict
    if os.path.exists(os.path.join(out, "trajectories.npz")):
        raise FileExistsError(f"{out} already holds a dataset; refusing to overwrite it")
    t0 = time.perf_counter()
    traj = collect(cfg, source, n, seed, backend, progress=progress)
    seconds = time.perf_counter() - t0
    summ = summary(traj, cfg)
    record.save(out, traj, {"source": source, "distribution": cfg.throws.name, "seed": seed,
                            "backend": backend, "code_version": code_version(), "seconds": seconds,
                            "counts": {"hit": int(np.sum(traj.hit)), "returned": int(np.sum(traj.on_opponent))},
                            **{k: v for k, v in summ.items() if k != "n"}, "world": to_dict(cfg)})
    return {**summ, "seconds": seconds}


def plot_landings(directory: str, path: str | None = None) -> str:
    """Draw a dataset's landing points over the table (like the paper's Figure 3); PNG path."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import os
    from ttmjx.world.config import Table
    traj, meta = record.load(directory)
    t = Table()
    fig, ax = plt.subplots(figsize=(5, 7))
    ax.add_patch(plt.Rectangle((-t.half_width, -t.half_length), t.width, t.length, color="#1f4e8c"))
    ax.plot([-t.half_width, t.half_width], [0, 0], color="white", lw=3)              # net
    ax.plot([0, 0], [-t.half_length, t.half_length], color="white", lw=0.8)          # centre line
    ax.add_patch(plt.Rectangle((-t.half_width, -t.half_length), t.width, t.length, fill=False, ec="white", lw=2))
    land = np.asarray(traj.landing)
    ok = np.isfinite(land[:, 0])
    on = np.asarray(traj.on_opponent, bool)
    # Drawn from the robot's side: the opponent's half (x > 0) at the top, y to the left.
    ax.scatter(-land[ok & on, 1], land[ok & on, 0], s=6, c="orange", label="landed on opponent's half")
    ax.scatter(-land[ok & ~on, 1], land[ok & ~on, 0], s=6, c="red", alpha=0.5, label="missed")
    ax.set_xlim(-1.3, 1.3), ax.set_ylim(-1.6, 2.2), ax.set_aspect("equal")
    summ = summary(traj, _world_of(meta))
    ax.set_title(f"{meta.get('source')} / {meta.get('distribution')}: n={traj.size}\n"
                 f"hit {summ['hit_rate']:.0%}, returned {summ['return_rate']:.0%}, "
                 f"coverage {summ['coverage']:.0%}")
    ax.legend(loc="lower left", fontsize=7)
    ax.set_xlabel("-y (m)"), ax.set_ylabel("x (m)")
    path = path or os.path.join(directory, "landings.png")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path


def _world_of(meta: dict) -> World:
    from ttmjx.world.config import from_dict
    return from_dict(World, meta["world"]) if "world" in meta else World()
