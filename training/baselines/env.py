"""GoalsEye's task for one throw as a brax environment, for brax's own RL trainers (issue #12).

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
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from brax.envs.base import Env, State, Wrapper
from brax.envs.wrappers.training import EpisodeWrapper, VmapWrapper

from ttmjx.world import env as task
from ttmjx.world import thrower
from ttmjx.world.backends import MjxPhysics
from ttmjx.world.config import World
from ttmjx.world.goals import uniform_goals
from training.baselines.config import RewardConfig


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
        k_throw, k_goal, k_state = jax.random.split(rng, 3)
        th = jax.tree.map(lambda x: x[0], thrower.sample_throws(k_throw, self.cfg, 1))
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


class FreshAutoReset(Wrapper):
    """brax's AutoResetWrapper, but a finished episode restarts from a NEW reset (throw, goal,
    home-pose noise) drawn from a key carried per environment, not from its first state again.
    The reset is computed only when some environment finished (lax.cond)."""

    def reset(self, rng) -> State:
        state = self.env.reset(rng)
        state.info["reset_key"] = jax.vmap(lambda k: jax.random.fold_in(k, 1))(rng)
        return state

    def step(self, state: State, action) -> State:
        if "steps" in state.info:
            state.info.update(steps=jnp.where(state.done, jnp.zeros_like(state.info["steps"]), state.info["steps"]))
        state = self.env.step(state.replace(done=jnp.zeros_like(state.done)), action)
        keys = jax.vmap(jax.random.split)(state.info["reset_key"])
        state.info["reset_key"] = keys[:, 0]

        def restart(_):
            fresh = self.env.reset(keys[:, 1])
            pick = lambda a, b: jnp.where(state.done.reshape((-1,) + (1,) * (a.ndim - 1)) > 0, a, b)  # noqa: E731
            return (jax.tree.map(pick, fresh.pipeline_state, state.pipeline_state),
                    jax.tree.map(pick, fresh.obs, state.obs))

        ps, obs = jax.lax.cond(jnp.any(state.done > 0), restart,
                               lambda _: (state.pipeline_state, state.obs), None)
        return state.replace(pipeline_state=ps, obs=obs)


def wrap_fresh(env: Env, episode_length: int = 1000, action_repeat: int = 1, randomization_fn=None) -> Env:
    """brax.envs.training.wrap with FreshAutoReset in place of AutoResetWrapper (the trainers'
    `wrap_env_fn`)."""
    if randomization_fn is not None:
        raise ValueError("wrap_fresh: domain randomization is not supported")
    return FreshAutoReset(EpisodeWrapper(VmapWrapper(env), episode_length, action_repeat))
