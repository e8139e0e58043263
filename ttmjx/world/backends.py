"""Two physics backends for one task, and the batched rollout that produces Trajectories.

* MJX: the whole rollout (policy, clipping, physics substeps, events) is one jit-compiled,
  vmapped `lax.scan`; the air forces MJX lacks come from ttmjx.world.ballphysics via xfrc_applied.
* MuJoCo C: physics in batched multi-threaded `mujoco.rollout` calls, one control step at a time
  (MuJoCo's own ellipsoid fluid model flies the ball); the policy and the task logic run as
  jit-compiled, vmapped JAX between the calls. The default on a CPU, where MJX is far slower
  (shared docs: PHYSICS.md; docs/BENCHMARKS.md).
"""
from __future__ import annotations

import dataclasses
import functools
import os
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ttmjx.world import ballphysics, env, observation, scene, timing
from ttmjx.world.config import World
from ttmjx.world.record import Trajectories, TrueTrack

@dataclasses.dataclass(frozen=True)
class BackendKind:
    """What a physics backend is and can do: the one place that tells the backends apart."""
    name: str
    about: str
    traceable: bool       # its rollouts are pure JAX: jitted and vmapped whole (rounds, seeds)
    demo_chunk: int       # throws per demonstration batch (large for latency-bound devices)

    def device(self, nthread: int | None = None) -> str:
        """The device it computes on, for reports."""
        return str(jax.devices()[0].device_kind) if self.traceable else f"cpu x{nthread or os.cpu_count()}"


REGISTRY = {
    "c": BackendKind("c", "MuJoCo C (mujoco.rollout) on the host's threads", traceable=False, demo_chunk=500),
    "mjx": BackendKind("mjx", "MJX (JAX) on the default device", traceable=True, demo_chunk=16384),
}
BACKENDS = tuple(REGISTRY)


def on_accelerator() -> bool:
    return jax.default_backend() in ("gpu", "cuda", "rocm", "tpu")


def backend_kind(name: str) -> BackendKind:
    """The registry's entry of a backend name ('auto': MJX on an accelerator, MuJoCo C on a CPU,
    where MJX is far slower); ValueError naming the choices otherwise."""
    if name == "auto":
        name = "mjx" if on_accelerator() else "c"
    if name not in REGISTRY:
        raise ValueError(f"unknown backend {name!r}; expected 'auto' or one of {BACKENDS}")
    return REGISTRY[name]


def resolve_backend(name: str) -> str:
    """'auto' -> the backend for this machine's device; a known name -> itself."""
    return backend_kind(name).name


Policy = env.Policy


def import_mjx():
    """mujoco.mjx, without the "Failed to import warp" lines its optional Warp backend prints
    when Warp is not installed (TTMJX_VERBOSE=1 shows them). Import brax after this too."""
    import sys
    if "mujoco.mjx" not in sys.modules and os.environ.get("TTMJX_VERBOSE", "") in ("", "0"):
        import contextlib
        import io
        said = io.StringIO()
        with contextlib.redirect_stdout(said):
            import mujoco.mjx  # noqa: F401
        rest = [ln for ln in said.getvalue().splitlines(keepends=True)
                if not ln.startswith(("Failed to import warp", "Failed to import mujoco_warp"))]
        sys.stdout.write("".join(rest))
    from mujoco import mjx
    return mjx


# MuJoCo Warp's buffers (world.mjx_impl = "warp"): contacts over all worlds of a batch (the
# scene has at most a few per world: ball with table, net or paddle), constraint rows per world.
WARP_CONTACTS = 1 << 20
WARP_CONSTRAINTS = 128


def _require_warp():
    """Raise naming the fix when world.mjx_impl = "warp" but warp-lang is missing."""
    import importlib.util
    if importlib.util.find_spec("warp") is None:
        raise RuntimeError("world.mjx_impl='warp' needs warp-lang: pip install 'ttmjx[warp]' "
                           "(or use --world.mjx-impl jax)")


