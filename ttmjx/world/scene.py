"""The MJCF scene: ITTF table, net, ball on a free joint, the 8-DOF robot with a paddle.

The XML is generated from the config so that every assumed number stays a config field.
Only the ball collides: every geom has contype = conaffinity = 0 and the ball's three contact
pairs (table, net, paddle) are listed explicitly; in MJX every collidable pair is allocated
every step, so this keeps the contact count at 3 (PHYSICS.md).
"""
from __future__ import annotations

import dataclasses
import functools

import mujoco
import numpy as np

from ttmjx.world.config import JOINT_NAMES, World


def _v(*xs) -> str:
    return " ".join(f"{float(x):.9g}" for x in xs)


def _link_inertial(mass: float, length: float, axis: str) -> str:
    """A rod-like inertial along `axis` of the given length, centred half way."""
    i_long = mass * 0.04**2 / 2
    i_perp = mass * (length**2 / 12 + 0.04**2 / 4) + 1e-4
    pos = {"x": (length / 2, 0, 0), "z": (0, 0, length / 2)}[axis]
    diag = {"x": (i_long, i_perp, i_perp), "z": (i_perp, i_perp, i_long)}[axis]
    return f'<inertial pos="{_v(*pos)}" mass="{mass}" diaginertia="{_v(*diag)}"/>'


@functools.lru_cache(maxsize=16)
def servo_inertia(cfg: World) -> tuple:
    """Joint-space inertia (diagonal of M, armature included) of the 8 robot joints at home.

    The servo gains are set from it: critically damped on the real inertia each joint moves
    (the gantry carries the whole arm, so its armature alone would under-damp it)."""
    m = mujoco.MjModel.from_xml_string(mjcf(cfg, True, inertia=(1.0,) * 8))
    d = mujoco.MjData(m)
    for i, name in enumerate(JOINT_NAMES):
        d.qpos[m.joint(name).qposadr[0]] = cfg.robot.home[i]
    mujoco.mj_forward(m, d)
    full = np.zeros((m.nv, m.nv))
    mujoco.mj_fullM(m, d, full)
    return tuple(float(full[m.joint(n).dofadr[0], m.joint(n).dofadr[0]]) for n in JOINT_NAMES)


# The arm's links 1-5 (ABB IRB 120 dimensions, PHYSICS.md): length (m), the axis they extend
# along, capsule radius (m), colour; link 6 carries the paddle. Joint axes of links 1-6.
ARM_LINKS = ((0.29, "z", 0.06, "1 1 1 1"), (0.27, "z", 0.05, "1 1 1 1"), (0.07, "z", 0.045, "1 1 1 1"),
             (0.302, "x", 0.04, "1 1 1 1"), (0.072, "x", 0.03, ".3 .3 .3 1"))
ARM_AXES = ("0 0 1", "0 1 0", "0 1 0", "1 0 0", "0 1 0", "1 0 0")


