"""The observation layout: the one place that knows which columns of a frame hold what.

A frame is what one throw shows the policy at one control step:

    13 values   joints (8) | ball position (3) | goal (2)                      the record, the robot
    16 values   joints (8) | ball position (3) | ball velocity (3) | goal (2)   World.ball_velocity_obs

A frame stack is [k, O]: the last k frames, oldest first (the newest is frames[-1]).
Joints are in JOINT_NAMES order (gantry metres, arm radians); positions in the table frame
(ttmjx.world.config). The functions work on [..., O] arrays of numpy or, given xp=jax.numpy,
of JAX (under jit too). Numpy-only at import: the robot side (deploy/) reads it.
"""
from __future__ import annotations

import numpy as np

WIDTHS = (13, 16)
JOINTS = slice(0, 8)
BALL_POS = slice(8, 11)
BALL_VEL = slice(11, 14)       # 16-value frames only
GOAL = slice(-2, None)         # the last two columns of either width


def check_width(width: int) -> int:
    if width not in WIDTHS:
        raise ValueError(f"observation width {width}; expected one of {WIDTHS}")
    return width


def names(width: int, joint_names) -> list[str]:
    """Column names of a frame of `width` values (the export contract's frame layout)."""
    ball = ["ball_x", "ball_y", "ball_z"]
    vel = ["ball_vx", "ball_vy", "ball_vz"] if check_width(width) == 16 else []
    return [*joint_names, *ball, *vel, "goal_x", "goal_y"]


def joints(frame):
    """[..., O] -> [..., 8]."""
    return frame[..., JOINTS]


def ball_pos(frame):
    """[..., O] -> [..., 3]."""
    return frame[..., BALL_POS]


def goal(frame):
    """[..., O] -> [..., 2]."""
    return frame[..., GOAL]


def joints_and_ball(frame):
    """[..., O] -> [..., 11]: joints and ball position (what the non-goal-directed ES policy reads)."""
    return frame[..., :BALL_POS.stop]


def make_frame(joint_pos, ball, goal_xy, ball_vel=None, xp=np):
    """joints [..., 8], ball position [..., 3], goal [..., 2] and, for 16 values, the ball
    velocity [..., 3] -> [..., 13 or 16]."""
    parts = [joint_pos, ball] + ([ball_vel] if ball_vel is not None else []) + [goal_xy]
    return xp.concatenate(parts, axis=-1)


def to_width(frame, width: int, ball_vel=None, xp=np):
    """[..., 13 or 16] -> [..., width]. 16 -> 13 drops the velocity columns; 13 -> 16 inserts
    `ball_vel` [..., 3], which is then required."""
    n = frame.shape[-1]
    check_width(n), check_width(width)
    if n == width:
        return frame
    if width == 13:
        return xp.concatenate([frame[..., :BALL_VEL.start], frame[..., BALL_VEL.stop:]], axis=-1)
    if ball_vel is None or ball_vel.shape[-1] != 3:
        raise ValueError(f"observation.to_width: ball_vel has shape {getattr(ball_vel, 'shape', None)}, "
                         f"expected [..., 3] to build 16-value frames")
    return xp.concatenate([frame[..., :BALL_VEL.start], ball_vel, frame[..., BALL_VEL.start:]], axis=-1)


def with_goal(frame, goal_xy, xp=np):
    """[..., O] frames with their goal columns replaced by `goal_xy` (broadcast to [..., 2])."""
    g = xp.broadcast_to(goal_xy, frame[..., GOAL].shape).astype(frame.dtype)
    return xp.concatenate([frame[..., :frame.shape[-1] - 2], g], axis=-1)


def stack_index(t: int, k: int) -> np.ndarray:
    """[t, k] frame indices of the stack at each of t steps, oldest first; steps before 0 repeat
    frame 0 (an episode starts with its first frame repeated, as env.reset does)."""
    return np.clip(np.arange(t)[:, None] - (k - 1) + np.arange(k)[None, :], 0, t - 1)


def frame_stack(obs, k: int):
    """[B, T, O] -> [B, T, k, O]: the last k frames at each step, oldest first (numpy or JAX)."""
    return obs[:, stack_index(obs.shape[1], k)]