def _ramp(ctrl0, ctrl1, n: int):
    """[..., n, 8] targets interpolated linearly over the n physics steps of a control step."""
    w = (jnp.arange(1, n + 1, dtype=jnp.float32) / n)[:, None]
    return ctrl0[..., None, :] + w * (ctrl1 - ctrl0)[..., None, :]


def _quat_rotate(q, v):
    """Rotate v [3] by the unit quaternion q [4] (w, x, y, z)."""
    w, u = q[0], q[1:]
    return v + 2.0 * jnp.cross(u, jnp.cross(u, v) + w * v)


class MjxPhysics:
    """MJX physics for one throw; jit/vmap the methods."""

    def __init__(self, cfg: World):
        mjx = import_mjx()
        self.cfg = cfg
        self.m = scene.model(cfg, fluid=False)  # zero density: MJX's box drag would be wrong
        self.lay = env.layout(self.m)
        self.ball_body = int(self.m.body("ball").id)
        if cfg.mjx_impl == "warp":
            _require_warp()
            self.mx = mjx.put_model(self.m, impl="warp")
            # Warp allocates its contact and constraint buffers up front: contacts are counted
            # over every world of a batch (vmap's episodes and lanes alike), constraints per world.
            self._data0 = mjx.make_data(self.m, impl="warp", naconmax=WARP_CONTACTS, njmax=WARP_CONSTRAINTS)
        else:
            self.mx = mjx.put_model(self.m)
            self._data0 = mjx.make_data(self.mx)

    def step(self, qpos, qvel, ctrl0, ctrl1):
        """One control step ramping the targets from ctrl0 to ctrl1 [8]; see step_ctrl."""
        return self.step_ctrl(qpos, qvel, _ramp(ctrl0, ctrl1, self.cfg.substeps))

    def step_ctrl(self, qpos, qvel, ctrl):
        """One control step. qpos [nq], qvel [nv], ctrl [S, 8] targets per physics step ->
        (qpos, qvel, ball [S, 6] world pos+vel after each physics step, paddle [S, 3], joints [S, 8])."""
        mjx = import_mjx()
        cfg, lay = self.cfg, self.lay
        bq, bv = lay.ball_qpos, lay.ball_qvel
        rq = jnp.array(lay.robot_qpos)

        def substep(d, ctrl):
            vel = d.qvel[bv:bv + 3]
            spin = _quat_rotate(d.qpos[bq + 3:bq + 7], d.qvel[bv + 3:bv + 6])
            force, torque = ballphysics.air_force_torque(vel, spin, cfg.ball)
            xfrc = jnp.zeros_like(d.xfrc_applied).at[self.ball_body].set(jnp.concatenate([force, torque]))
            d = mjx.step(self.mx, d.replace(ctrl=ctrl, xfrc_applied=xfrc))
            ball = jnp.concatenate([d.qpos[bq:bq + 3], d.qvel[bv:bv + 3]])
            return d, (ball, d.sensordata[:3], d.qpos[rq])

        d = self._data0.replace(qpos=qpos, qvel=qvel)
        d, (ball, paddle, joints) = jax.lax.scan(substep, d, ctrl)
        return d.qpos, d.qvel, ball, paddle, joints


