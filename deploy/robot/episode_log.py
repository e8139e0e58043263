"""One robot episode as the project's trajectory record plus the runner's own arrays.

On disk (`save_episode`): `<name>.npz` + `<name>.meta.json` written by ttmjx.world.record.save (B = 1)
and `<name>.deploy.npz` beside them with the arrays below (plain numeric, loaded without pickle).

Per tick (T = contract horizon):
  t_grid [T]       deadline t0 + n * dt (the time observations are interpolated to)
  t_wake [T]       when the tick started (NaN if skipped)
  t_sent [T]       when its command was sent (NaN if skipped or nothing sent)
  latency [T]      t_sent - t_grid
  executed [T]     the tick ran (False: its deadline passed first, or after the episode ended)
  raw_actions [T, 8]   the policy's output (NaN where it was not called)
  commands [T, 8]      the target sent (= Trajectories.actions; the held target on skipped ticks)
  faults [T]       int32 fault bits (deploy.robot.safety.FAULTS)
  ball_used_t [T, 2], ball_used_xyz [T, 2, 3]    the two tracker samples interpolated
  joint_used_t [T, 2], joint_used_q [T, 2, 8]    the two joint samples interpolated
Raw streams, everything received during the episode (accepted or not):
  ball_t [N], ball_xyz [N, 3], ball_ok [N]   the tracker's samples (sample time, position)
  joint_t [M], joint_q [M, 8], joint_ok [M]  the joint feedback
Times are the runner's clock; positions table frame, m. The record's `obs` holds what the policy
saw: the line through the two tracker samples used, evaluated at the tick. None of these is
the ball's true position: only the simulated station knows it, and adds (deploy.sim.station.with_truth)
  true_ball_t [P], true_ball_xyz [P, 3]   the true centre at the launch and every physics step
                                          until the throw was over (landing included)
  true_ball_pos [T, 3]                    the true centre at each tick's t_grid (NaN outside)
"""
from __future__ import annotations

import contextlib
import json
import os
import re
from typing import NamedTuple

import numpy as np

from deploy.robot.contract import REAL_OBS_SIZE
from ttmjx.world import files, observation, record
from ttmjx.world.record import Trajectories

EXTRAS_SUFFIX = ".deploy.npz"


class Episode(NamedTuple):
    traj: Trajectories      # B = 1
    extras: dict            # name -> array (see the module docstring)
    meta: dict              # JSON-ready


class EpisodeLog:
    """Arrays of one episode, filled tick by tick."""

    def __init__(self, horizon: int, goal: np.ndarray, obs_size: int = REAL_OBS_SIZE):
        T = horizon
        self.horizon, self.goal = T, np.asarray(goal, np.float32)
        nan = lambda *s: np.full(s, np.nan)  # noqa: E731
        # The record's 13-value frames (a 16-value policy's velocity columns are `ball_vel`, the
        # same slope: observation.to_width(obs, 16, ball_vel) gives back what the policy saw).
        observation.check_width(obs_size)
        self.obs = np.zeros((T, REAL_OBS_SIZE), np.float32)
        self.ball_vel = np.zeros((T, 3), np.float32)
        self.valid = np.zeros(T, bool)
        self.t_grid, self.t_wake, self.t_sent = nan(T), nan(T), nan(T)
        self.executed = np.zeros(T, bool)
        self.raw_actions, self.commands = nan(T, 8), nan(T, 8)
        self.faults = np.zeros(T, np.int32)
        self.ball_used_t, self.ball_used_xyz = nan(T, 2), nan(T, 2, 3)
        self.joint_used_t, self.joint_used_q = nan(T, 2), nan(T, 2, 8)
        self._ball, self._joint = [], []

    def add_ball(self, t: float, xyz: np.ndarray, ok: bool) -> None:
        self._ball.append((t, np.asarray(xyz, np.float64).reshape(3), ok))

    def add_joint(self, t: float, q: np.ndarray, ok: bool) -> None:
        self._joint.append((t, np.asarray(q, np.float64).reshape(8), ok))

    def tick(self, n: int, *, t_grid, frame, ball, joint, command, faults, executed,
             t_wake=np.nan, t_sent=np.nan, raw_action=None) -> None:
        """Record tick n. ball/joint: the Interpolated used; frame [O]; command [8]."""
        self.t_grid[n], self.t_wake[n], self.t_sent[n] = t_grid, t_wake, t_sent
        self.obs[n], self.ball_vel[n] = observation.to_width(frame, REAL_OBS_SIZE), ball.slope
        self.valid[n], self.executed[n] = True, executed
        self.commands[n] = command
        if raw_action is not None:
            self.raw_actions[n] = raw_action
        self.faults[n] |= faults
        self.ball_used_t[n] = (ball.t_lo, ball.t_hi)
        self.ball_used_xyz[n] = (ball.x_lo, ball.x_hi)
        self.joint_used_t[n] = (joint.t_lo, joint.t_hi)
        self.joint_used_q[n] = (joint.x_lo, joint.x_hi)

    def extras(self) -> dict:
        ball, joint = self._ball, self._joint
        return {
            "t_grid": self.t_grid, "t_wake": self.t_wake, "t_sent": self.t_sent,
            "latency": self.t_sent - self.t_grid, "executed": self.executed,
            "raw_actions": self.raw_actions, "commands": self.commands, "faults": self.faults,
            "ball_used_t": self.ball_used_t, "ball_used_xyz": self.ball_used_xyz,
            "joint_used_t": self.joint_used_t, "joint_used_q": self.joint_used_q,
            "ball_t": np.array([b[0] for b in ball], np.float64),
            "ball_xyz": np.array([b[1] for b in ball], np.float64).reshape(-1, 3),
            "ball_ok": np.array([b[2] for b in ball], bool),
            "joint_t": np.array([j[0] for j in joint], np.float64),
            "joint_q": np.array([j[1] for j in joint], np.float64).reshape(-1, 8),
            "joint_ok": np.array([j[2] for j in joint], bool),
        }

    def trajectories(self) -> Trajectories:
        """The B = 1 record. ball_vel is the slope between the two ball samples used (an
        estimate: the robot observes no velocity). Outcome fields the runner cannot see (hit,
        landing, net...) are False / -1 / NaN; launch_pos/launch_vel are the first tick's ball
        position and velocity estimate; launch_spin and aim are NaN."""
        nan2, nan3 = np.full((1, 2), np.nan, np.float32), np.full((1, 3), np.nan, np.float32)
        first = int(np.argmax(self.valid)) if self.valid.any() else 0
        f = np.zeros(1, bool)
        return record.to_numpy(Trajectories(
            obs=self.obs[None], ball_vel=self.ball_vel[None],
            actions=np.nan_to_num(self.commands, nan=0.0)[None], valid=self.valid[None],
            goal=self.goal[None], hit=f, hit_step=np.full(1, -1, np.int32), landing=nan2,
            on_opponent=f, bounce_own=f, net=f,
            launch_pos=observation.ball_pos(self.obs[first])[None], launch_vel=self.ball_vel[first][None],
            launch_spin=nan3, aim=nan2))


