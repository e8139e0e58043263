"""What a run reports: metrics.jsonl (one row per iteration), TensorBoard scalars, the progress
bar and the learning-curve PNG."""
from __future__ import annotations

import json
import math
import os
import sys

from ttmjx.world import files


class MetricsLog:
    """metrics.jsonl and TensorBoard scalars of one run directory."""

    def __init__(self, run_dir: str):
        self.run_dir = run_dir
        self.path = os.path.join(run_dir, "metrics.jsonl")
        self._writer = None
        self.torn = ""          # a last line cut short by a crash mid-append, dropped by rows()

    def rows(self) -> list[dict]:
        """The rows written; a last line cut short by a crash mid-append is dropped."""
        if not os.path.exists(self.path):
            return []
        lines = [line for line in open(self.path) if line.strip()]
        self.torn = ""
        if lines and not lines[-1].endswith("\n"):
            self.torn = lines.pop()
        rows = []
        for i, line in enumerate(lines):
            try:
                rows.append(json.loads(line))
            except ValueError as e:
                raise ValueError(f"{self.path}: line {i + 1} is not a JSON row ({e}); repair or remove it") from None
        return rows

    def start(self):
        self._replace([])

    def truncate(self, iteration: int):
        """Drop rows of iterations at or after `iteration` (a resumed run redoes them)."""
        self._replace([r for r in self.rows() if r["iteration"] < iteration])

    def _replace(self, rows: list[dict]):
        """The whole file, written atomically (a crash leaves the old rows or the new ones)."""
        files.write_bytes(self.path, "".join(json.dumps(files.json_safe(r)) + "\n" for r in rows).encode())

    def write(self, row: dict):
        """Append one row (flushed and synced: it is on disk before the checkpoint covering it)."""
        files.append_bytes(self.path, (json.dumps(files.json_safe(row)) + "\n").encode())
        writer = self._tensorboard()
        if writer:
            for k, v in row.items():
                if isinstance(v, (int, float)) and k not in ("trajectories", "iteration") and math.isfinite(v):
                    writer.add_scalar(k, v, row["trajectories"])
            writer.flush()

    def _tensorboard(self):
        if self._writer is None:
            try:
                from tensorboardX import SummaryWriter
                self._writer = SummaryWriter(os.path.join(self.run_dir, "tensorboard"))
            except Exception:  # TensorBoard logs are a convenience, never a reason to stop
                self._writer = False
        return self._writer

    def close(self):
        if self._writer:
            self._writer.close()
        self._writer = None


def progress_bar(total: int, initial: int, enabled: bool):
    from tqdm import tqdm
    return tqdm(total=total, initial=initial, unit="traj", disable=not enabled, file=sys.stderr, dynamic_ncols=True)


def postfix(row: dict) -> str:
    """The progress bar's summary of an iteration."""
    s = f"it {row['iteration']} loss {row['loss']:.3f}"
    if "eval_within_30cm" in row:
        s += f" | eval <=30cm {row['eval_within_30cm']:.0%} <=20cm {row['eval_within_20cm']:.0%}"
    return s


def plot_curves(metrics_path: str, png: str) -> str | None:
    """Learning curves against total trajectories (demonstrations + practice)."""
    if not os.path.exists(metrics_path):
        return None
    rows = [json.loads(line) for line in open(metrics_path) if line.strip()]
    ev = [r for r in rows if "eval_within_30cm" in r]
    if not ev:
        return None
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    x = [r["trajectories"] for r in ev]
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    a.plot(x, [100 * r["eval_within_30cm"] for r in ev], "o-", label="<= 30 cm")
    a.plot(x, [100 * r["eval_within_20cm"] for r in ev], "s-", label="<= 20 cm")
    a.plot(x, [100 * r["eval_hit_rate"] for r in ev], ":", color="gray", label="hit rate")
    a.set_xlabel("total trajectories (demonstrations + practice)"), a.set_ylabel("% of balls")
    a.legend(), a.grid(alpha=0.3)
    b.plot(x, [r["eval_mean_dist"] for r in ev], "o-", color="C2")
    b.set_xlabel("total trajectories"), b.set_ylabel("mean distance to goal (m)"), b.grid(alpha=0.3)
    fig.suptitle(os.path.basename(os.path.dirname(os.path.abspath(metrics_path))))
    fig.tight_layout()
    files.write_figure(png, fig, dpi=110)
    plt.close(fig)
    return png