class CPhysics:
    """MuJoCo C physics for a batch, through mujoco.rollout's persistent thread pool."""

    def __init__(self, cfg: World, nthread: int | None = None):
        self.cfg = cfg
        self.m = scene.model(cfg, fluid=True)
        self.lay = env.layout(self.m)
        self.nthread = nthread or os.cpu_count() or 1
        self.datas = [mujoco.MjData(self.m) for _ in range(self.nthread)]
        from mujoco import rollout
        self.pool = rollout.Rollout(nthread=self.nthread)
        self.spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.nstate = mujoco.mj_stateSize(self.m, self.spec)
        self.nq, self.nv = self.m.nq, self.m.nv

    def initial_state(self, qpos, qvel):
        """[B, nstate] full physics state for mujoco.rollout from qpos [B, nq], qvel [B, nv]."""
        b = qpos.shape[0]
        st = np.zeros((b, self.nstate))
        st[:, 1:1 + self.nq] = qpos
        st[:, 1 + self.nq:1 + self.nq + self.nv] = qvel
        return st

    def step(self, qpos, qvel, ctrl0, ctrl1):
        """One control step for B throws ramping the targets from ctrl0 to ctrl1 [B, 8]; see step_ctrl."""
        return self.step_ctrl(qpos, qvel, np.asarray(_ramp(np.asarray(ctrl0, np.float64), np.asarray(ctrl1, np.float64),
                                                           self.cfg.substeps), np.float64))

    def step_ctrl(self, qpos, qvel, ctrl):
        """One control step for B throws. qpos [B, nq], qvel [B, nv], ctrl [B, S, 8] targets per
        physics step -> (qpos [B, nq], qvel [B, nv], ball [B, S, 6], paddle [B, S, 3], joints
        [B, S, 8]) as numpy float64."""
        qpos, qvel = np.asarray(qpos, np.float64), np.asarray(qvel, np.float64)
        ctrl = np.asarray(ctrl, np.float64)
        state, sensordata = self.pool.rollout(self.m, self.datas, self.initial_state(qpos, qvel), ctrl,
                                              nstep=self.cfg.substeps)
        nq, nv = self.nq, self.nv
        lay = self.lay
        q = state[:, :, 1:1 + nq]
        v = state[:, :, 1 + nq:1 + nq + nv]
        ball = np.concatenate([q[:, :, lay.ball_qpos:lay.ball_qpos + 3],
                               v[:, :, lay.ball_qvel:lay.ball_qvel + 3]], axis=-1)
        return q[:, -1], v[:, -1], ball, sensordata[:, :, :3], q[:, :, list(lay.robot_qpos)]

    def close(self):
        self.pool.close()


def _record(cfg: World, lay: env.Layout, states: env.State, frames, vels, actions, valids) -> Trajectories:
    """Assemble Trajectories from the final states and per-step arrays [B, T, ...]."""
    ev = states.events
    obs13 = observation.to_width(frames, 13, xp=jnp)   # the record keeps 13 values and the velocity apart
    return Trajectories(
        obs=obs13, ball_vel=vels, actions=actions, valid=valids, goal=states.goal,
        hit=ev.hit, hit_step=ev.hit_step, landing=jnp.where(ev.hit[:, None], ev.landing, jnp.nan),
        on_opponent=ev.on_opponent, bounce_own=ev.bounce_own, net=ev.net,
        launch_pos=states.launch[:, 0:3], launch_vel=states.launch[:, 3:6],
        launch_spin=states.launch[:, 6:9], aim=states.aim)


def _true_track(lay: env.Layout, qpos, ball_steps, xp=jnp) -> TrueTrack:
    """TrueTrack from qpos [B, T, nq] at the start of each control step and the ball [B, T, S, 3]
    after each of its physics steps."""
    b, t, s = ball_steps.shape[:3]
    ball = qpos[:, :, lay.ball_qpos:lay.ball_qpos + 3]
    fine = xp.concatenate([ball[:, :1], ball_steps.reshape(b, t * s, 3)], 1)
    f32 = lambda x: xp.asarray(x, xp.float32)  # noqa: E731
    return TrueTrack(ball=f32(ball), joints=f32(qpos[:, :, list(lay.robot_qpos)]), ball_physics=f32(fine))