def save_episode(directory: str, name: str, ep: Episode) -> str:
    """Write the record (ttmjx.world.record.save) and the extras beside it; refuses to overwrite.
    In a session directory being resumed (`session`), an episode already logged is compared with
    the one the session replays instead: equal, it is kept; different, a ValueError names it."""
    extras_path = os.path.join(directory, name + EXTRAS_SUFFIX)
    resumed = _RESUMED.get(os.path.abspath(directory))
    if resumed is not None:
        if not os.path.exists(os.path.join(directory, PLAN_FILE)):
            files.write_json(os.path.join(directory, PLAN_FILE), resumed)   # with the first episode
        if episode_complete(directory, name):
            same_episode(directory, name, ep)
            return os.path.join(directory, name + ".npz")
    if os.path.exists(extras_path):
        raise FileExistsError(f"{extras_path} already exists; refusing to overwrite an episode log")
    tmp = extras_path + ".tmp.npz"
    try:
        path = record.save(directory, ep.traj, ep.meta, name=name)
        np.savez(tmp, **ep.extras)
        os.replace(tmp, extras_path)
    except OSError as e:        # a full disk: numpy's writes name no file
        if e.filename or e.errno is None:
            raise
        raise OSError(e.errno, f"{e.strerror} (logging episode {name}; the episodes before it are kept)",
                      os.path.join(directory, name)) from None
    return path


def load_episode(directory: str, name: str) -> Episode:
    """Inverse of save_episode (no pickle)."""
    traj, meta = record.load(directory, name)
    extras_path = os.path.join(directory, name + EXTRAS_SUFFIX)
    if not os.path.exists(extras_path):
        raise record.RecordError(f"{extras_path}: missing (an episode log without its runner arrays)")
    with np.load(extras_path, allow_pickle=False) as z:
        extras = {k: z[k] for k in z.files}
    return Episode(traj, extras, meta)


# -- sessions: a directory of one session's episode logs, resumable --------------------------
# A session directory holds PLAN_FILE (what the session is: the export's manifest hash, the
# goals, the seed, the station and its timing), the episodes `episode_<i:04d>` as they end, and
# SESSION_FILE (the summary) when the session is complete. The same command on a directory with
# an unfinished session resumes it: on a reproducible station (simulated or fake time) the session
# is played again from its start, each episode already logged compared with the replayed one and
# kept, and the episodes after it logged, so the summary is the uninterrupted session's.
PLAN_FILE = "session.plan.json"
SESSION_FILE = "session.json"
_EPISODE = re.compile(r"(episode_\d{4})(\.npz|\.meta\.json|\.deploy\.npz|\.npz\.tmp\.npz|\.deploy\.npz\.tmp\.npz|)$")
_RESUMED: dict[str, dict] = {}      # absolute session directory -> its plan, while a session runs


