"""Bootstrap demonstrations: hits collected in the world, one dataset format.

Sources (`SOURCES`, `ttmjx demos --source`, `RunConfig.demo_source`):

- `paper`: the paper's bootstrap procedure ("Building up the initial bootstrap dataset";
  training/bootstrap_paper.py builds it, ttmjx/tools/bootstrap.py plays its result): an ES policy
  trained in simulation until it returns balls (narrow), its rollouts with 4 of the 8 joints
  perturbed, relabelled goal-conditioned imitation and self-practice with goals up the table
  (shift), then over the whole half (expand); the demonstrations are the last policy's episodes,
  goals uniform over the half and 4 joints perturbed (`Perturbation`). The shipped weights
  (ttmjx/tools/assets/paper_policy.*) make it a gather only; `ttmjx demos --source paper
  --rebuild stages|all` builds the procedure again.
- `striker`: the scripted striker (ttmjx/tools/striker.py) aimed at ONE fixed point,
  `paper_target`, with the same perturbation: a nearly deterministic model-based returner.
  Datasets whose metadata says `paper` without `source_version` 2 are striker datasets
  (`dataset_source`): the striker was called `paper` then.
- `es`: the ES policy alone (ttmjx/tools/es.py, shipped weights) with the same perturbation:
  the paper procedure's narrow first stage.
- `oracle`: the goal-directed striker aiming every return at a random target of the half. Its
  landings are its own targets (98% within 30 cm), so imitating it is nearly goal reaching: an
  UPPER BOUND, not the paper's bootstrap. Named `scripted` before (still accepted, `LEGACY`).

The goal in the observations is a placeholder (zeros): no source reads it (the `paper` policy
draws its own goal per episode); the trainer relabels each demonstration with where its ball
landed.
"""
from __future__ import annotations

import dataclasses
import functools
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx.world import backends, observation, record, thrower
from ttmjx.world.config import JOINT_NAMES, World, opponent_half

SOURCES = ("paper", "striker", "es", "oracle")
# Old names of sources (datasets, config.json, scripts). `paper` meant the striker source in
# datasets without a source_version and is now the paper's procedure: the name stays valid, so it is not mapped here; a
# DATASET from before says so by lacking `source_version` (`dataset_source`), and a run's
# config.json from before keeps its collected demonstrations in its run directory (a resumed
# run does not collect again).
LEGACY = {"scripted": "oracle"}
SOURCE_VERSION = 2   # in the metadata of datasets written since `paper` is the paper's procedure
NARROW_FIGURE_N = 1000   # ES episodes drawn as the narrow map beside a `paper` dataset
COVERAGE_GRID = (6, 4)  # cells along the table's length (x) and width (y) of the opponent's half
COVER_RADIUS = 0.3      # m: the paper's looser success radius; "area within 30 cm of a landing"


def renamed(source: str) -> str:
    """An old source name's current one (`LEGACY`: "scripted" is "oracle"); others unchanged.
    The one place old names are read: configs, checkpoints and datasets go through it."""
    return LEGACY.get(source, source)


def dataset_source(meta: dict) -> str:
    """The current name of the source a dataset's metadata records: `paper` written without
    a `source_version` is today's `striker`."""
    source = meta.get("source", "?")
    if source == "paper" and meta.get("source_version", 1) < SOURCE_VERSION:
        return "striker"
    return renamed(source)


