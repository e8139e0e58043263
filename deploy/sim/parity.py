"""Parity: one export played twice on the same draws, by the training world and by the robot runner
on the simulated station, and where the two first part (`ttmjx robot parity`).

(a) The training world (ttmjx.world.backends.Backend, MuJoCo C or MJX) plays the export's weights
in JAX toward N uniform goals: the draw of `ttmjx eval --goals N --seed S` (goals, then throws and
the rollout key), each episode's start pose (home + the reset noise) and timing (latencies and
command delay drawn within the trained spreads, the tracker's phase `lead`, the joint sampling
phase) from that key. An ensemble export plays as the runner plays it: the members' actions
averaged at every step.

(b) deploy.robot.runner.Runner plays the export as loaded for the robot (numpy) on the simulated
station (deploy.sim.station, MuJoCo C), toward the same goals, on the same throws, from the same
start poses, with each episode's timing set to the world's draw: the station's latencies and
command delay are the drawn ones, its tracker samples the ball `lead` physics steps after the
launch and its joint feedback falls on the drawn phase, and the runner starts the episode on its
ball trigger as on the cell; each sensor sample's jitter and drop is the world's per-sample draw
(DrawnStation).

Per control step the two are compared on what the policy sees (the frame: sensed joints, sensed
ball, in 16-value frames its sensed velocity, goal) and on the command actually sent (the world's clipped target against the runner's
after its safety filter): the first step where each parts beyond its tolerance and by how much,
then hit, landing and the strict goal metrics of both on the same goals and throws.
"""
from __future__ import annotations

import dataclasses
import math
import os
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from deploy.robot.exported import _unflatten, read_weights
from deploy.robot.runner import Runner
from deploy.sim.station import Loaded, SimClock, SimStation, complete_episode, goal_summary
from ttmjx.world import files, observation, thrower, timing
from ttmjx.world.config import TIMING_PROFILES, Timing
from ttmjx.world.env import Policy, uniform_goals
from ttmjx.world.goals import goal_metrics
from ttmjx.world.record import OBS_JOINTS

# Tolerances of "the same": float32 rounding through two implementations of one network (frames
# and commands, rad or m), and a landing within 1 mm.
FRAME_TOL = COMMAND_TOL = 1e-4
# The sensed velocity is a slope over one tracker interval (8 ms at 125 Hz): FRAME_TOL over it.
VELOCITY_TOL = FRAME_TOL * 125.0
LANDING_TOL = 1e-3
# Each quantity compared per control step, with its tolerance.
TOLERANCES = {"joints_seen": FRAME_TOL, "ball_seen": FRAME_TOL, "ball_vel_seen": VELOCITY_TOL,
              "goal": FRAME_TOL, "command": COMMAND_TOL}
QUANTITIES = tuple(TOLERANCES)
ARMED_S = 1.0          # s between arming and the launch: the arm settles at its start pose


class ParityError(ValueError):
    """A parity request that cannot be played (exit 2 at the command line)."""


class WorldPlay(NamedTuple):
    """What the world played and drew: goals [N, 2], throws, Trajectories [N] (numpy), draws."""
    goals: np.ndarray
    throws: object
    tr: object
    draws: object


# --------------------------------------------------------------------------------------------
# (a) the world
# --------------------------------------------------------------------------------------------
def export_params(loaded: Loaded):
    """(PolicyConfig, PolicyParams with a leading [members] axis, members) of the export's
    weights, for the JAX policy (models.policy.make_policy)."""
    from models.config import PolicyConfig
    from models.normalizer import Normalizer
    from models.policy import PolicyParams
    spec, tensors = read_weights(loaded.policy_dir)
    members = int(tensors["net/params/head/bias"].shape[0])
    tensors = {k: jnp.asarray(v) for k, v in tensors.items()}
    norm = _unflatten(tensors, "norm")
    params = PolicyParams(_unflatten(tensors, "net"), Normalizer(**{k: norm[k] for k in Normalizer._fields}))
    pcfg = PolicyConfig(kind=spec.kind, hidden=spec.hidden, layers=spec.layers, obs_size=spec.obs_size,
                        frame_stack=spec.frame_stack)
    return pcfg, params, members


