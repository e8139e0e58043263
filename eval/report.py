"""What `ttmjx eval RUN --out DIR` writes, so anyone can check or recompute the numbers:

* `summary.json`: the metrics object (the one `--json` prints);
* `episodes.csv`: one row per episode: goal_x, goal_y, hit (0/1), landing_x, landing_y (empty
  when the ball was not hit or never came down after the hit), on_opponent_half (0/1: its first
  bounce after the hit was on the opponent's half), distance_m (landing to goal, empty without a
  landing), success_30cm, success_20cm (0/1, the strict success of ttmjx.world.goals);
* `tracks.npz` (plain arrays, no pickle; table frame, m): the simulation's truth, ball_pos
  [N, T, 3] float32, the ball's true centre at the start of each control step, ball_pos_physics
  [N, T * S + 1, 3] float32, the same at the start and after each of the S physics steps of
  every control step (ball_pos_physics[:, t * S] == ball_pos[:, t]), joints [N, T, 8] float32,
  the true joint positions at the start of each control step; and what the policy saw,
  ball_observed [N, T, 3] float32 (the observation's ball: under a timing model the tracker's
  delayed view, extrapolated to the tick; equal to ball_pos only at ideal timing); valid [N, T]
  bool, the steps played (the episode had not ended before them: the landing lies in the last
  valid step, so the sample after it is the ball after the landing); hit_step [N] int32, the
  control step of the first paddle contact (-1: no hit); control_hz; physics_dt (s);
  table_top_z and ball_radius (m); net_zone (m, ttmjx.world.env.net_zone). A landing is where
  the ball, after the hit, first comes down through table_top_z + ball_radius, a contact whose
  lowest point lies within net_zone of the net (|x|) being the net's (tests/test_true_tracks.py
  recomputes every landing from ball_pos_physics within 1 cm).

Every file is written atomically (ttmjx.world.files); summary.json last, so a directory holding it
is complete.
"""
from __future__ import annotations

import csv
import io
import os

import numpy as np

from ttmjx.world import env, files
from ttmjx.world.config import World
from ttmjx.world.goals import RADII, scored_distance
from ttmjx.world.record import OBS_BALL, Trajectories, TrueTrack

EPISODE_COLUMNS = ("goal_x", "goal_y", "hit", "landing_x", "landing_y", "on_opponent_half", "distance_m",
                   "success_30cm", "success_20cm")


def check_out_dir(out: str) -> None:
    """FileExistsError unless `out` is new or an empty directory."""
    if os.path.exists(out) and (not os.path.isdir(out) or os.listdir(out)):
        raise FileExistsError(f"--out {out!r} exists and is not an empty directory; expected a new or empty one")


def episode_table(traj: Trajectories) -> str:
    """episodes.csv of B episodes (header + B rows)."""
    goal, landing = np.asarray(traj.goal, np.float32), np.asarray(traj.landing, np.float32)
    hit, on_opp = np.asarray(traj.hit, bool), np.asarray(traj.on_opponent, bool)
    g64, l64 = goal.astype(np.float64), landing.astype(np.float64)    # goal_metrics' arithmetic
    scored = scored_distance(l64, g64, hit, on_opp)
    dist = np.linalg.norm(l64 - g64, axis=-1)
    num = lambda v: "" if not np.isfinite(v) else str(v)  # noqa: E731 (numpy's shortest exact text)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(EPISODE_COLUMNS)
    for i in range(len(goal)):
        w.writerow([num(goal[i, 0]), num(goal[i, 1]), int(hit[i]), num(landing[i, 0]), num(landing[i, 1]),
                    int(hit[i] and on_opp[i]), num(dist[i]), int(scored[i] <= RADII[0]), int(scored[i] <= RADII[1])])
    return buf.getvalue()


def tracks(traj: Trajectories, world: World, true: TrueTrack | None) -> dict:
    """The arrays of tracks.npz (module docstring) for B episodes of T steps; without `true` (a
    record that carries no truth) the observed arrays alone, never the observation as the truth."""
    out = {"ball_observed": np.asarray(traj.obs, np.float32)[:, :, OBS_BALL], "valid": np.asarray(traj.valid, bool),
           "hit_step": np.asarray(traj.hit_step, np.int32), "control_hz": np.int32(world.control_hz),
           "physics_dt": np.float64(world.physics_dt), "net_zone": np.float64(env.net_zone(world)),
           "table_top_z": np.float64(world.table.top_z), "ball_radius": np.float64(world.ball.radius)}
    if true is not None:
        out.update(ball_pos=np.asarray(true.ball, np.float32), joints=np.asarray(true.joints, np.float32),
                   ball_pos_physics=np.asarray(true.ball_physics, np.float32))
    return out


def write_eval_dir(out: str, summary: dict, traj: Trajectories, world: World, true: TrueTrack | None = None) -> None:
    """summary.json, episodes.csv and tracks.npz of one evaluation into `out` (new or empty);
    `true`: the rollout's truth (Backend.rollout(truth=True)), tracks.npz's ball_pos."""
    check_out_dir(out)
    # All three appear together (files.staged_dir): a full disk or a kill leaves `out` as it was,
    # so the same command runs again.
    with files.staged_dir(out, last=("summary.json",)) as stage:
        files.write_bytes(os.path.join(stage, "episodes.csv"), episode_table(traj).encode())
        buf = io.BytesIO()
        np.savez(buf, **tracks(traj, world, true))
        files.write_bytes(os.path.join(stage, "tracks.npz"), buf.getvalue())
        files.write_json(os.path.join(stage, "summary.json"), summary)
