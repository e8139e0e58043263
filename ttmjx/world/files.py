"""Files that are whole or absent: atomic writes (write, flush, fsync, rename) and checksums.

A crash or a full disk at any moment leaves either the old file or the new one under the name,
never a half-written one. Standard library only (the robot side uses it too).
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import tempfile


def write_bytes(path: str, data: bytes) -> None:
    """Write `data` to `path` atomically."""
    directory = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=directory)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def append_bytes(path: str, data: bytes) -> None:
    """Append `data` to `path` and sync it to disk (a crash can cut only this append short)."""
    with open(path, "ab") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def json_safe(x):
    """Non-finite floats -> None, recursively (JSON has no NaN or infinity)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [json_safe(v) for v in x]
    return x


def write_figure(path: str, fig, **savefig) -> str:
    """A matplotlib figure written as PNG atomically (a crash leaves the old picture or the new
    one); the caller closes the figure."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", **savefig)
    write_bytes(path, buf.getvalue())
    return path


def write_json(path: str, obj, indent: int | None = 2) -> None:
    """Write `obj` as strict JSON (non-finite floats as null) atomically."""
    write_bytes(path, (json.dumps(json_safe(obj), indent=indent, allow_nan=False) + "\n").encode())


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _hash_all(paths: list[str]) -> list[str]:
    """sha256 of each file, in order; on several threads (hashlib releases the GIL for large
    blocks: a checkpoint's ~2 GB at paper scale hashes in a fraction of the serial time)."""
    if len(paths) < 2:
        return [sha256_file(p) for p in paths]
    from concurrent.futures import ThreadPoolExecutor
    with ThreadPoolExecutor(max_workers=min(8, len(paths), os.cpu_count() or 1)) as pool:
        return list(pool.map(sha256_file, paths))


def tree_checksums(directory: str, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """{relative path: sha256} of every file under `directory` (names in `exclude` skipped)."""
    rels = sorted(os.path.relpath(os.path.join(dirpath, n), directory)
                  for dirpath, _, names in os.walk(directory) for n in names if n not in exclude)
    return dict(zip(rels, _hash_all([os.path.join(directory, r) for r in rels])))


def first_mismatch(directory: str, expected: dict[str, str]) -> str | None:
    """The first file under `directory` (in `expected`'s order) that is missing or differs from
    `expected`, as 'path: reason'; None if all match."""
    paths = [os.path.join(directory, rel) for rel in expected]
    missing = [p for p in paths if not os.path.exists(p)]
    present = [p for p in paths if p not in missing]
    digests = dict(zip(present, _hash_all(present)))
    for path, digest in zip(paths, expected.values()):
        if path in missing:
            return f"{path}: missing"
        if digests[path] != digest:
            return f"{path}: checksum mismatch"
    return None


class staged_dir:
    """`with staged_dir(final) as tmp:` write a directory's files into `tmp` (a hidden sibling of
    `final`); on success they appear under `final` at once (a rename; into an existing directory
    that holds other files, file by file with the names in `last`, such as a manifest, moved
    last), on an error or a signal the staging directory is removed and
    `final` is left as it was. A full disk or a kill can therefore never leave half of an
    export or of an evaluation's records under the final name."""

    def __init__(self, final: str, last: tuple[str, ...] = ()):
        self.final, self.last = os.path.abspath(final), tuple(last)

    def __enter__(self) -> str:
        parent = os.path.dirname(self.final)
        os.makedirs(parent, exist_ok=True)
        self.tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(self.final)}.partial-", dir=parent)
        return self.tmp

    def __exit__(self, kind, value, tb) -> bool:
        import shutil
        if kind is not None:
            shutil.rmtree(self.tmp, ignore_errors=True)
            return False
        try:
            if not os.path.exists(self.final) or (os.path.isdir(self.final) and not os.listdir(self.final)):
                os.replace(self.tmp, self.final)        # an empty directory is replaced whole
            else:
                names = sorted(os.listdir(self.tmp), key=lambda n: (n in self.last, n))
                for name in names:
                    os.replace(os.path.join(self.tmp, name), os.path.join(self.final, name))
                os.rmdir(self.tmp)
            fd = os.open(os.path.dirname(self.final), os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        except BaseException:
            shutil.rmtree(self.tmp, ignore_errors=True)
            raise
        return False


def what_it_holds(directory: str, names: list[str] | None = None) -> str:
    """'a training run (config.json, checkpoints/, ...)': what a project directory holds, named by
    the files that mark each kind of output, with up to four of `names` (default: all its
    entries) shown; for refusing an --out that holds something other than the command's own."""
    every = sorted(os.listdir(directory))
    names = every if names is None else names
    if "config.json" in every or "checkpoints" in every:
        what = "a training run"
    elif "manifest.json" in every:
        what = "an export"
    elif "trajectories.npz" in every:
        what = "a dataset"
    elif "results" in every or "runs" in every:
        what = "an experiment table"
    elif "session.json" in every or any(n.startswith("episode_") for n in every):
        what = "robot episode logs"
    else:
        what = "other files"
    shown = ", ".join(n + ("/" if os.path.isdir(os.path.join(directory, n)) else "") for n in names[:4])
    return f"{what} ({shown}{', ...' if len(names) > 4 else ''})"