def averaged(policy: Policy) -> Policy:
    """The members of an ensemble [M, ...] acting as one: every member steps on the same
    observation and the actions are averaged (the runner's ensemble export)."""
    def init(p, key):
        return jax.vmap(lambda q: policy.init(q, key))(p)

    def apply(p, carry, obs, key):
        carry, act = jax.vmap(lambda q, c: policy.apply(q, c, obs, key))(p, carry)
        return carry, act.mean(0)
    return Policy(init, apply)


def world_play(loaded: Loaded, tm: Timing, backend: str, n: int, seed: int) -> WorldPlay:
    """The export played by the world on `backend` under the timing tm, toward n uniform goals of
    `ttmjx eval --seed seed`'s draw."""
    from models.policy import make_policy
    from ttmjx.world.backends import Backend
    cfg = dataclasses.replace(loaded.cfg, timing=tm)
    pcfg, params, _ = export_params(loaded)
    k_goal, k_run = jax.random.split(jax.random.PRNGKey(seed))
    goals = np.asarray(uniform_goals(k_goal, n, cfg.table), np.float32)
    k_throw, k_roll = jax.random.split(k_run)
    throws = thrower.sample_throws(k_throw, cfg, n)
    world = Backend(cfg, backend)
    tr = world.rollout_one(averaged(make_policy(pcfg)), params, k_roll, throws, goals)
    draws = jax.tree.map(np.asarray, world.timing_draws(k_roll, n))
    return WorldPlay(goals, throws, jax.tree.map(np.asarray, tr), draws)


# --------------------------------------------------------------------------------------------
# (b) the runner
# --------------------------------------------------------------------------------------------
@jax.jit
def _sample_draws(key, sensor, m):
    """(jitter fraction in [0, 1), keep draw in [0, 1)) of sample m of a sensor: the world's
    per-sample draws (ttmjx.world.timing.read)."""
    return (timing._uniform(key, sensor, m[None], 0)[0], timing._uniform(key, sensor, m[None], 1)[0])