def mjcf(cfg: World, fluid: bool = True, inertia: tuple | None = None) -> str:
    """MJCF text of the scene.

    fluid=True uses MuJoCo's ellipsoid fluid model for the ball (C backend). The MJX model is
    built with fluid=False (zero air density) and ttmjx.world.ballphysics applies the same forces.
    """
    t, b, c, r = cfg.table, cfg.ball, cfg.contacts, cfg.robot
    m = r.link_masses
    # MuJoCo's blunt-drag term is C rho A |v| v, so C = Cd / 2 for the usual 1/2 rho Cd A.
    fluidcoef = _v(b.drag_coefficient / 2, 0.25, b.angular_drag_coefficient, 0.0, b.magnus_coefficient)
    density = b.air_density if fluid else 0.0

    def joint_xml(i: int, kind: str, axis: str) -> str:
        return (f'<joint name="{JOINT_NAMES[i]}" type="{kind}" axis="{axis}" limited="true" '
                f'range="{_v(r.lower[i], r.upper[i])}" armature="{r.armature[i]}"/>')

    def solref(k, d):
        return f'solref="{_v(-k, -d)}" solimp="{_v(c.impedance, c.impedance, 0.001)}"'

    bh, bw = r.blade_half_size
    blade_centre = r.extension + bh
    actuators = []
    inertia = inertia or servo_inertia(cfg)
    for i, name in enumerate(JOINT_NAMES):
        # Over-damped servo (ratio servo_damping at the home-pose inertia): a critically or
        # over-damped response to a speed-limited ramp never overshoots the ramp's speed or range.
        kp = inertia[i] * r.servo_omega**2
        kv = 2.0 * r.servo_damping * inertia[i] * r.servo_omega
        actuators.append(
            f'<position name="{name}" joint="{name}" kp="{kp:.6g}" kv="{kv:.6g}" '
            f'ctrlrange="{_v(r.lower[i], r.upper[i])}" ctrllimited="true"/>')

    paddle = f"""
      <inertial pos="{_v(blade_centre * 0.7, 0, 0)}" mass="{m[6] + r.paddle_mass}"
                diaginertia="{_v(1e-3, 3e-3, 3e-3)}"/>
      <geom name="extension" type="capsule" fromto="0 0 0 {r.extension} 0 0" size="0.012" rgba=".2 .2 .2 1"/>
      <site name="paddle" pos="{_v(blade_centre, 0, 0)}" size="0.01"/>
      <geom name="paddle" type="box" pos="{_v(blade_centre, 0, 0)}"
            size="{_v(bh, bw, r.blade_thickness / 2)}" rgba="0.8 0.1 0.1 1"/>"""

    def arm_xml(pos: str, tip: str, k: int = 0) -> str:
        """Bodies link1..link6 nested from ARM_LINKS; the last holds `tip` (the paddle)."""
        axis = ARM_AXES[k]
        head = f'<body name="link{k + 1}" pos="{pos}" gravcomp="1">{joint_xml(k + 2, "hinge", axis)}'
        if k == len(ARM_LINKS):
            return f"{head}{tip}</body>"
        length, along, radius, rgba = ARM_LINKS[k]
        end = _v(0, 0, length) if along == "z" else _v(length, 0, 0)
        return (f'{head}{_link_inertial(m[k + 1], length, along)}'
                f'<geom type="capsule" fromto="0 0 0 {end}" size="{radius}" rgba="{rgba}"/>'
                f'{arm_xml(end, tip, k + 1)}</body>')

    return f"""
<mujoco model="ttmjx">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{cfg.physics_dt}" integrator="Euler" density="{density}" viscosity="0"
          gravity="0 0 -9.81" cone="pyramidal"
          iterations="{c.solver_iterations}" ls_iterations="{c.line_search_iterations}"/>
  <default>
    <geom contype="0" conaffinity="0" group="1"/>
  </default>
  <visual><global offwidth="640" offheight="480"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".2 .3 .4" rgb2=".1 .2 .3" width="256" height="256"/>
    <material name="floor" texture="grid" texrepeat="6 6"/>
  </asset>
  <worldbody>
    <light pos="0 0 4" dir="0 0 -1" diffuse=".8 .8 .8"/>
    <camera name="side" pos="0.3 -3.6 2.0" xyaxes="1 0 0 0 0.5 0.87"/>
    <camera name="behind" pos="-4.2 0 2.0" xyaxes="0 -1 0 0.42 0 0.9"/>
    <geom name="floor" type="plane" size="5 5 0.1" material="floor"/>
    <geom name="table" type="box" pos="0 0 {t.top_z - t.thickness / 2}"
          size="{_v(t.half_length, t.half_width, t.thickness / 2)}" rgba="0.1 0.25 0.5 1"/>
    <geom name="net" type="box" pos="0 0 {t.top_z + t.net_height / 2}"
          size="{_v(t.net_thickness / 2, t.net_length / 2, t.net_height / 2)}" rgba="0.9 0.9 0.9 0.6"/>
    <body name="ball" pos="1.5 0 1.0">
      <freejoint name="ball"/>
      <inertial pos="0 0 0" mass="{b.mass}" diaginertia="{_v(*(3 * [b.hollow_inertia]))}"/>
      <geom name="ball" type="sphere" size="{b.radius}" rgba="1 0.5 0 1"
            fluidshape="ellipsoid" fluidcoef="{fluidcoef}"/>
    </body>
    <body name="gantry_x" pos="{_v(r.base_x, r.base_y, 0)}" gravcomp="1">
      {joint_xml(0, "slide", "1 0 0")}
      <inertial pos="0 0 0.3" mass="{r.gantry_mass}" diaginertia="1 1 1"/>
      <body name="gantry_y" gravcomp="1">
        {joint_xml(1, "slide", "0 1 0")}
        <inertial pos="0 0 0.3" mass="{r.gantry_mass + m[0]}" diaginertia="1 1 1"/>
        <geom type="box" pos="0 0 {r.base_z / 2}" size="0.1 0.1 {r.base_z / 2}" rgba=".5 .5 .5 1"/>
        {arm_xml(f"0 0 {r.base_z}", paddle)}
      </body>
    </body>
  </worldbody>
  <contact>
    <pair geom1="ball" geom2="table" condim="3" {solref(c.table_stiffness, c.table_damping)}
          friction="{_v(c.table_friction, c.table_friction, 0.005, 1e-4, 1e-4)}"/>
    <pair geom1="ball" geom2="net" condim="3" {solref(c.net_stiffness, c.net_damping)}
          friction="{_v(c.net_friction, c.net_friction, 0.005, 1e-4, 1e-4)}"/>
    <pair geom1="ball" geom2="paddle" condim="3" {solref(c.paddle_stiffness, c.paddle_damping)}
          friction="{_v(c.paddle_friction, c.paddle_friction, 0.005, 1e-4, 1e-4)}"/>
  </contact>
  <actuator>
    {chr(10).join(actuators)}
  </actuator>
  <sensor>
    <!-- The blade centre: events tell paddle contacts from table/net ones by it. -->
    <framepos name="paddle" objtype="site" objname="paddle"/>
  </sensor>
</mujoco>
"""


@functools.lru_cache(maxsize=16)
def _model_cached(cfg: World, fluid: bool) -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_string(mjcf(cfg, fluid))


def model(cfg: World, fluid: bool = True) -> mujoco.MjModel:
    """The compiled MuJoCo model (cached per config). Do not mutate the result."""
    return _model_cached(cfg, fluid)


@dataclasses.dataclass(frozen=True)
class Ids:
    """MuJoCo addresses looked up once by name."""
    ball_qpos: int          # 7 values: xyz + quaternion
    ball_qvel: int          # 6 values: linear (world) + angular (local frame)
    ball_body: int
    robot_qpos: np.ndarray  # [8]
    robot_qvel: np.ndarray  # [8]
    paddle_geom: int
    paddle_site: int


def ids(m: mujoco.MjModel) -> Ids:
    ball_j = m.joint("ball")
    return Ids(
        ball_qpos=int(ball_j.qposadr[0]),
        ball_qvel=int(ball_j.dofadr[0]),
        ball_body=int(m.body("ball").id),
        robot_qpos=np.array([m.joint(n).qposadr[0] for n in JOINT_NAMES]),
        robot_qvel=np.array([m.joint(n).dofadr[0] for n in JOINT_NAMES]),
        paddle_geom=int(m.geom("paddle").id),
        paddle_site=int(m.site("paddle").id),
    )