def source_name(source: str) -> str:
    """The current name of a source (old names mapped, `LEGACY`); ValueError for unknown ones."""
    source = renamed(source)
    if source not in SOURCES:
        raise ValueError(f"unknown demonstration source {source!r}; expected one of {SOURCES}")
    return source


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """"Perturb 4 of the 8 robot joint angles" (paper, "Building up the initial bootstrap
    dataset"): per episode, a constant offset uniform in +-`offset[i]` is added to the command of
    joint `joints[i]` (JOINT_NAMES order) for the whole episode. The paper names neither the
    joints nor the sizes; the defaults come from what the landings do, never from a learning
    result (docs/DATA.md, "Bootstrap sources"):

    - joints: four arm joints that turn the blade's face, j1 (base yaw), j2 (shoulder pitch), j5
      (wrist pitch) and j6 (the blade's roll about the extension). Measured on 48 narrow throws,
      0.05 rad on j1 moves the landing 0.18 m across the table; on j2 0.19 m along it; on j5
      and j6 0.15-0.18 m obliquely: together they spread the landings both ways. The gantry (a
      translation, 2.5 m of landing per m) and j4 (0.04 m per 0.05 rad) matter less; j3 acts
      as j2.
    - offset (rad, half-widths of the uniform draw): scaled as one vector so that the landings
      spread toward goals uniform on the opponent's half while most balls still land there
      (the measurements: docs/DESIGN.md, "Measurements behind the code").

    These sizes were chosen for the `striker` source, which receives the offset on its commands
    with the true joints observed (`perturbed`); `es` and `paper` receive the same sizes as a
    hidden calibration offset (`perturbed(..., hidden=True)`), not re-chosen.
    """
    joints: tuple = (2, 3, 6, 7)
    offset: tuple = (0.15, 0.12, 0.08, 0.08)

    def __post_init__(self):
        if len(set(self.joints)) != len(self.joints) or not all(0 <= j < 8 for j in self.joints):
            raise ValueError(f"Perturbation.joints={self.joints}: expected distinct joint indices in 0..7 "
                             f"({JOINT_NAMES})")
        if len(self.offset) != len(self.joints) or not all(o >= 0 for o in self.offset):
            raise ValueError(f"Perturbation.offset={self.offset}: expected one half-width >= 0 per joint "
                             f"of {self.joints}")

    def draw(self, key) -> jax.Array:
        """[8] one episode's command offsets: zero off `joints`."""
        u = jax.random.uniform(key, (len(self.joints),), minval=-1.0, maxval=1.0)
        return jnp.zeros(8).at[jnp.array(self.joints)].set(u * jnp.array(self.offset))


@functools.lru_cache(maxsize=64)
def perturbed(policy: backends.Policy, pert: Perturbation, hidden: bool = False) -> backends.Policy:
    """`policy` with `pert`'s per-episode offset added to every command it sends. The offset is
    drawn at the episode's start and carried; the environment clips the result (ranges, speed).

    hidden=False (the `striker` source): the policy sees the true joints, so a closed-loop
    policy may correct part of the offset. hidden=True (`es`, `paper`): the joint angles
    themselves are perturbed, as a calibration offset the policy cannot see: it is shown its
    joints moved back by the offset (as models.policy.with_joint_offset), so it plays its usual
    stroke and the executed one is that stroke moved by the offset. A learned policy whose
    targets follow its observed joints (the imitation policies of `paper`) integrates an offset
    it can see into a drift (docs/DESIGN.md, "Measurements behind the code"). The record keeps
    the TRUE joints and the executed commands. One object per (policy, pert, hidden): compiled
    rollouts are kept by the policy they play."""
    def init(params, key):
        k_policy, k_offset = jax.random.split(key)
        return policy.init(params, k_policy), pert.draw(k_offset)

    def apply(params, carry, obs, key):
        inner, offset = carry
        if hidden:
            move = lambda f: f.at[..., observation.JOINTS].add(-offset.astype(f.dtype))  # noqa: E731
            obs = obs._replace(frame=move(obs.frame), frames=move(obs.frames))
        inner, action = policy.apply(params, inner, obs, key)
        return (inner, offset), action + offset
    return backends.Policy(init=init, apply=apply)


def paper_target(cfg: World) -> tuple[float, float]:
    """The `striker` source's one aim point: the centre of the opponent's half, so that a
    symmetric perturbation spreads the landings over the whole half (the paper's ES policy
    aimed near the net on one side; its data were then shifted to cover the table)."""
    return cfg.table.half_length / 2, 0.0


def narrow_striker(cfg: World):
    """The striker for the `striker` source: `striker.imitable()` aimed at `paper_target` on every
    throw, with its own per-episode joint offsets and posture draws off (the `Perturbation`
    wrapper is the only one)."""
    from ttmjx.tools import striker
    x, y = paper_target(cfg)
    return dataclasses.replace(striker.imitable(), target_x=(x, x), target_y=(y, y), perturb_joints=0)


def source_policy(cfg: World, source: str, params_dir: str | None = None,
                  pert: Perturbation | None = Perturbation()):
    """(Policy, params) of a demonstration source (`SOURCES`; old names accepted). params_dir:
    other weights than the shipped ones (`paper`: a directory of tools/bootstrap.py weights;
    `es`: es.load_policy's). pert=None: without the joint perturbation (`striker`, `es`, `paper`)."""
    wrap = (lambda p, hidden: p) if pert is None else (lambda p, hidden: perturbed(p, pert, hidden))  # noqa: E731
    source = source_name(source)
    if source == "oracle":
        from ttmjx.tools import striker
        return striker.striker_policy(cfg, striker.imitable()), None
    if source == "striker":
        from ttmjx.tools import striker
        return wrap(striker.striker_policy(cfg, narrow_striker(cfg)), False), None
    if source == "paper":
        from ttmjx.tools import bootstrap
        policy, params = bootstrap.load_policy(cfg, params_dir)
        return wrap(policy, True), params
    from ttmjx.tools import es
    policy, params = es.load_policy(cfg, params_dir)
    return wrap(policy, True), params


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