@functools.cache
def _primitives(cfg: World, lay: env.Layout) -> tuple:
    """(reset, observe, command, controls, advance) batched over throws, jitted where they run
    alone: one set per world, shared by every Backend of it, so that a new Backend (one per
    evaluation, say) runs what an earlier one traced and compiled."""
    return (jax.jit(jax.vmap(functools.partial(env.reset, cfg, lay))),
            jax.vmap(functools.partial(env.observe, cfg, lay)),
            jax.vmap(functools.partial(env.command, cfg)),
            jax.jit(jax.vmap(functools.partial(env.controls, cfg))),
            jax.jit(jax.vmap(functools.partial(env.advance, cfg, lay))))


class _Recent(dict):
    """A dict that keeps its `size` most recently used entries: compiled rollouts, keyed by the
    policy they play (a policy wrapped anew for each round would otherwise pile them up). For
    one thread: a read moves the entry to the end."""

    def __init__(self, size: int):
        super().__init__()
        self.size = size

    def __getitem__(self, key):
        value = super().pop(key)
        super().__setitem__(key, value)      # most recent last
        return value

    def __setitem__(self, key, value):
        super().pop(key, None)
        super().__setitem__(key, value)
        while len(self) > self.size:
            del self[next(iter(self))]


@functools.cache
def _rollouts(cfg: World, lay: env.Layout) -> _Recent:
    """The compiled rollouts of one world, shared by its Backends (see _primitives)."""
    return _Recent(16)