def episode_complete(directory: str, name: str) -> bool:
    return all(os.path.exists(os.path.join(directory, name + ext)) for ext in (".npz", ".meta.json", EXTRAS_SUFFIX))


def _arrays_equal(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and bool(np.all((a == b) | ((a != a) & (b != b))))


def same_episode(directory: str, name: str, ep: Episode) -> None:
    """ValueError naming the logged episode if the replayed `ep` differs from it."""
    old = load_episode(directory, name)
    new_traj = record.to_numpy(ep.traj)
    diff = [f for f in new_traj._fields if not _arrays_equal(getattr(new_traj, f), getattr(old.traj, f))]
    diff += [k for k in set(ep.extras) | set(old.extras)
             if k not in ep.extras or k not in old.extras or not _arrays_equal(ep.extras[k], old.extras[k])]
    meta = json.loads(json.dumps(files.json_safe(ep.meta)))
    diff += [k for k in meta if old.meta.get(k) != meta[k]]
    if diff:
        raise ValueError(f"{os.path.join(directory, name)}: the resumed session replays this episode differently "
                         f"({', '.join(sorted(diff)[:4])} differ); {directory} holds another session: choose a new --out")


def describe(directory: str) -> str:
    """What a directory that is not a robot session holds, in a few words."""
    what = files.what_it_holds(directory)
    if what.startswith("robot episode logs"):     # episodes without a plan: not this command's kind
        return what.replace("robot episode logs", f"episode logs without {PLAN_FILE} (another command's session)", 1)
    return what


def session_state(directory: str | None, plan: dict) -> tuple[str, int]:
    """('new' | 'resume' | 'finished', episodes logged) of a session directory for the session
    `plan` (JSON values); ValueError naming the directory if it holds something else (another
    session, a training run, an export, other files). Nothing is written."""
    if directory is None or not os.path.exists(directory):
        return "new", 0
    if not os.path.isdir(directory):
        raise ValueError(f"--out {directory!r} is a file; expected a new directory or one of this session's")
    names = os.listdir(directory)
    if not names:
        return "new", 0
    plan_path = os.path.join(directory, PLAN_FILE)
    if not os.path.exists(plan_path):
        raise ValueError(f"--out {directory!r} holds {describe(directory)}, not a session of this command; "
                         f"choose a new or empty directory")
    try:
        with open(plan_path) as f:
            saved = json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{plan_path}: unreadable ({e}); delete {directory} or choose a new --out") from None
    plan = json.loads(json.dumps(files.json_safe(plan)))
    diff = sorted(k for k in set(saved) | set(plan) if saved.get(k) != plan.get(k))
    if diff:
        raise ValueError(f"--out {directory!r} holds another session (its {', '.join(diff)} differ from this "
                         f"command's); choose a new --out")
    foreign = [n for n in names if n not in (PLAN_FILE, SESSION_FILE) and not _EPISODE.match(n)
               and not (n.startswith(".") and n.endswith(".tmp"))]
    if foreign:
        raise ValueError(f"--out {directory!r}: a session directory that also holds {', '.join(sorted(foreign)[:4])}; "
                         f"move them away or choose a new --out")
    logged = sorted({m.group(1) for m in map(_EPISODE.match, names) if m})
    done = sum(episode_complete(directory, n) for n in logged)
    if os.path.exists(os.path.join(directory, SESSION_FILE)):
        return "finished", done
    return "resume", done


@contextlib.contextmanager
def session(directory: str | None, plan: dict):
    """The session in `directory` (None: no logs) while it runs: a new one writes `plan` with its
    first episode; an unfinished one (session_state 'resume') has its torn episode files (a kill
    mid-save) removed and its logged episodes compared, not rewritten, as they are replayed."""
    if directory is None:
        yield
        return
    state, _ = session_state(directory, plan)
    key = os.path.abspath(directory)
    if state == "resume":
        for n in os.listdir(directory):
            m = _EPISODE.match(n)
            if (m and not episode_complete(directory, m.group(1))) or (n.startswith(".") and n.endswith(".tmp")):
                os.remove(os.path.join(directory, n))
    _RESUMED[key] = json.loads(json.dumps(files.json_safe(plan)))
    try:
        yield
    finally:
        _RESUMED.pop(key, None)


def read_session(directory: str) -> dict:
    """The summary of a finished session (SESSION_FILE)."""
    path = os.path.join(directory, SESSION_FILE)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable ({e}); delete it to play the session's last episodes again") from None