def area_within(landing, on_opponent, table, radius: float = COVER_RADIUS, cell: float = 0.02) -> float:
    """Fraction of the opponent's half's area within `radius` (m) of some landing on it (a
    goal there has a demonstration that landed within the success radius), on a `cell` grid.
    landing [B, 2], on_opponent [B] bool."""
    (x0, x1), (y0, y1) = opponent_half(table)
    pts = np.asarray(landing, np.float64)[np.asarray(on_opponent, bool)]
    if len(pts) == 0:
        return 0.0
    gx, gy = np.meshgrid(np.arange(x0 + cell / 2, x1, cell), np.arange(y0 + cell / 2, y1, cell))
    grid = np.stack([gx.ravel(), gy.ravel()], 1)
    near = np.zeros(len(grid), bool)
    for start in range(0, len(pts), 256):     # [G, 256] distances at a time: bounded memory
        d2 = ((grid[:, None, :] - pts[None, start:start + 256]) ** 2).sum(-1)
        near |= (d2 <= radius**2).any(1)
    return float(near.mean())


def summary(traj: record.Trajectories, cfg: World) -> dict:
    """Rates and spread of a record's landings: hit rate, return rate (first bounce after the
    hit on the opponent's half), `coverage` (6 x 4 grid cells reached), `area_within_30cm`
    (`area_within`) and the std (m) of the landings on the half along x and y."""
    on = np.asarray(traj.on_opponent, bool)
    land = np.asarray(traj.landing)[on]
    std = land.std(0) if len(land) > 1 else np.zeros(2)
    return {"n": traj.size, "hit_rate": float(np.mean(traj.hit)), "return_rate": float(np.mean(on)),
            "coverage": coverage(traj.landing, on, cfg.table),
            "area_within_30cm": area_within(traj.landing, on, cfg.table),
            "landing_std_x": float(std[0]), "landing_std_y": float(std[1])}


def collect(cfg: World, source: str, n: int, seed: int, backend: str = "c", chunk: int | None = None,
            progress: bool = False, params_dir: str | None = None,
            pert: Perturbation | None = Perturbation(), truth: bool = False):
    """n demonstrations in chunks on `backend`; [n, T, ...] record. pert: `source_policy`'s.
    truth=True: (record, record.TrueTrack [n]), the true ball and joints beside what the policy
    observed (the same record)."""
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    policy, params = source_policy(cfg, source, params_dir, pert)
    be = backends.Backend(cfg, backend)
    # MJX wants large batches (thousands of throws in flight); the C backend smaller chunks
    # so progress shows and memory stays small.
    chunk = chunk or be.kind.demo_chunk
    parts, truths = [], []
    bar = _bar(n, progress)
    for start in range(0, n, chunk):
        m = min(chunk, n - start)
        k_roll, th = chunk_draws(cfg, seed, start, m)
        out = jax.tree.map(np.asarray, be.rollout_one(policy, params, k_roll, th, np.zeros((m, 2), np.float32),
                                                      truth=truth))
        parts.append(out[0] if truth else out)
        if truth:
            truths.append(out[1])
        bar.update(m)
    bar.close()
    traj = record.concat(parts)
    if not truth:
        return traj
    return traj, record.TrueTrack(*(np.concatenate(x) for x in zip(*truths)))


def chunk_draws(cfg: World, seed: int, start: int, m: int):
    """(rollout key, m throws) of the chunk of a collection of `seed` that starts at demonstration
    `start`: what `collect` and `collect_lanes` both play, so their records agree."""
    k_throw, k_roll = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(seed), start))
    return k_roll, thrower.sample_throws(k_throw, cfg, m)