class Backend:
    """reset/step/rollout for a batch of throws on one physics backend."""

    def __init__(self, cfg: World, name: str = "c", nthread: int | None = None):
        if name == "auto" or name not in REGISTRY:
            raise ValueError(f"unknown backend {name!r}; expected one of {BACKENDS}")
        self.kind = REGISTRY[name]
        self.cfg, self.name = cfg, name
        self.physics = MjxPhysics(cfg) if self.kind.traceable else CPhysics(cfg, nthread)
        self.lay = self.physics.lay
        self._reset, self._observe, self._command, self._controls, self._advance = _primitives(cfg, self.lay)
        self._rollouts = _rollouts(cfg, self.lay)

    # -- batched primitives ---------------------------------------------------------------
    def reset(self, key, throws, goals) -> env.State:
        """[B] states at launch. throws: a Throw with [B, ...] fields; goals [B, 2]."""
        b = np.shape(throws.launch_pos)[0]
        goals = env.check_goals(goals, b)
        keys = jax.random.split(key, b)
        return self._reset(keys, jnp.asarray(throws.launch_pos, jnp.float32),
                           jnp.asarray(throws.launch_vel, jnp.float32),
                           jnp.asarray(throws.launch_spin, jnp.float32),
                           jnp.asarray(throws.aim, jnp.float32), jnp.asarray(goals))

    def step(self, states: env.State, actions) -> env.State:
        """One control step for B throws with actions [B, 8] (validated)."""
        actions = env.check_actions(actions, states.t.shape[0])
        target = self._command(states, jnp.asarray(actions))
        return self._advance(states, target, *self._physics(states, target))

    def _physics(self, states: env.State, target):
        """One control step of physics for the batch -> (qpos, qvel, ball, paddle, joints, cmds)."""
        # Ideal timing ramps inside the physics step (no command history to keep).
        ctrl, cmds = (None, states.cmds) if self.cfg.timing.ideal else self._controls(states, target)
        if self.kind.traceable:
            if ctrl is None:
                out = jax.vmap(self.physics.step)(states.qpos, states.qvel, states.target, target)
            else:
                out = jax.vmap(self.physics.step_ctrl)(states.qpos, states.qvel, ctrl)
        elif ctrl is None:
            out = self.physics.step(np.asarray(states.qpos), np.asarray(states.qvel),
                                    np.asarray(states.target), np.asarray(target))
        else:
            out = self.physics.step_ctrl(np.asarray(states.qpos), np.asarray(states.qvel), np.asarray(ctrl))
        return (*out, cmds)

    # -- rollouts ------------------------------------------------------------------------
    def rollout(self, policy: Policy, params, keys, throws, goals, horizon: int | None = None,
                members: int | None = None, truth: bool = False):
        """Roll `policy` out in L independent lanes of B throws: params leaves [L, ...], keys [L]
        (one rollout key per lane), throws [L, B, ...], goals [L, B, 2] -> Trajectories
        [L, B, ...] with T = horizon (default cfg.horizon) steps. One run is a lane of one
        (rollout_one).

        Lane l gets exactly the draws and record it gets alone: on MJX the one-lane rollout
        (rollout_fn) is vmapped over lanes; on MuJoCo C the L x B throws step together through
        one host loop (one thread pool, one policy call per control step).

        members=N: params carry an ensemble axis [L, N, ...]; throw b of a lane is played by
        member b // (B / N) (B must be a multiple of N).

        truth=True: (record, TrueTrack [L, B, ...]), the simulation's true ball and joints beside
        what the policy observed (evaluation and recording paths; the same draws and record)."""
        goals = _check_lanes(throws, goals, members)
        t_max = horizon or self.cfg.horizon
        if self.kind.traceable:
            key_ = ("mjx", policy, t_max, members, truth)
            if key_ not in self._rollouts:
                self._rollouts[key_] = jax.jit(jax.vmap(self.rollout_fn(policy, t_max, members, truth)))
            return self._rollouts[key_](params, keys, throws, jnp.asarray(goals))
        return self._c_rollout(policy, params, keys, throws, goals, t_max, members, truth)

    def rollout_one(self, policy: Policy, params, key, throws, goals, horizon: int | None = None,
                    members: int | None = None, truth: bool = False):
        """`rollout` of one run, as a lane of one: params, key, throws [B, ...] and goals [B, 2]
        without the lane axis -> Trajectories [B, ...] (truth=True: and TrueTrack [B, ...])."""
        out = self.rollout(policy, lane_of_one(params), lane_of_one(key), lane_of_one(throws),
                           lane_of_one(goals), horizon, members, truth)
        return lane(out)

    def timing_draws(self, key, b: int):
        """The per-episode timing (ttmjx.world.timing.Draw, [B] fields) that a lane with rollout
        key `key` draws for its B throws: to line a station up with a rollout (tests/test_timing.py)."""
        keys, _, _ = _episode_keys(key, b)
        return jax.vmap(lambda k: timing.draw(self.cfg, env.timing_key(k)))(keys)

    def _reset_keys(self, key, throws, goals):
        keys, k_init, k_act = _episode_keys(key, goals.shape[0])
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        states = self._reset(keys, f32(throws.launch_pos), f32(throws.launch_vel), f32(throws.launch_spin),
                             f32(throws.aim), f32(goals))
        return states, k_init, k_act

    def _act_fn(self, policy: Policy, members):
        """observe -> act -> clip for a batch: (params, carry, states, key) -> (carry, obs, target)."""
        _, apply_b = batched_policy(policy, members)

        def act(params, carry, states, key):
            obs = self._observe(states)
            carry, action = apply_b(params, carry, obs, jax.random.split(key, states.t.shape[0]))
            return carry, obs, self._command(states, action)
        return act

    def _c_rollout(self, policy, params, keys, throws, goals, t_max, members, truth: bool = False):
        """The host loop over lanes: params [L, ...], keys [L], throws and goals [L, B, ...]. The
        compiled one-lane steps are vmapped over lanes; the physics steps all L x B throws at once.
        truth: also the TrueTrack, kept on the host (no compiled program changes)."""
        lanes, b = np.shape(goals)[:2]
        # XLA compiles a vmap over one lane apart from the one-lane function, and for some
        # policies it rounds differently: a lane of one runs the one-lane function itself, so a
        # single run records what it recorded before lanes (tests/test_lanes.py, collect_lanes).
        over = _on_one_lane if lanes == 1 else (lambda f: jax.jit(jax.vmap(f)))
        ck = ("c", policy, members, lanes == 1)
        if ck not in self._rollouts:
            init_b, _ = batched_policy(policy, members)
            act = self._act_fn(policy, members)
            self._rollouts[ck] = tuple(over(f) for f in (init_b, act, self._reset_keys))
        init, act, reset = self._rollouts[ck]
        f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
        states, k_init, k_act = reset(keys, jax.tree.map(f32, throws), f32(goals))
        # [L, B, ...] <-> [L * B, ...] (typed PRNG keys among the leaves: reshape, no numpy)
        flat = lambda tree: jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), tree)  # noqa: E731
        unflat = lambda tree: jax.tree.map(lambda x: x.reshape((lanes, b) + x.shape[1:]), tree)  # noqa: E731
        fold = jax.vmap(jax.random.fold_in, in_axes=(0, None))
        carry = init(params, jax.vmap(jax.random.split, in_axes=(0, None))(k_init, b))
        frames, vels, actions, valids, qposs, balls = [], [], [], [], [], []
        flat_states = flat(states)
        for t in range(t_max):
            valid = ~np.asarray(flat_states.events.done)
            carry, obs, target = act(params, carry, states, fold(k_act, t))
            target = flat(target)
            out = self._physics(flat_states, target)
            frames.append(flat(obs.frame)), vels.append(flat(obs.ball_vel)), actions.append(target)
            valids.append(valid)
            if truth:
                qposs.append(np.asarray(flat_states.qpos)), balls.append(np.asarray(out[2])[..., :3])
            flat_states = self._advance(flat_states, target, *out)
            states = unflat(flat_states)
            if not valid.any():
                break
        pad = t_max - len(frames)
        stack = lambda xs: np.concatenate([np.stack([np.asarray(x) for x in xs], 1),  # noqa: E731
                                           np.repeat(np.asarray(xs[-1])[:, None], pad, 1)], 1)
        valid_arr = np.concatenate([np.stack(valids, 1), np.zeros((len(valids[0]), pad), bool)], 1)
        alone = lambda xs: _as_if_alone(stack(xs), valid_arr, lanes)  # noqa: E731
        rec = _record(self.cfg, self.lay, flat_states, alone(frames), alone(vels), alone(actions), valid_arr)
        rec = jax.tree.map(np.asarray, unflat(rec))
        return (rec, unflat(_true_track(self.lay, alone(qposs), alone(balls), np))) if truth else rec

    def rollout_fn(self, policy: Policy, t_max: int | None = None, members: int | None = None,
                   truth: bool = False):
        """MJX only: a pure, jittable `(params, key, throws, goals [B, 2]) -> Trajectories`
        (no input validation: for use inside larger jit-compiled functions); truth=True:
        -> (Trajectories, TrueTrack), a program of its own (practice's is unchanged)."""
        if not self.kind.traceable:
            raise ValueError(f"rollout_fn needs a traceable backend (mjx); {self.name} steps on the host")
        t_max = t_max or self.cfg.horizon
        init_b, _ = batched_policy(policy, members)
        act = self._act_fn(policy, members)
        advance = jax.vmap(functools.partial(env.advance, self.cfg, self.lay))

        def run(params, key, throws, goals):
            states, k_init, k_act = self._reset_keys(key, throws, goals)
            carry = init_b(params, jax.random.split(k_init, states.t.shape[0]))

            def body(c, t):
                carry, states = c
                valid = ~states.events.done
                carry, obs, target = act(params, carry, states, jax.random.fold_in(k_act, t))
                out = self._physics(states, target)
                ys = (obs.frame, obs.ball_vel, target, valid)
                if truth:   # the state before the step and the ball after each physics step
                    ys += (states.qpos, out[2][..., :3])
                return (carry, advance(states, target, *out)), ys

            (carry, states), ys = jax.lax.scan(body, (carry, states), jnp.arange(t_max))
            sw = lambda x: jnp.swapaxes(x, 0, 1)  # noqa: E731
            rec = _record(self.cfg, self.lay, states, *(sw(y) for y in ys[:4]))
            return (rec, _true_track(self.lay, sw(ys[4]), sw(ys[5]))) if truth else rec
        return run


