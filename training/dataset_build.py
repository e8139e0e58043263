"""`ttmjx demos`: a bootstrap dataset written whole or not at all. With a rebuild, the paper's
procedure first builds its policy into OUT/bootstrap/ (training/bootstrap_paper.py, resumable
there); then the dataset is collected and written (ttmjx/tools/demos.py make_dataset). A
dataset cut short (a full disk, a signal) leaves no partial files, so the same command runs
again; what the rebuild built stays.
"""
from __future__ import annotations

import os
import shutil
from typing import Callable

from ttmjx.tools import demos
from ttmjx.world.config import World

BUILT = "bootstrap"     # OUT/bootstrap/: what --rebuild built, kept when the dataset fails


def rebuilt_policy(out: str, world: World, rebuild: str, n: int, seed: int, es_generations: tuple[int, int],
                   progress: bool, log: Callable[[str], None]) -> tuple[str | None, str | None]:
    """(params_dir, es_dir) for make_dataset: the paper procedure built again in OUT/bootstrap/
    (`rebuild` 'stages': from the shipped ES weights; 'all': ES too), or (None, None) for the
    shipped weights ('none')."""
    if rebuild == "none":
        return None, None
    from training import bootstrap_paper
    built = os.path.join(out, BUILT)
    bootstrap_paper.build(built, bootstrap_paper.default_world().with_throws(world.throws.name, spin=world.throws.spin),
                          bootstrap_paper.Procedure(final=n, seed=seed, es_generations=es_generations),
                          rebuild_es=rebuild == "all", progress=progress, log=log)
    return built, (built if rebuild == "all" else None)


def dataset(world: World, source: str, n: int, seed: int, out: str, backend: str = "c", rebuild: str = "none",
            es_generations: tuple[int, int] = (134, 330), progress: bool = True,
            log: Callable[[str], None] = print) -> dict:
    """make_dataset's summary of the dataset written to `out`, after the rebuild `rebuild` asks
    for; on any failure (signals included) `out` is left as it was before, less nothing the
    rebuild built."""
    params_dir, es_dir = rebuilt_policy(out, world, rebuild, n, seed, es_generations, progress, log)
    fresh = not os.path.exists(out) or not os.listdir(out)
    try:
        return demos.make_dataset(world, source, n, seed, out, backend, progress=progress,
                                  params_dir=params_dir, es_dir=es_dir)
    except BaseException:
        if fresh:
            remove_partial(out, keep=(BUILT,))
        raise


def remove_partial(out: str, keep: tuple[str, ...] = ()) -> None:
    """Delete everything in `out` but the names in `keep`, and `out` itself if that empties it."""
    if not os.path.isdir(out):
        return
    for name in os.listdir(out):
        if name not in keep:
            path = os.path.join(out, name)
            shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)
    if not os.listdir(out):
        os.rmdir(out)