def collect_lanes(cfg: World, source: str, n: int, seeds: list[int], backend: str = "c",
                  progress: bool = False, place=None, devices: int = 1) -> list:
    """`collect(cfg, source, n, seed, backend)` for several seeds at once -> [S] records, record
    s with the draws of `collect(..., seeds[s])` (the same chunks, keys and throws; on MuJoCo C
    the same records, on MJX the same up to float32 arithmetic batched differently, which the
    contact can carry to a few cm of landing), played together as the lanes of one
    `Backend.rollout` (collect plays a lane of one): the setup of a table's lanes is then one
    rollout per chunk, not one per lane. As many seeds share a call as fit the backend's demonstration chunk
    on each of `devices` devices; on MJX `place` (a tree [S, ...] -> the same laid over the
    devices, training.seeds) splits a call's seeds over them, a group padded to the devices with
    copies of its last seed (computed, dropped)."""
    if n < 1 or not seeds:
        raise ValueError(f"collect_lanes: n={n} and {len(seeds)} seeds, expected n >= 1 and at least one seed")
    policy, params = source_policy(cfg, source)
    be = backends.Backend(cfg, backend)
    split = place is not None and be.kind.traceable
    devices = devices if split else 1
    chunk = be.kind.demo_chunk
    per_call = max(1, chunk // min(chunk, n)) * devices   # seeds whose chunks of throws fit one call
    out = []
    bar = _bar(n * len(seeds), progress)
    for g in range(0, len(seeds), per_call):
        group = seeds[g:g + per_call]
        width = -(-len(group) // devices) * devices
        played = group + [group[-1]] * (width - len(group))
        lay = place if split else (lambda tree: tree)
        lanes = lay(jax.tree.map(lambda x: jnp.broadcast_to(x, (width,) + jnp.shape(x)), params))
        parts = []
        for start in range(0, n, chunk):
            m = min(chunk, n - start)
            draws = [chunk_draws(cfg, s, start, m) for s in played]
            th = jax.tree.map(lambda *xs: jnp.stack(xs), *[d[1] for d in draws])
            rec = be.rollout(policy, lanes, lay(jnp.stack([d[0] for d in draws])), lay(th),
                             lay(jnp.zeros((width, m, 2), jnp.float32)))
            parts.append(jax.tree.map(np.asarray, rec))
            bar.update(m * len(group))
        out += [record.concat([jax.tree.map(lambda x: x[i], p) for p in parts]) for i in range(len(group))]
    bar.close()
    return out


def truth_arrays(true: record.TrueTrack) -> dict:
    """The arrays a `ttmjx demos` dataset keeps beside its record (record.save's extra): the
    ball's true centre and the true joints at the start of each control step, [B, T, 3] and
    [B, T, 8] (the record's `obs` holds what the policy observed: under a timing model the
    tracker's delayed view)."""
    return {"true_ball_pos": np.asarray(true.ball, np.float32), "true_joints": np.asarray(true.joints, np.float32)}


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
                 progress: bool = True, params_dir: str | None = None, es_dir: str | None = None) -> dict:
    """Collect and write a dataset to `out` (refuses to overwrite) with its landing-coverage
    figure `out/coverage.png`; returns the JSON summary. For `paper` the figure is the initial
    narrow ES policy's landings (n episodes, at most `NARROW_FIGURE_N`, unperturbed: the policy
    itself, as the paper's figure; ES weights from `es_dir`)
    beside the dataset's, as the paper's figure, and the summary adds the narrow map's numbers
    (`narrow_*`). params_dir: `source_policy`'s."""
    import os
    from ttmjx.world.config import to_dict
    if os.path.exists(os.path.join(out, "trajectories.npz")):
        raise FileExistsError(f"{out} already holds a dataset; refusing to overwrite it")
    source = source_name(source)
    t0 = time.perf_counter()
    traj, true = collect(cfg, source, n, seed, backend, progress=progress, params_dir=params_dir, truth=True)
    seconds = time.perf_counter() - t0
    summ = summary(traj, cfg)
    narrow = None
    if source == "paper":
        t1 = time.perf_counter()
        narrow = collect(cfg, "es", min(n, NARROW_FIGURE_N), seed + 1, backend, progress=progress, params_dir=es_dir,
                         pert=None)
        summ.update({f"narrow_{k}": v for k, v in summary(narrow, cfg).items()})
        summ["narrow_seconds"] = time.perf_counter() - t1
    meta = {"source": source, "source_version": SOURCE_VERSION, "distribution": cfg.throws.name, "seed": seed,
            "backend": backend, "code_version": code_version(), "seconds": seconds,
            "counts": {"hit": int(np.sum(traj.hit)), "returned": int(np.sum(traj.on_opponent))},
            **{k: v for k, v in summ.items() if k != "n"}, "world": to_dict(cfg)}
    record.save(out, traj, meta, extra=truth_arrays(true))
    path = os.path.join(out, "coverage.png")
    if narrow is not None:
        plot_bootstrap(narrow, traj, cfg, path)
    else:
        plot_coverage(traj, meta, path)
    return {**summ, "seconds": seconds}


SOURCE_LABELS = {"paper": "paper: the paper's bootstrap procedure (ES, shift, expand), 4 joints perturbed",
                 "striker": "striker: narrow scripted striker, 4 joints perturbed",
                 "es": "es: ES policy, 4 joints perturbed",
                 "oracle": "oracle: goal-directed striker (upper bound)"}


def _draw_landings(ax, traj: record.Trajectories, cfg: World, title: str):
    """The table seen from the robot's side (the opponent's half at the top, y to the left),
    the opponent's half outlined, a record's landings over it."""
    import matplotlib.pyplot as plt
    t = cfg.table
    ax.add_patch(plt.Rectangle((-t.half_width, -t.half_length), t.width, t.length, color="#1f4e8c"))
    ax.plot([-t.half_width, t.half_width], [0, 0], color="white", lw=3)              # net
    ax.plot([0, 0], [-t.half_length, t.half_length], color="white", lw=0.8)          # centre line
    ax.add_patch(plt.Rectangle((-t.half_width, -t.half_length), t.width, t.length, fill=False, ec="white", lw=2))
    ax.add_patch(plt.Rectangle((-t.half_width, 0), t.width, t.half_length, fill=False, ec="gold", lw=2.5,
                               label="opponent's half"))
    land = np.asarray(traj.landing)
    ok = np.isfinite(land[:, 0])
    on = np.asarray(traj.on_opponent, bool)
    ax.scatter(-land[ok & on, 1], land[ok & on, 0], s=5, c="orange", label="landed on the opponent's half")
    ax.scatter(-land[ok & ~on, 1], land[ok & ~on, 0], s=5, c="red", alpha=0.5, label="elsewhere")
    ax.set_xlim(-1.3, 1.3), ax.set_ylim(-1.6, 2.2), ax.set_aspect("equal")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper left", fontsize=7)
    ax.set_xlabel("-y (m)"), ax.set_ylabel("x (m)")


def _summary_rows(s: dict) -> list[tuple[str, str]]:
    return [("hit", f"{s['hit_rate']:.1%}"), ("on opponent's half", f"{s['return_rate']:.1%}"),
            ("half's area within 30 cm", f"{s['area_within_30cm']:.1%}"),
            ("6 x 4 cells reached", f"{s['coverage']:.0%}"),
            ("landing std x / y", f"{s['landing_std_x']:.2f} / {s['landing_std_y']:.2f} m")]


def _save(fig, path: str) -> str:
    import matplotlib.pyplot as plt
    from ttmjx.world import files
    files.write_figure(path, fig, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_coverage(traj: record.Trajectories, meta: dict, path: str) -> str:
    """Draw a record's landings over the table, the opponent's half outlined, with the summary
    table (`summary`) beside them (like the paper's Figure 3); writes the PNG at `path`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cfg = _world_of(meta)
    fig, ax = plt.subplots(figsize=(7.5, 6))
    source = dataset_source(meta)
    _draw_landings(ax, traj, cfg, f"{SOURCE_LABELS.get(source, source)}\n{meta.get('distribution')} throws, "
                                  f"n={traj.size}")
    rows = _summary_rows(summary(traj, cfg))
    tab = ax.table(cellText=[[v] for _, v in rows], rowLabels=[k for k, _ in rows], colWidths=[0.32],
                   bbox=[1.55, 0.55, 0.45, 0.4])
    tab.set_fontsize(8)
    return _save(fig, path)


def plot_bootstrap(narrow: record.Trajectories, final: record.Trajectories, cfg: World, path: str) -> str:
    """The paper's figure of its bootstrap: the narrow ES policy's landings beside the final
    demonstrations', each with its summary under it; writes the PNG at `path`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 7.5))
    for ax, traj, title in ((axes[0], narrow, "the initial narrow policy (ES)"),
                            (axes[1], final, "the bootstrap dataset (after shift and expand)")):
        _draw_landings(ax, traj, cfg, f"{title}\n{cfg.throws.name} throws, n={traj.size}")
        text = "\n".join(f"{k}: {v}" for k, v in _summary_rows(summary(traj, cfg)))
        ax.text(0.5, -0.12, text, transform=ax.transAxes, ha="center", va="top", fontsize=8, family="monospace")
    return _save(fig, path)


def plot_landings(directory: str, path: str | None = None) -> str:
    """`plot_coverage` of a dataset directory; PNG path (default DIR/landings.png)."""
    import os
    traj, meta = record.load(directory)
    return plot_coverage(traj, meta, path or os.path.join(directory, "landings.png"))


def _world_of(meta: dict) -> World:
    from ttmjx.world.config import from_dict
    return from_dict(World, meta["world"]) if "world" in meta else World()
