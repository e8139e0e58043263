"""The start pose is the paper's: "in simulation the robot is initialized with the front edge of
the paddle facing forward, reducing the probability of hitting the ball through random
exploration" (GoalsEye, any-ball results). In the home pose (ttmjx/world/config.py Robot.home)
the blade lies nearly flat, face up, its tip toward the net: a ball coming down the table meets
its edge, not its face. Checked on the MuJoCo model, over the per-episode perturbation too."""
import itertools

import mujoco
import numpy as np

from ttmjx.world import scene
from ttmjx.world.config import World

# "Edge forward": the ball's travel (-x) lies closer to the blade's plane than to its normal, i.e.
# the face turns less than 45 degrees toward the ball (face-on: 90). Measured: 11.5 degrees at the
# home pose, at most 20.3 at the corners of the per-episode perturbation.
MAX_FACE_TILT_DEG = 45.0


def blade_axes(cfg: World, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(face normal, long axis) of the blade in the world frame for the 8 robot joints q."""
    m = scene.model(cfg)
    d = mujoco.MjData(m)
    robot = [m.jnt_qposadr[j] for j in range(m.njnt) if m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE]
    d.qpos[robot] = q
    mujoco.mj_kinematics(m, d)
    rot = d.geom_xmat[m.geom("paddle").id].reshape(3, 3)
    return rot[:, 2], rot[:, 0]


def test_the_blade_starts_edge_forward_as_in_the_paper():
    cfg = World()
    home, spread = np.array(cfg.robot.home), np.array(cfg.robot.home_noise)
    corners = [home + spread * np.array(s) for s in itertools.product((-1, 1), repeat=8)]
    for q in [home, *corners]:
        normal, along = blade_axes(cfg, q)
        tilt = np.degrees(np.arcsin(abs(normal @ np.array([-1.0, 0.0, 0.0]))))
        assert tilt < MAX_FACE_TILT_DEG, (q, tilt)
        assert along[0] > 0.9, along          # the tip points down the table, toward the net
