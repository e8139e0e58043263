"""Headless video of a few throws (`ttmjx render`): an animated GIF written with Pillow.

The OpenGL backend is chosen when rendering starts, never at import, so everything else works
on a machine without one: EGL (Debian's libegl1; GPU drivers or Mesa), then OSMesa (Debian's
libosmesa6). MUJOCO_GL=egl or MUJOCO_GL=osmesa forces one.
"""
from __future__ import annotations

import ctypes.util
import io
import os

import jax
import mujoco
import numpy as np

from ttmjx.world import backends, env, files, observation, scene
from ttmjx.world.config import World
from ttmjx.world.record import Trajectories, TrueTrack

# (MUJOCO_GL name, shared library, Debian package), in order of preference.
GL_BACKENDS = (("egl", "EGL", "libegl1"), ("osmesa", "OSMesa", "libosmesa6"))


class NoOpenGLError(RuntimeError):
    """No headless OpenGL here; the message names the system package to install."""


def _context_class(name: str):
    if name == "egl":
        from mujoco.egl import GLContext
    else:
        from mujoco.osmesa import GLContext
    return GLContext


def gl_context_class():
    """The GLContext class of the first headless OpenGL that opens a context here."""
    forced = os.environ.get("MUJOCO_GL", "").lower()
    tried = []
    for name, lib, package in GL_BACKENDS:
        if forced in ("egl", "osmesa") and name != forced:
            continue
        if ctypes.util.find_library(lib) is None:
            tried.append(f"{name}: no lib{lib} (Debian package {package})")
            continue
        os.environ.setdefault("PYOPENGL_PLATFORM", name)   # read when PyOpenGL is first imported
        try:
            cls = _context_class(name)
            cls(1, 1).free()
            return cls
        except Exception as e:  # a library that is present but cannot open a context
            tried.append(f"{name}: {type(e).__name__}: {e}")
    raise NoOpenGLError("no headless OpenGL to render with (" + "; ".join(tried) + "); install Debian's "
                        "libegl1 or libosmesa6 (apt-get install libosmesa6)")


def renderer(m, height: int, width: int) -> mujoco.Renderer:
    """A MuJoCo renderer on the headless OpenGL chosen now."""
    from mujoco.rendering.classic import gl_context
    gl_context.GLContext = gl_context_class()   # mujoco.Renderer reads this attribute when it is built
    return mujoco.Renderer(m, height, width)


def policy_for(cfg: World, source: str) -> backends.Policy:
    if source == "scripted":
        from ttmjx.tools import striker
        return striker.striker_policy(cfg)
    if source == "hold":
        return backends.hold_policy()
    raise ValueError(f"unknown source {source!r}; expected 'scripted' or 'hold'")


def frames_of(cfg: World, traj: Trajectories, width: int = 480, height: int = 320, camera: str = "side",
              every: int = 2, true: TrueTrack | None = None) -> list[np.ndarray]:
    """RGB frames [H, W, 3] replaying each throw's valid steps (every `every` control steps): the
    true ball and joints of `true` (Backend.rollout(truth=True)), or without it what the policy
    observed (under a timing model the tracker's delayed view, not where the ball was)."""
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    lay = env.layout(m)
    out = []
    view = renderer(m, height, width)
    try:
        for b in range(traj.size):
            n = int(np.asarray(traj.valid[b]).sum())
            for t in range(0, max(n, 1), every):
                d.qpos[:] = m.qpos0
                joints, ball = ((true.joints[b, t], true.ball[b, t]) if true is not None else
                                (observation.joints(traj.obs[b, t]), observation.ball_pos(traj.obs[b, t])))
                d.qpos[list(lay.robot_qpos)] = joints
                d.qpos[lay.ball_qpos:lay.ball_qpos + 3] = ball
                mujoco.mj_forward(m, d)
                view.update_scene(d, camera=camera)
                out.append(view.render().copy())
    finally:
        view.close()
    return out


def render_throws(cfg: World, path: str, n: int = 3, seed: int = 0, source: str = "scripted") -> str:
    """Simulate n throws on the C backend and write them as an animated GIF to `path`."""
    from PIL import Image
    from ttmjx.world import thrower
    if n < 1:
        raise ValueError(f"n must be >= 1, got {n}")
    if os.path.isdir(path):
        raise ValueError(f"--out {path!r} is a directory; expected a .gif file path")
    gl_context_class()   # no OpenGL: say so before simulating anything
    key = jax.random.PRNGKey(seed)
    th = thrower.sample_throws(key, cfg, n)
    be = backends.Backend(cfg, "c")
    traj, true = be.rollout_one(policy_for(cfg, source), None, key, th, np.zeros((n, 2), np.float32), truth=True)
    frames = frames_of(cfg, traj, true=true)
    imgs = [Image.fromarray(f) for f in frames]
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    buf = io.BytesIO()
    imgs[0].save(buf, format="GIF", save_all=True, append_images=imgs[1:], duration=int(2000 / cfg.control_hz), loop=0)
    files.write_bytes(path, buf.getvalue())    # whole or absent: never a truncated GIF under its name
    return path