def _as_if_alone(x, valid, lanes: int):
    """Per-step values [L * B, T, ...] of lanes stepped together, as each lane alone records them:
    a lane alone stops at its first step with no valid throw and repeats that step's values to
    the horizon (invalid steps, but kept in the cache: identical data whatever runs beside it)."""
    t_max = valid.shape[1]
    live = valid.reshape(lanes, -1, t_max).any(1)                     # [L, T]
    end = np.where(live.all(1), t_max - 1, np.argmin(live, 1))        # [L] last recorded step
    idx = np.minimum(np.arange(t_max)[None], end[:, None])            # [L, T]
    idx = np.repeat(idx, valid.shape[0] // lanes, 0)                  # [L * B, T]
    return np.take_along_axis(x, idx.reshape(idx.shape + (1,) * (x.ndim - 2)), 1)


def _on_one_lane(f):
    """jit(f) on a lane axis of one, without vmap: the lane taken off the arguments and put back
    on the results outside the compiled program (the program is f's own)."""
    g = jax.jit(f)
    return lambda *args: jax.tree.map(lambda x: x[None], g(*lane(args)))


def _check_lanes(throws, goals, members: int | None) -> np.ndarray:
    """goals [L, B, 2] checked against throws [L, B, ...] and the ensemble's equal blocks
    (ValueError naming the problem) -> float32 [L, B, 2]."""
    lanes, b = np.shape(throws.launch_pos)[:2]
    if np.shape(goals)[:2] != (lanes, b):
        raise ValueError(f"goals of shape {np.shape(goals)}; expected [{lanes}, {b}, 2], one per lane and throw")
    if members and b % members:
        raise ValueError(f"{b} throws cannot be split evenly over {members} ensemble members")
    return env.check_goals(np.reshape(goals, (-1, 2)), lanes * b).reshape(lanes, b, 2)


def lane_of_one(tree):
    """One run's pytree as a lane of one: a leading axis of 1 on every leaf."""
    return jax.tree.map(lambda x: x[None] if isinstance(x, jax.Array) else np.asarray(x)[None], tree)


def lane(tree, i: int = 0):
    """Lane i of a pytree with a leading lane axis."""
    return jax.tree.map(lambda x: x[i], tree)


def _episode_keys(key, b: int):
    """(reset keys [B], policy-init key, action key) of a rollout."""
    k_reset, k_init, k_act = jax.random.split(key, 3)
    return jax.random.split(k_reset, b), k_init, k_act


def batched_policy(policy: Policy, members: int | None = None):
    """(init_b, apply_b) of a one-throw policy over a flat batch of B throws.

    Without members the params are shared. With members=N the params have a leading [N] axis
    and the batch is played in N contiguous blocks, one per member (vmap over members of a vmap
    over throws: no per-throw copies of the parameters)."""
    init1 = jax.vmap(policy.init, in_axes=(None, 0))
    apply1 = jax.vmap(policy.apply, in_axes=(None, 0, 0, 0))
    if not members:
        return init1, apply1
    split = lambda x: x.reshape((members, -1) + x.shape[1:])  # noqa: E731
    merge = lambda x: x.reshape((-1,) + x.shape[2:])  # noqa: E731

    def init_b(params, keys):
        return jax.tree.map(merge, jax.vmap(init1)(params, split(keys)))

    def apply_b(params, carry, obs, keys):
        carry, action = jax.vmap(apply1)(params, jax.tree.map(split, carry), jax.tree.map(split, obs), split(keys))
        return jax.tree.map(merge, carry), merge(action)
    return init_b, apply_b


def hold_policy() -> Policy:
    """A policy that keeps the robot at its reset pose (events and physics tests)."""
    return Policy(init=lambda params, key: jnp.zeros(()),
                  apply=lambda params, carry, obs, key: (carry, observation.joints(obs.frame)))
