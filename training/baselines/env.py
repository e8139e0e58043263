"""GoalsEye's task for one throw as a brax environment, for brax's own RL trainers.

The same world as GoalsEye's practice: MJX physics (ttmjx.world.backends.MjxPhysics), the
world's command clipping, events and observation (ttmjx.world.env), the world's throws
(ttmjx.world.thrower) and the evaluation's uniform goals on the opponent's half
(ttmjx.world.goals). Only the learning differs:

* observation [k * O]: the frame stack the GoalsEye framestack policy sees (env.observe),
  flattened, oldest frame first: joints, ball position, [ball velocity], goal, per frame.
* action [8] in brax's units (its policies are centred on 0, their exploration noise ~1):
  joint targets `home + a * reach`, reach = the larger distance from the home pose to either
  joint limit, then env.command clips to the joint ranges and to the speed limits exactly as for
  GoalsEye. So a = 0 holds the home pose, a in [-1, 1]^8 reaches every pose in the joint box and
  nothing else can be commanded; the map is affine, so a brax MLP whose mean is `a` is a
  GoalsEye framestack policy with Normalizer act_mean = home, act_std = reach (training/
  baselines/agents.py converts it; eval and export use it unchanged). An incremental map
  (target = last target + a * max step) would need the last target in the policy, which the
  observation does not hold: the policy would no longer be a function of what GoalsEye sees.
* control rate: the world's (World.control_hz), one step per control step.
* reward: the paper's RL baselines (Section V-B): closeness of the landing to the goal, paddle
  contact, landing on the opponent's half, and small penalties for the arm's distance from its
  home pose and for action changes; weights in RewardConfig.
* done: at the horizon (RewardConfig.end_at_landing=False, the default: every episode is
  World.horizon control steps, as GoalsEye's rollouts, so N trajectories are exactly N * horizon
  brax steps), or at the world's episode end (landing, ball below the table, horizon). After
  the world's episode end its events are frozen, so no reward term but the style penalties can
  change: the two settings differ only in compute and in the penalties after the landing.

Brax's AutoResetWrapper restarts a finished episode from the SAME first state (throw and goal)
forever; `wrap_fresh` is brax's training wrapper with a fresh reset (new throw, new goal) instead.

Throws are solved ahead, `pool` per environment at a time: solving a throw is a
Newton solve over simulated flights, thousands of sequential tiny steps whose latency on a GPU
does not depend on how many throws are solved together, and it used to run at every episode
end (inside the training step, once per `horizon` steps) and twice per ES epoch or evaluation
(the reset, and brax's automatic restart after the last step). With a pool, one solve of
n x pool throws serves `pool` episodes of n environments; every episode still starts from a
throw of its own, never reused (tests/test_baselines.py).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ttmjx.world.backends import MjxPhysics, import_mjx

import_mjx()   # brax imports mujoco.mjx: first without the optional Warp backend's noise
from brax.envs.base import Env, State, Wrapper  # noqa: E402
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper  # noqa: E402

from training.baselines.config import RewardConfig  # noqa: E402
from training.baselines.resumable import any_seed  # noqa: E402
from ttmjx.world import env as task  # noqa: E402
from ttmjx.world import thrower  # noqa: E402
from ttmjx.world.config import World  # noqa: E402
from ttmjx.world.env import uniform_goals  # noqa: E402

TERMS = ("r_goal", "r_hit", "r_opponent", "r_pose", "r_smooth")


def reach(cfg: World) -> np.ndarray:
    """[8] the action scale: the larger distance from the home pose to either joint limit."""
    r = cfg.robot
    home, lo, hi = (np.asarray(x, np.float32) for x in (r.home, r.lower, r.upper))
    return np.maximum(home - lo, hi - home)


def targets(cfg: World, action):
    """[8] brax action -> joint targets (before env.command's clipping): home + a * reach."""
    return jnp.asarray(cfg.robot.home, jnp.float32) + action * jnp.asarray(reach(cfg))


def reward_terms(cfg: World, rcfg: RewardConfig, before: task.State, after: task.State) -> dict:
    """The reward's terms {name: []} for one control step from `before` to `after`."""
    e0, e1 = before.events, after.events
    new = lambda flag: (getattr(e1, flag) & ~getattr(e0, flag)).astype(jnp.float32)  # noqa: E731
    landing = jnp.where(jnp.isfinite(e1.landing), e1.landing, 0.0)
    closeness = jnp.exp(-jnp.linalg.norm(landing - after.goal) / rcfg.goal_scale)
    home, scale = jnp.asarray(cfg.robot.home, jnp.float32), jnp.asarray(reach(cfg))
    seen = after.frames[-1][:8]           # the joints the policy sees
    max_step = jnp.asarray(cfg.robot.max_speed, jnp.float32) * cfg.robot.speed_margin * cfg.control_dt
    return {"r_goal": rcfg.goal * new("landed") * closeness,
            "r_hit": rcfg.hit * new("hit"),
            "r_opponent": rcfg.opponent * new("on_opponent"),
            "r_pose": -rcfg.pose * jnp.mean(((seen - home) / scale) ** 2),
            "r_smooth": -rcfg.smooth * jnp.mean(((after.target - before.target) / max_step) ** 2)}


class GoalEnv(Env):
    """One throw toward one goal (brax vmaps it); see the module docstring."""

    def __init__(self, cfg: World, reward: RewardConfig = RewardConfig()):
        self.cfg, self.reward_cfg = cfg, reward
        self.physics = MjxPhysics(cfg)
        self.lay = self.physics.lay

    def reset(self, rng) -> State:
        k_throw = jax.random.split(rng, 3)[0]
        return self.reset_with(rng, jax.tree.map(lambda x: x[0], thrower.sample_throws(k_throw, self.cfg, 1)))

    def reset_with(self, rng, th: thrower.Throw) -> State:
        """reset(rng) with the throw given (solved elsewhere, e.g. FreshAutoReset's pool): the goal
        and the home-pose noise are drawn from rng as reset draws them."""
        _, k_goal, k_state = jax.random.split(rng, 3)
        goal = uniform_goals(k_goal, 1, self.cfg.table)[0]
        s = task.reset(self.cfg, self.lay, k_state, th.launch_pos, th.launch_vel, th.launch_spin, th.aim, goal)
        zero = jnp.zeros((), jnp.float32)
        return State(pipeline_state=s, obs=self._obs(s), reward=zero, done=zero,
                     metrics={k: zero for k in TERMS}, info={})

    def step(self, state: State, action) -> State:
        s = state.pipeline_state
        target = task.command(self.cfg, s, targets(self.cfg, action))
        ctrl, cmds = task.controls(self.cfg, s, target)
        out = (self.physics.step(s.qpos, s.qvel, s.target, target) if ctrl is None
               else self.physics.step_ctrl(s.qpos, s.qvel, ctrl))
        s2 = task.advance(self.cfg, self.lay, s, target, *out, cmds=cmds)
        terms = reward_terms(self.cfg, self.reward_cfg, s, s2)
        done = s2.events.done if self.reward_cfg.end_at_landing else s2.t >= self.cfg.horizon
        return state.replace(pipeline_state=s2, obs=self._obs(s2), reward=sum(terms.values()),
                             done=done.astype(jnp.float32), metrics={**state.metrics, **terms})

    def _obs(self, s: task.State):
        return task.observe(self.cfg, self.lay, s).frames.reshape(-1)

    @property
    def observation_size(self) -> int:
        return self.cfg.frame_stack * self.cfg.obs_size

    @property
    def action_size(self) -> int:
        return 8

    @property
    def backend(self) -> str:
        return "mjx"


def _episode_info(state: State, n: int) -> State:
    """state with the info brax 0.14.2's EpisodeWrapper.reset adds (tests/test_baselines.py
    compares the structure with brax's own)."""
    zero = jnp.zeros((n,))
    state.info.update(steps=zero, truncation=zero, episode_done=zero,
                      episode_metrics={"sum_reward": zero, "length": zero, **{k: zero for k in state.metrics}})
    return state


class FreshAutoReset(Wrapper):
    """brax's AutoResetWrapper, but a finished episode restarts from a NEW reset (throw, goal,
    home-pose noise) drawn from a key carried per environment, not from its first state again.
    The restart is computed only when some environment finished (lax.cond; of any seed when
    the seeds are vmapped together, see any_seed).

    Throws come from a pool of `pool` per environment (info['throw_pool'] [n, pool, ...],
    info['throw_next'] [n]: the next unused one), solved in one batch at reset and again when an
    environment that finished has used all of its own (lax.cond): each episode's throw is used
    once. Wraps EpisodeWrapper(VmapWrapper(GoalEnv)) (wrap_fresh); reset builds that state
    directly (GoalEnv.reset_with + EpisodeWrapper's info)."""

    def __init__(self, env: Env, pool: int = 1):
        super().__init__(env)
        if int(pool) < 1:
            raise ValueError(f"throw pool {pool!r}; expected an integer >= 1")
        self.pool = int(pool)
        self.goal_env = env.unwrapped

    def _solve(self, key, n: int):
        """n x pool fresh throws, leaves [n, pool, ...]."""
        th = thrower.sample_throws(key, self.goal_env.cfg, n * self.pool)
        return jax.tree.map(lambda x: x.reshape((n, self.pool) + x.shape[1:]), th)

    def reset(self, rng) -> State:
        n = rng.shape[0]
        pool = self._solve(jax.random.fold_in(rng[0], 2), n)
        state = jax.vmap(self.goal_env.reset_with)(rng, jax.tree.map(lambda x: x[:, 0], pool))
        state = _episode_info(state, n)
        state.info.update(reset_key=jax.vmap(lambda k: jax.random.fold_in(k, 1))(rng), throw_pool=pool,
                          throw_next=jnp.ones((n,), jnp.int32))
        return state

    def step(self, state: State, action) -> State:
        if "steps" in state.info:
            state.info.update(steps=jnp.where(state.done, jnp.zeros_like(state.info["steps"]), state.info["steps"]))
        state = self.env.step(state.replace(done=jnp.zeros_like(state.done)), action)
        keys = jax.vmap(jax.random.split)(state.info["reset_key"])
        state.info["reset_key"] = keys[:, 0]
        n, pool, nxt = state.done.shape[0], state.info["throw_pool"], state.info["throw_next"]

        def restart(_):
            done = state.done > 0
            need = jnp.any(done & (nxt >= self.pool))

            def refill(_):   # where(need, ...): a seed that needs none keeps its pool (any_seed)
                fresh = self._solve(jax.random.fold_in(keys[0, 1], 3), n)
                return jax.tree.map(lambda a, b: jnp.where(need, a, b), fresh, pool), jnp.where(need, 0, nxt)
            p, i = jax.lax.cond(any_seed(need), refill, lambda _: (pool, nxt), None)
            th = jax.tree.map(lambda x: x[jnp.arange(n), jnp.minimum(i, self.pool - 1)], p)
            fresh = jax.vmap(self.goal_env.reset_with)(keys[:, 1], th)
            pick = lambda a, b: jnp.where(done.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
            return (jax.tree.map(pick, fresh.pipeline_state, state.pipeline_state),
                    jax.tree.map(pick, fresh.obs, state.obs), p, jnp.where(done, i + 1, i))

        ps, obs, pool, nxt = jax.lax.cond(any_seed(jnp.any(state.done > 0)), restart,
                                          lambda _: (state.pipeline_state, state.obs, pool, nxt), None)
        state.info.update(throw_pool=pool, throw_next=nxt)
        return state.replace(pipeline_state=ps, obs=obs)


def wrap_fresh(env: Env, episode_length: int = 1000, action_repeat: int = 1, randomization_fn=None,
               pool: int = 1) -> Env:
    """brax.envs.training.wrap with FreshAutoReset in place of AutoResetWrapper (the trainers'
    `wrap_env_fn`; `pool`: throws solved ahead per environment, functools.partial it in)."""
    if randomization_fn is not None:
        raise ValueError("wrap_fresh: domain randomization is not supported")
    return FreshAutoReset(EpisodeWrapper(VmapWrapper(env), episode_length, action_repeat), pool)
