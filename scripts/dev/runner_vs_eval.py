"""The same policy, goals and throws played by evaluation and by the robot runner.

(a) `ttmjx eval`'s rollout (eval.evaluate.rollout_goals_one on ttmjx.world.backends.Backend("c")) of
one member of a run's moving-average policy toward N uniform goals (the draw of
`ttmjx eval RUN --goals N --member M --seed S`); (b) that member exported and played by
deploy.robot.runner.Runner on the simulated station (deploy.sim.station) toward the same goals, on the
same throws, from the same start poses. Per episode: the first step whose frame or command
differs, hit, landing; in all: the goal metrics of both and the fraction on the opponent's half.

    python scripts/dev/runner_vs_eval.py RUN --n 100 --timing zero --start launch --json
    python scripts/dev/runner_vs_eval.py RUN --n 100 --timing nominal --start trigger --pose home --charge-compute

--timing zero: ideal sensors (deploy.sim.station.TIMING); --start launch: tick 0 at the launch (the
station announces it), as the simulation's episodes start; trigger: at the runner's ball
trigger; --pose eval: each episode starts from the evaluation's start pose (home + the reset
noise), home: from the contract's home. Compute time is charged to the simulated clock only
with --charge-compute (as `ttmjx robot run` does).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import tempfile

import jax
import numpy as np

from deploy.robot.exported import export_world, load_export
from deploy.robot.runner import Runner
from deploy.sim.export import export
from deploy.sim.station import TIMING, SimClock, SimStation, goal_summary, play
from eval.evaluate import rollout_goals_one
from models.policy import member
from training.checkpoint import load_checkpoint
from ttmjx.world import files, thrower
from ttmjx.world.backends import Backend
from ttmjx.world.env import uniform_goals
from ttmjx.world.goals import goal_metrics

FRAME_TOL = ACTION_TOL = 1e-4


def evaluation(run: str, member_index: int, n: int, seed: int, timing=None):
    """(cfg, params of the member, goals [n, 2], throws, Trajectories) of `ttmjx eval run
    --goals n --member member_index --seed seed` (eval.evaluate.evaluate_uniform's draws);
    timing: a ttmjx.world.config.Timing to evaluate under instead of the run's."""
    loaded = load_checkpoint(run)
    cfg, params = loaded.cfg, member(loaded.params, member_index)
    if timing is not None:
        cfg = dataclasses.replace(cfg, world=dataclasses.replace(cfg.world, timing=timing))
    k_goal, k_run = jax.random.split(jax.random.PRNGKey(seed))
    goals = np.asarray(uniform_goals(k_goal, n, cfg.world.table), np.float32)
    tr = rollout_goals_one(cfg.world, cfg.policy, params, Backend(cfg.world, "c"), k_run, goals)
    throws = thrower.sample_throws(jax.random.split(k_run)[0], cfg.world, n)   # rollout_goals_one's throws
    return cfg, params, goals, throws, tr


def station_throws(throws) -> list[tuple]:
    """The launches as the evaluation's reset sees them (float32) -> SimStation.throw_in's tuples."""
    fields = [np.asarray(x, np.float32).astype(np.float64)
              for x in (throws.launch_pos, throws.launch_vel, throws.launch_spin, throws.aim)]
    return list(zip(*fields))


def runner_play(export_dir: str, goals, throws, poses, timing: str = "zero", sync_launch: bool = True,
                charge_compute: bool = False, throw_delay_s: float = 1.0):
    """(episodes, runner, station): the export played by the runner on the simulated station
    toward goals [N, 2] with the station's throws and start poses [N, 8]."""
    policy, contract = load_export(export_dir)
    clock = SimClock(charge_compute=charge_compute)
    station = SimStation(export_world(policy.contract_doc), contract, clock=clock,
                         timing=TIMING[timing] if isinstance(timing, str) else timing)
    runner = Runner(station.robot, station.tracker, clock, policy, contract)
    station.prefetch()
    episodes = play(runner, station, goals, throws=throws, poses=poses, sync_launch=sync_launch,
                    throw_delay_s=throw_delay_s)
    return episodes, runner, station


def first_divergence(frames_a, actions_a, frames_b, actions_b, steps: int) -> dict | None:
    """The first of `steps` steps where the frames [T, O] or commands [T, 8] of (a) and (b)
    differ by more than the tolerances: {step, what, columns, diff}; None if none does."""
    for t in range(steps):
        for what, a, b, tol in (("frame", frames_a, frames_b, FRAME_TOL),
                                ("command", actions_a, actions_b, ACTION_TOL)):
            d = np.abs(np.asarray(a[t], np.float64) - np.asarray(b[t], np.float64))
            if not np.all(d <= tol):
                return {"step": t, "what": what, "columns": np.flatnonzero(~(d <= tol)).tolist(),
                        "diff": float(np.nanmax(d))}
    return None


def episode_rows(tr, episodes, steps: int) -> list[dict]:
    """Per episode: first divergence over the first `steps` valid steps, hit and landing of both."""
    rows = []
    for i, ep in enumerate(episodes):
        k = int(min(steps, tr.valid[i].sum()))
        rows.append({"episode": i, "diverges": first_divergence(tr.obs[i], tr.actions[i], ep.traj.obs[0],
                                                                ep.extras["commands"], k),
                     "hit": [bool(tr.hit[i]), bool(ep.traj.hit[0])],
                     "landing": [np.asarray(tr.landing[i]).tolist(), ep.traj.landing[0].tolist()],
                     "late_landing": late_landing(ep)})
    return rows


def late_landing(ep) -> bool:
    """The station saw a landing after the evaluation's time limit (launch + episode_s)."""
    ev = ep.meta.get("events") or {}
    t_land, t_launch = ev.get("t_land"), ev.get("t_launch")
    episode_s = ep.meta["contract"]["episode_s"]
    return t_land is not None and t_launch is not None and t_land - t_launch > episode_s


def summary(tr, episodes, rows: list[dict], n_goals: int) -> dict:
    diverged = [r["diverges"]["step"] for r in rows if r["diverges"] is not None]
    return {
        "episodes": len(episodes), "goals": n_goals,
        "eval": {**goal_metrics(tr.landing, tr.goal, tr.hit, tr.on_opponent),
                 "on_opponent": float(np.mean(tr.on_opponent))},
        "runner": goal_summary(episodes),
        "diverged": len(diverged), "first_divergence_steps": sorted(diverged),
        "same_hit": int(sum(a == b for a, b in (r["hit"] for r in rows))),
        "late_landings": int(sum(r["late_landing"] for r in rows)),
    }


def print_report(rows: list[dict], out: dict) -> None:
    for r in rows:
        d = r["diverges"]
        div = ("same" if d is None
               else f"{d['what']} differs at step {d['step']} (cols {d['columns']}, {d['diff']:.2e})")
        print(f"episode {r['episode']:3d}: {div}; hit {r['hit']}; landing eval {_xy(r['landing'][0])} "
              f"runner {_xy(r['landing'][1])}")
    for side in ("eval", "runner"):
        m = out[side]
        print(f"{side:6s}: <=30cm {m['within_30cm']:.1%}  <=20cm {m['within_20cm']:.1%}  "
              f"hit {m['hit_rate']:.1%}  on opponent {m['on_opponent']:.1%}  mean dist {m['mean_dist']:.3f}")


def _xy(p) -> str:
    return "-" if not all(math.isfinite(v) for v in p) else f"({p[0]:+.3f}, {p[1]:+.3f})"


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run", help="a run directory (or its checkpoints/)")
    p.add_argument("--member", type=int, default=0)
    p.add_argument("--n", type=int, default=100, help="uniform goals (episodes)")
    p.add_argument("--seed", type=int, default=1234, help="ttmjx eval's --seed")
    p.add_argument("--export", default=None, help="an export of that member (default: exported to a temp dir)")
    p.add_argument("--timing", choices=sorted(TIMING), default="zero", help="the station's timing profile")
    p.add_argument("--eval-timing", choices=sorted(TIMING), default=None,
                   help="evaluate under this timing profile (default: the run's own world timing)")
    p.add_argument("--start", choices=("launch", "trigger"), default="launch")
    p.add_argument("--pose", choices=("eval", "home"), default="eval",
                   help="start pose: the evaluation's (home + its reset noise) or the contract's home")
    p.add_argument("--charge-compute", action="store_true")
    p.add_argument("--throw-delay", type=float, default=1.0, help="s between arming and the launch")
    p.add_argument("--steps", type=int, default=20, help="steps compared per episode")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    cfg, params, goals, throws, tr = evaluation(a.run, a.member, a.n, a.seed,
                                                None if a.eval_timing is None else TIMING[a.eval_timing])
    export_dir = a.export or export(params, cfg.policy, cfg.world,
                                    os.path.join(tempfile.mkdtemp(), "policy"), source=f"{a.run}@member{a.member}")
    poses = np.asarray(tr.obs[:, 0, :8], np.float64) if a.pose == "eval" else None   # eval's start poses
    episodes, _, _ = runner_play(export_dir, goals, station_throws(throws), poses, a.timing,
                                 a.start == "launch", a.charge_compute, a.throw_delay)
    tr = jax.tree.map(lambda x: np.asarray(x)[:len(episodes)], tr)
    rows = episode_rows(tr, episodes, a.steps)
    out = {**summary(tr, episodes, rows, a.n), "run": a.run, "member": a.member, "seed": a.seed,
           "timing": a.timing, "eval_timing": a.eval_timing or "run's own", "start": a.start, "pose": a.pose, "charge_compute": a.charge_compute}
    print_report(rows, out)
    if a.json:
        print(json.dumps(files.json_safe(out)))
    return out


if __name__ == "__main__":
    main()
