"""Air forces on the ball, written in JAX for MJX (which ignores MuJoCo's ellipsoid fluid model).

These are MuJoCo's ellipsoid-model terms specialised to a sphere (semi-axes all r), so that
the C backend (MuJoCo's own model) and MJX (these forces through xfrc_applied) fly the same
ball. For a sphere the Kutta lift and slender drag vanish, leaving:

    blunt drag   f_D = -C_b rho pi r^2 |v| v                 (C_b = Cd / 2)
    Magnus       f_M =  C_M rho V (w x v)                    (V = 4/3 pi r^3)
    added mass   f_A =  rho (V / 2) (v x w)                  (sphere's virtual mass V / 2)
    angular drag g_D = -C_a rho (8/15 pi r^5) |w| w

All functions work on one ball; vmap for batches. Works on numpy inputs too.
"""
from __future__ import annotations

import jax.numpy as jnp

from ttmjx.world.config import Ball


def air_force_torque(vel, angvel, ball: Ball):
    """World-frame force [3] and torque [3] of the air on a ball with velocity `vel` [3] (m/s)
    and world-frame angular velocity `angvel` [3] (rad/s)."""
    r, rho = ball.radius, ball.air_density
    volume = 4.0 / 3.0 * jnp.pi * r**3
    speed = jnp.linalg.norm(vel)
    drag = -(ball.drag_coefficient / 2) * rho * jnp.pi * r**2 * speed * vel
    magnus = ball.magnus_coefficient * rho * volume * jnp.cross(angvel, vel)
    added_mass = rho * (volume / 2) * jnp.cross(vel, angvel)
    torque = -ball.angular_drag_coefficient * rho * (8.0 / 15.0 * jnp.pi * r**5) * jnp.linalg.norm(angvel) * angvel
    return drag + magnus + added_mass, torque


def ball_acceleration(vel, angvel, ball: Ball, gravity: float = 9.81):
    """Linear acceleration [3] of a ball in flight (gravity + air), m/s^2."""
    force, _ = air_force_torque(vel, angvel, ball)
    return force / ball.mass + jnp.array([0.0, 0.0, -gravity])
