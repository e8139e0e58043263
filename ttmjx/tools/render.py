"""Headless video of a few throws (`ttmjx render`): an animated GIF written with Pillow.

On a CPU machine MuJoCo renders through OSMesa (MUJOCO_GL=osmesa, Debian's libosmesa6);
on a GPU machine through EGL.
"""
from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from ttmjx.world import backends, env, observation, scene  # noqa: E402
from ttmjx.world.config import World  # noqa: E402
from ttmjx.world.record import Trajectories  # noqa: E402


def policy_for(cfg: World, source: str) -> backends.Policy:
    if source == "scripted":
        from ttmjx.tools import striker
        return striker.striker_policy(cfg)
    if source == "hold":
        return backends.hold_policy()
    raise ValueError(f"unknown source {source!r}; expected 'scripted' or 'hold'")


def frames_of(cfg: World, traj: Trajectories, width: int = 480, height: int = 320, camera: str = "side",
              every: int = 2) -> list[np.ndarray]:
    """RGB frames [H, W, 3] replaying each throw's valid steps (every `every` control steps)."""
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    lay = env.layout(m)
    out = []
    renderer = mujoco.Renderer(m, height, width)
    try:
        for b in range(traj.size):
            n = int(np.asarray(traj.valid[b]).sum())
            for t in range(0, max(n, 1), every):
                d.qpos[:] = m.qpos0
                d.qpos[list(lay.robot_qpos)] = observation.joints(traj.obs[b, t])
                d.qpos[lay.ball_qpos:lay.ball_qpos + 3] = observation.ball_pos(traj.obs[b, t])
                mujoco.mj_forward(m, d)
                renderer.update_scene(d, camera=camera)
                out.append(renderer.render().copy())
    finally:
        renderer.close()
    return out


def render_throws(cfg: World, path: str, n: int = 3, seed: int = 0, source: str = "scripted") -> str:
    """Simulate n throws on the C backend and write them as an animated GIF to `path`."""
    from PIL import Image
    from ttmjx.world import thrower
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    key = jax.random.PRNGKey(seed)
    th = thrower.sample_throws(key, cfg, n)
    be = backends.Backend(cfg, "c")
    traj = be.rollout(policy_for(cfg, source), None, key, th, np.zeros((n, 2), np.float32))
    frames = frames_of(cfg, traj)
    imgs = [Image.fromarray(f) for f in frames]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=int(2000 / cfg.control_hz), loop=0)
    return path