class DrawnStation(SimStation):
    """The simulated station with each sample's jitter and drop drawn as the world draws them for
    the episode in play (`episode`: its tick-0 physics step, joint phase and timing key); outside
    an episode, from the station's own stream as SimStation draws them."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.episode: tuple[int, int, jax.Array] | None = None
        self._sensor = timing.JOINT

    def _sample(self, t: float) -> None:
        self._sensor = timing.JOINT
        super()._sample(t)

    def _sample_ball(self, t: float) -> None:
        self._sensor = timing.BALL
        super()._sample_ball(t)

    def _delivery(self, t: float, latency: float) -> float | None:
        if self.episode is None:
            return super()._delivery(t, latency)
        tick0, phase, key = self.episode
        every = self.ball_every if self._sensor == timing.BALL else self.joint_every
        offset = self.n - tick0 - (0 if self._sensor == timing.BALL else phase)
        jitter, keep = (float(x) for x in _sample_draws(key, self._sensor, jnp.int32(offset // every)))
        tm = self.timing
        if tm.drop_prob and keep < tm.drop_prob:
            return None
        return t + latency + jitter * tm.jitter_s


def station_throws(throws) -> list[tuple]:
    """The launches as the world's reset sees them (float32) -> SimStation.throw_in's tuples."""
    fields = [np.asarray(x, np.float32).astype(np.float64)
              for x in (throws.launch_pos, throws.launch_vel, throws.launch_spin, throws.aim)]
    return list(zip(*fields))


def drawn_timing(station: SimStation, draws, i: int) -> None:
    """Episode i's latencies and command delay (physics steps in the world's draw) on the station."""
    dt = station.dt
    station.tracker_latency_s = float(draws.ball_latency[i]) * dt
    station.joint_latency_s = float(draws.joint_latency[i]) * dt
    station.action_delay_s = float(draws.action_delay[i]) * dt
    if station.delays_log:
        station.delays_log[-1] = (station.tracker_latency_s, station.joint_latency_s, station.action_delay_s)


def runner_play(loaded: Loaded, tm: Timing, played: WorldPlay, poses=None, seed: int = 0):
    """(episodes, runner, station): the export played by the runner on a simulated station under
    `timing`, each episode lined up with the world's: its throw, goal and start pose poses [N, 8]
    (default: the world's), its timing draw, the tracker's first sample `lead` physics steps after
    the launch and the joint samples on the world's phase; started on the runner's ball trigger
    (without a tracker rate, at the launch, as the world's ideal episodes start)."""
    clock = SimClock()
    station = DrawnStation(loaded.cfg, loaded.contract, clock=clock, seed=seed, timing=tm)
    runner = Runner(station.robot, station.tracker, clock, loaded.policy, loaded.contract)
    station.prefetch()
    if poses is None:
        poses = np.asarray(played.tr.obs[:, 0, OBS_JOINTS], np.float64)   # the robot holds still at tick 0
    d = played.draws
    episodes = []
    for i, throw in enumerate(station_throws(played.throws)):
        if not runner.move_home(poses[i]):
            raise ParityError(f"episode {i}: the runner could not reach the start pose "
                              f"({runner.mode.name}); the station cannot be driven")
        lead, phase = int(d.lead[i]), int(d.joint_phase[i])
        base = math.ceil((clock.now() + ARMED_S - station.t_origin) / station.dt)
        step = base + (-base - lead) % station.ball_every        # the first tracker sample `lead` steps later
        station.joint_offset = (step + lead + phase) % station.joint_every
        station.episode = (step + lead, phase, jnp.asarray(d.key[i]))
        t_launch = station.throw_in((step - 0.5) * station.dt + station.t_origin - clock.now(), throw)
        drawn_timing(station, d, i)
        # Without a tracker rate the world's tick 0 is the launch and it acts at once: the runner
        # is told the launch (the station announces it); with one, the runner's own ball trigger.
        ep = runner.run_episode(played.goals[i], t_launch if tm.tracker_hz is None else None)
        if ep is None:
            raise ParityError(f"episode {i}: the runner never saw the ball (timing {tm})")
        episodes.append(complete_episode(ep, station.finish_throw(), loaded.contract))
        station.episode = None
    return episodes, runner, station


# --------------------------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------------------------
def step_differences(tr, ep, i: int, velocity: bool = False) -> dict[str, np.ndarray]:
    """{quantity: [T] largest absolute difference per control step} of world episode i and the
    runner's episode over the steps both logged (NaN where either did not). velocity: the policy
    reads 16-value frames, whose sensed ball velocity both records keep apart (`ball_vel`; for
    13-value frames the world's ball_vel is the true velocity, which no policy saw)."""
    t = min(tr.obs.shape[1], len(ep.traj.obs[0]))
    valid = np.asarray(tr.valid[i, :t]) & np.asarray(ep.traj.valid[0, :t])
    a, b = np.asarray(tr.obs[i, :t], np.float64), np.asarray(ep.traj.obs[0, :t], np.float64)
    cols = {"joints_seen": observation.JOINTS, "ball_seen": observation.BALL_POS, "goal": observation.GOAL}
    out = {k: np.abs(a[:, c] - b[:, c]).max(-1) for k, c in cols.items()}
    out["ball_vel_seen"] = (np.abs(np.asarray(tr.ball_vel[i, :t], np.float64)
                                   - np.asarray(ep.traj.ball_vel[0, :t], np.float64)).max(-1)
                            if velocity else np.zeros(t))
    out["command"] = np.abs(np.asarray(tr.actions[i, :t], np.float64)
                            - np.asarray(ep.extras["commands"][:t], np.float64)).max(-1)
    return {k: np.where(valid, out[k], np.nan) for k in QUANTITIES}


def first_part(diff: np.ndarray, tol: float) -> int | None:
    """The first step whose difference exceeds tol (None: none does)."""
    over = np.flatnonzero(np.nan_to_num(diff, nan=0.0) > tol)
    return int(over[0]) if over.size else None


def episode_row(tr, ep, i: int, velocity: bool = False) -> dict:
    """Episode i: per quantity the first step it parts and its largest difference; hit and
    landing on both sides (velocity: as step_differences)."""
    diffs = step_differences(tr, ep, i, velocity)
    parts = {k: first_part(v, TOLERANCES[k]) for k, v in diffs.items()}
    land_a, land_b = np.asarray(tr.landing[i], np.float64), np.asarray(ep.traj.landing[0], np.float64)
    both = np.all(np.isfinite(land_a)) and np.all(np.isfinite(land_b))
    firsts = [s for s in parts.values() if s is not None]
    return {
        "episode": i, "first_part": min(firsts) if firsts else None,
        "parts": parts, "max_diff": {k: float(np.nanmax(v)) if np.any(np.isfinite(v)) else None for k, v in diffs.items()},
        "hit": [bool(tr.hit[i]), bool(ep.traj.hit[0])],
        "landing": [land_a.tolist(), land_b.tolist()],
        "landing_diff_m": float(np.linalg.norm(land_a - land_b)) if both else None,
        "end": ep.meta["end"],
    }


def differences_by_step(tr, episodes, velocity: bool = False) -> dict[str, np.ndarray]:
    """{quantity: [N, T] per-step difference} over all episodes (NaN past either's end)."""
    rows = [step_differences(tr, ep, i, velocity) for i, ep in enumerate(episodes)]
    t = max(len(r["command"]) for r in rows)
    pad = lambda v: np.concatenate([v, np.full(t - len(v), np.nan)])  # noqa: E731
    return {k: np.stack([pad(r[k]) for r in rows]) for k in QUANTITIES}


def summary(played: WorldPlay, episodes, rows: list[dict]) -> dict:
    """Both sides' goal metrics on the same goals and throws, and how often and where they part."""
    tr = played.tr
    n = len(episodes)
    firsts = [r["first_part"] for r in rows if r["first_part"] is not None]
    land = [r["landing_diff_m"] for r in rows if r["landing_diff_m"] is not None]
    world = {**goal_metrics(tr.landing[:n], played.goals[:n], tr.hit[:n], tr.on_opponent[:n]),
             "on_opponent": float(np.mean(tr.on_opponent[:n]))}
    runner = goal_summary(episodes)
    return {
        "episodes": n,
        "world": world, "runner": runner,
        "gap_30cm_points": 100.0 * (runner["within_30cm"] - world["within_30cm"]),
        "parted": len(firsts), "first_part_steps": sorted(firsts),
        "parted_by": {q: sum(r["parts"][q] is not None for r in rows) for q in QUANTITIES},
        "same_hit": int(sum(a == b for a, b in (r["hit"] for r in rows))),
        "same_landing": int(sum(d <= LANDING_TOL for d in land)),
        "landing_diff_m": {"median": float(np.median(land)), "max": float(np.max(land))} if land else None,
    }


def parity_table(out: dict) -> str:
    """Per episode where the two part, then both sides' metrics."""
    lines = [f"{'ep':>3s}  {'parts at':>8s}  {'what':24s}  {'hit w/r':7s}  {'landing diff':>12s}"]
    for r in out["rows"]:
        what = ",".join(q for q in QUANTITIES if r["parts"][q] is not None and r["parts"][q] == r["first_part"])
        at = "-" if r["first_part"] is None else str(r["first_part"])
        ld = "-" if r["landing_diff_m"] is None else f"{100 * r['landing_diff_m']:.2f} cm"
        hit = "".join("y" if h else "n" for h in r["hit"])
        lines.append(f"{r['episode']:3d}  {at:>8s}  {what or 'same':24s}  {hit:7s}  {ld:>12s}")
    for side in ("world", "runner"):
        m = out[side]
        lines.append(f"{side:6s}: <=30cm {m['within_30cm']:.1%}  <=20cm {m['within_20cm']:.1%}  "
                     f"hit {m['hit_rate']:.1%}  on opponent {m['on_opponent']:.1%}")
    lines.append(f"parted {out['parted']} of {out['episodes']} episodes ({out['parted_by']}); same hit "
                 f"{out['same_hit']}, same landing (1 mm) {out['same_landing']}; runner - world "
                 f"{out['gap_30cm_points']:+.1f} points within 30 cm")
    return "\n".join(lines)


def plot(diffs: dict[str, np.ndarray], dt: float, path: str) -> None:
    """Per quantity the median and largest difference over episodes against the step (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, len(QUANTITIES), figsize=(4 * len(QUANTITIES), 3.2))
    for ax, q in zip(axes, QUANTITIES):
        v = diffs[q]
        t = np.arange(v.shape[1]) * dt
        with np.errstate(all="ignore"):
            finite = np.isfinite(v).any(0)
            ax.semilogy(t[finite], np.nanmax(v[:, finite], 0) + 1e-9, label="largest")
            ax.semilogy(t[finite], np.nanmedian(v[:, finite], 0) + 1e-9, label="median")
        ax.axhline(TOLERANCES[q], color="k", ls=":", lw=1, label="tolerance")
        ax.set_title(q.replace("_", " "))
        ax.set_xlabel("time since tick 0 (s)")
    axes[0].set_ylabel("|world - runner|")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    files.write_figure(path, fig, dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------------------------
# The whole comparison
# --------------------------------------------------------------------------------------------
def parity_timing(loaded: Loaded, name: str) -> Timing:
    """The timing both sides play: 'trained' (the export's, its per-episode spreads drawn),
    'centre' (the trained timing without its spreads) or a profile (zero, nominal)."""
    trained = loaded.cfg.timing
    if name == "trained":
        tm = trained
    elif name == "centre":
        tm = dataclasses.replace(trained, delay_spread_s=0.0, action_delay_spread_s=None)
    elif name in TIMING_PROFILES:
        tm = dataclasses.replace(TIMING_PROFILES[name], extrapolate_s=trained.extrapolate_s)
    else:
        raise ParityError(f"--timing {name!r}; expected trained, centre or one of {', '.join(TIMING_PROFILES)}")
    return tm


def run_parity(policy_dir: str, n: int = 16, seed: int = 1234, backend: str = "c", timing: str = "trained",
               out_dir: str | None = None) -> dict:
    """Play the export both ways (module docstring); the summary with a row per episode. out_dir:
    parity.json and parity.png written there (atomically)."""
    from deploy.robot.timing_check import TimingError
    from deploy.sim.station import load_for_station
    try:
        loaded = load_for_station(policy_dir)
    except TimingError as e:
        raise ParityError(f"--policy {policy_dir!r}: {e}") from None
    tm = parity_timing(loaded, timing)
    played = world_play(loaded, tm, backend, n, seed)
    episodes, runner, station = runner_play(loaded, tm, played, seed=seed)
    velocity = loaded.contract.obs_size > observation.BALL_VEL.start + 2       # 16-value frames
    rows = [episode_row(played.tr, ep, i, velocity) for i, ep in enumerate(episodes)]
    out = {**summary(played, episodes, rows), "rows": rows, "policy": policy_dir, "backend": backend,
           "timing": timing, "seed": seed, "goals": n,
           "runner_faults": {"skipped": runner.skipped, "overruns": runner.overruns,
                             "per_episode": [ep.meta["faults"] for ep in episodes]}}
    out = files.json_safe(out)
    if out_dir:
        os.makedirs(out_dir, exist_ok=True)
        files.write_json(os.path.join(out_dir, "parity.json"), out)
        plot(differences_by_step(played.tr, episodes, velocity), loaded.cfg.control_dt, os.path.join(out_dir, "parity.png"))
    return out

