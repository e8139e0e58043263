"""Frozen configuration of the simulated world.

Frame (used everywhere, reported by `ttmjx throw --json`): x along the table's length,
y across it, z up; the table's centre is at x = y = 0. The robot stands behind the end line at
negative x, the thrower (the "opponent") at positive x. Goals and landings are (x, y) on the
table top, in metres.

Numbers marked *assumed* in shared/docs/PHYSICS.md have no public source: they are fields here,
not constants in code.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

DEG = math.pi / 180.0

JOINT_NAMES = ("gantry_x", "gantry_y", "j1", "j2", "j3", "j4", "j5", "j6")


@dataclasses.dataclass(frozen=True)
class Table:
    """ITTF table and net (PHYSICS.md)."""
    length: float = 2.74                  # m, along x
    width: float = 1.525                  # m, along y
    top_z: float = 0.76                   # m, height of the playing surface
    thickness: float = 0.03               # m, of the table top
    net_height: float = 0.1525            # m, above the playing surface
    net_length: float = 1.83              # m, across the table (it overhangs the sides)
    # The collision box of the net is thicker than a real net (2 cm): at 1 ms steps a ball at
    # 20 m/s moves 2 cm a step, and the thicker box keeps it from tunnelling.
    net_thickness: float = 0.02

    @property
    def half_length(self) -> float:
        return self.length / 2

    @property
    def half_width(self) -> float:
        return self.width / 2


@dataclasses.dataclass(frozen=True)
class Ball:
    radius: float = 0.02                  # m (40 mm ball)
    mass: float = 0.0027                  # kg (2.7 g)
    drag_coefficient: float = 0.47        # Cd in F = 1/2 rho Cd A |v| v
    magnus_coefficient: float = 1.0       # MuJoCo fluidcoef[4]: F_M = C_M rho V (w x v)
    angular_drag_coefficient: float = 1.5 # MuJoCo fluidcoef[2]
    air_density: float = 1.225           # kg/m^3 at sea level, 15 C

    @property
    def hollow_inertia(self) -> float:
        """Moment of inertia of a thin spherical shell, 2/3 m r^2 (kg m^2)."""
        return 2.0 / 3.0 * self.mass * self.radius**2


@dataclasses.dataclass(frozen=True)
class Contacts:
    """Bouncy contacts: MuJoCo's direct (-stiffness, -damping) solref.

    sqrt(k) * dt <= 1 at 1 ms (PHYSICS.md). At 1 ms a bounce lasts only ~5 physics steps, so
    its COR depends on where the ball is at the first step inside the surface (the arrival
    phase); the stiffnesses sit at a measured minimum of that spread, the dampings centre the
    band, and both are checked by MEASURED restitution over speeds and arrival phases
    (ttmjx/tools/calibration.py, tests/test_physics.py). Lower stiffness would bounce more evenly
    but lets a 20 m/s ball sink past the mid-plane of the 3 cm table and tunnel.
    """
    # Measured (C and MJX, normal impacts 2-10 m/s x 16 arrival phases): COR 0.869-0.912,
    # mean 0.889 (band 0.86-0.92); deepest sink at 20 m/s 3.1 cm (tunnels past ~22 m/s).
    table_stiffness: float = 3.58e5
    table_damping: float = 46.0
    table_friction: float = 0.2
    # Measured (C and MJX, normal impacts 2-10 m/s x 16 arrival phases on the held blade):
    # COR 0.728-0.811, mean 0.767 (band 0.72-0.82); sinks 3.1 cm at 20 m/s (needs the 3 cm blade).
    paddle_stiffness: float = 3.3e5
    paddle_damping: float = 101.0
    paddle_friction: float = 0.6
    # Measured: a dead-ish net (mean COR ~0.42, 0.08-0.91 by arrival phase); sinks <= 2.4 cm at
    # 25 m/s, never past its mid-plane.
    net_stiffness: float = 1.0e6
    net_damping: float = 900.0
    net_friction: float = 0.3
    impedance: float = 0.99
    # The constraint solver's caps (MuJoCo's defaults: 100 and 50). Measured on this scene (64
    # thrower throws, 1.6 s each): MuJoCo C's Newton solver stops on its tolerance after at most
    # 5 iterations with at most 6 line-search evaluations, MJX's after at most 5. The caps matter
    # for speed on MJX: there a batch's while loop runs until its slowest world stops, and the
    # line search is a scan of `line_search_iterations` steps under vmap, every step computed
    # for every world (both branches of its cond). 50 -> 8 moved no ball by more than 3 um over
    # those throws; BENCHMARKS.md "Where a paper-sim round's time goes" has the speed.
    solver_iterations: int = 10
    line_search_iterations: int = 8

    def __post_init__(self):
        for name in ("solver_iterations", "line_search_iterations"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or not 1 <= v <= 1000:
                raise ValueError(f"world.contacts.{name} must be an integer in [1, 1000], got {v!r}")


@dataclasses.dataclass(frozen=True)
class Robot:
    """ABB IRB 120T on a two-axis gantry (PHYSICS.md); order = JOINT_NAMES."""
    # Gantry carriage centre (world x, y) and the arm base height (assumed).
    base_x: float = -1.95
    base_y: float = 0.0
    base_z: float = 0.55
    lower: tuple = (-0.25, -0.9, -165 * DEG, -110 * DEG, -110 * DEG, -160 * DEG, -120 * DEG, -400 * DEG)
    """Joint lower limits (gantry m, arm rad), JOINT_NAMES order."""
    upper: tuple = (0.25, 0.9, 165 * DEG, 110 * DEG, 70 * DEG, 160 * DEG, 120 * DEG, 400 * DEG)
    """Joint upper limits (gantry m, arm rad)."""
    max_speed: tuple = (2.0, 2.0, 250 * DEG, 250 * DEG, 250 * DEG, 420 * DEG, 590 * DEG, 600 * DEG)
    """Joint speed limits (m/s, rad/s)."""
    speed_margin: float = 0.92
    """Fraction of the speed limits the command clipping uses, so the servo's lag never pushes a
    joint past the real limit."""
    link_masses: tuple = (6.215, 3.067, 3.909, 2.944, 1.328, 0.546, 0.137)
    """Arm link masses (kg), base to wrist."""
    gantry_mass: float = 10.0                 # assumed
    paddle_mass: float = 0.15                 # assumed
    extension: float = 0.17426               # m, flange to blade centre
    blade_half_size: tuple = (0.075, 0.08)    # along the extension, across (assumed 15 x 16 cm)
    # Thicker than a real blade: a 20 m/s ball sinks 3.1 cm into the paddle contact (measured), and
    # a 3 cm box keeps its centre off the blade's mid-plane up to ~22 m/s (tests/test_physics.py).
    blade_thickness: float = 0.03
    # Reflected motor inertia dominates the joint-space inertia, which decouples the joints so
    # that a critically damped servo cannot overshoot the speed limits.
    armature: tuple = (20.0, 20.0, 4.0, 4.0, 2.0, 0.2, 0.2, 0.05)
    servo_omega: float = 60.0                 # rad/s natural frequency of the position servos
    servo_damping: float = 1.3                # damping ratio at the home-pose inertia (> 1: pose changes
                                              # that add inertia keep the servo near critical)
    home: tuple = (0.0, 0.0, 0.0, 0.35, -0.35, 0.0, -0.2, 0.0)
    """Pose at the start of every episode."""
    home_noise: tuple = (0.02, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05, 0.05)
    """Half-width of the uniform perturbation of the home pose per episode."""

    def __post_init__(self):
        for name in ("lower", "upper", "max_speed", "armature", "home", "home_noise"):
            if len(getattr(self, name)) != 8:
                raise ValueError(f"Robot.{name} must have 8 entries (one per joint {JOINT_NAMES}), "
                                 f"got {len(getattr(self, name))}")


@dataclasses.dataclass(frozen=True)
class Throws:
    """The three throw distributions of the paper; `name` picks one (ttmjx/world/thrower.py).

    narrow: one launch position, narrow speed range, forehand landing region.
    any:    wide launch positions and velocities (~5-9 m/s), landing anywhere on the robot's half.
    varied: three launch x positions cycled, yaw swept, fixed speed.

    Positions in the world frame (robot at x < 0, thrower behind x = +1.37), aims (x, y) on the
    robot's half, speeds in m/s. Launches are solved with drag (and Magnus with spin) so the first
    bounce lands on the aim; a candidate that cannot (no low arc at an allowed speed clears the
    net) is redrawn, so each distribution is its ranges conditioned on feasible throws.
    """
    name: str = "narrow"
    """Distribution: narrow, any or varied."""
    spin: bool = False
    """Throws with spin (off in the paper)."""
    max_spin: float = 150.0                    # rad/s per axis when spin is on
    # narrow
    narrow_launch: tuple = (1.75, 0.35, 0.95)
    narrow_speed: tuple = (6.5, 7.5)
    narrow_aim_x: tuple = (-0.95, -0.55)
    narrow_aim_y: tuple = (-0.40, -0.15)
    # any
    any_launch_x: tuple = (1.5, 2.0)
    any_launch_y: tuple = (-0.6, 0.6)
    any_launch_z: tuple = (0.85, 1.1)
    any_speed: tuple = (5.0, 9.0)
    any_aim_x: tuple = (-1.25, -0.25)
    any_aim_y: tuple = (-0.65, 0.65)
    # varied
    varied_launch_x: tuple = (1.6, 1.8, 2.0)
    varied_launch_yz: tuple = (0.0, 0.95)
    varied_speed: float = 7.0
    varied_yaw_deg: tuple = (-12.0, 12.0)
    # Horizontal distance from the launch point to the aim along the yawed line: a fixed-speed,
    # fixed-site thrower lands deeper on the robot's half the closer it stands to the net.
    varied_distance: tuple = (2.5, 2.85)
    # Launch solve (ttmjx/world/thrower.py).
    candidates: int = 16                      # most candidates drawn per throw; first valid kept
    newton_iters: int = 5                     # Newton steps of the launch-velocity solve
    max_pitch: float = 0.6                    # rad: low arcs only (sets the slowest `any` speed)
    net_margin: float = 0.02                  # m: the ball's bottom clears the net tape by this
    solve_tol: float = 0.005                  # m: predicted first bounce within this of the aim
    max_flight_s: float = 1.5                 # s: a throw not down by then is invalid

    def __post_init__(self):
        if self.name not in THROW_DISTRIBUTIONS:
            raise ValueError(f"unknown throw distribution {self.name!r}; expected one of "
                             f"{THROW_DISTRIBUTIONS}")
        if self.candidates < 1 or self.newton_iters < 1:
            raise ValueError(f"Throws.candidates and Throws.newton_iters must be >= 1, got "
                             f"{self.candidates} and {self.newton_iters}")
        if len(self.varied_launch_x) != 3:
            raise ValueError(f"Throws.varied_launch_x must hold 3 positions, got {self.varied_launch_x}")


THROW_DISTRIBUTIONS = ("narrow", "any", "varied")

def physics_steps_per_sample(hz: float | None, physics_dt: float, name: str = "rate") -> int:
    """Physics steps between two samples of a sensor at `hz` (None: every physics step); a rate
    that is not a whole number of physics steps is a ValueError naming `name`. The one rule the
    training world (ttmjx.world.timing) and the simulated station (deploy/sim/station.py) share."""
    if hz is None:
        return 1
    k = 1.0 / (hz * physics_dt) if hz > 0 else 0.5
    if abs(k - round(k)) > 1e-6 or round(k) < 1:
        raise ValueError(f"{name}={hz} is not a whole number of physics steps of {physics_dt:.6g} s "
                         f"(1/(hz*dt) = {k:.4g}); pick a rate that divides it")
    return int(round(k))


@dataclasses.dataclass(frozen=True)
class Timing:
    """When the policy's inputs were sensed and when its commands act: one model for the training
    world (ttmjx/world/timing.py, both backends) and the simulated station (deploy/sim/station.py).

    Sensors sample at their rate (None: every physics step) and deliver each sample its latency
    (+ a uniform jitter) later; a sample may be dropped. At each control step the policy sees the
    line through the two newest delivered samples, evaluated at the step's time and followed at
    most `extrapolate_s` past the newest sample (then held): the robot runner's rule
    (deploy/robot/interp.py). Commands start acting `action_delay_s` after they are issued. With a
    tracker rate, episodes start at the ball's first tracker sample after the launch (the
    runner's trigger), not at the launch. Profiles: TIMING_PROFILES (docs/DESIGN.md gives the
    sources of the nominal values)."""
    tracker_hz: float | None = None
    """Ball tracker rate (Hz); None: every physics step."""
    tracker_latency_s: float = 0.0
    """Delay from a ball sample to its delivery (s)."""
    joint_hz: float | None = None
    """Joint feedback rate (Hz); None: every physics step."""
    joint_latency_s: float = 0.0
    """Delay from a joint sample to its delivery (s)."""
    action_delay_s: float = 0.0
    """Delay from a command to the start of its motion (s)."""
    jitter_s: float = 0.0
    """Extra delivery delay of each sample, uniform in [0, jitter_s] (s); below one sample period."""
    drop_prob: float = 0.0
    """Probability that a sample is never delivered."""
    extrapolate_s: float = 0.1
    """How far past the newest sample its line is followed (s); the runner's rule (the export's
    contract carries it). Far enough to bring a ball seen 50 ms late to the tick's time, so the
    ball's position does not depend on the tracker's latency; exports trained before it was
    recorded followed the line 20 ms (deploy.robot.contract.Contract.extrapolate_s)."""
    delay_spread_s: float = 0.0
    """Per episode, each of the two latencies and the action delay is shifted by a uniform draw in
    [-delay_spread_s, +delay_spread_s], never below zero (training randomization around the
    profile, so the profile itself sits in the middle of what training saw; 0: fixed)."""
    action_delay_spread_s: float | None = None
    """The per-episode spread of the action delay alone (s); None: delay_spread_s."""
    ideal_timing: bool = False
    """The explicit choice of ideal timing (every physics step sensed at once, commands acting at
    once): every field above is reset to its ideal value. Presets train under the cell's timing
    (CELL_TRAINING); a policy trained ideal plays only on an ideal station (`ttmjx robot run`
    refuses a real cell's timing for it)."""

    def __post_init__(self):
        self._check()
        if self.ideal_timing:
            for f in dataclasses.fields(self):
                if f.name not in ("ideal_timing", "extrapolate_s"):
                    object.__setattr__(self, f.name, f.default)

    def _check(self):
        """Every field in range (before ideal_timing resets them: a bad value is refused either way)."""
        for name in ("tracker_latency_s", "joint_latency_s", "action_delay_s", "jitter_s",
                     "extrapolate_s", "delay_spread_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"Timing.{name}={v!r}, expected a finite number of seconds >= 0")
        v = self.action_delay_spread_s
        if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
            raise ValueError(f"Timing.action_delay_spread_s={v!r}, expected None or a finite number of seconds >= 0")
        for name in ("tracker_hz", "joint_hz"):
            v = getattr(self, name)
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"Timing.{name}={v!r}, expected a rate in Hz > 0 or None")
        if not 0.0 <= self.drop_prob < 1.0:
            raise ValueError(f"Timing.drop_prob={self.drop_prob!r}, expected in [0, 1)")

    @property
    def ideal(self) -> bool:
        """Every physics step sensed at once and every command acting at once."""
        return (self.tracker_hz is None and self.joint_hz is None and self.tracker_latency_s == 0
                and self.joint_latency_s == 0 and self.action_delay_s == 0 and self.jitter_s == 0
                and self.drop_prob == 0 and max(self.spreads()) == 0)

    def spreads(self) -> tuple[float, float, float]:
        """Per-episode spreads (s) of the tracker latency, the joint latency and the action delay."""
        a = self.delay_spread_s if self.action_delay_spread_s is None else self.action_delay_spread_s
        return self.delay_spread_s, self.delay_spread_s, a

    def trained_ranges(self) -> dict:
        """What a policy trained under this timing saw, per episode: the sensor rates (None: every
        physics step) and [lowest, highest] of each latency and of the action delay (s), the
        jitter and drop probability ([0, largest]). deploy/sim/export.py records it in the contract;
        a station whose timing falls outside it is refused (deploy/robot/timing_check.py)."""
        rb, rj, ra = self.spreads()
        span = lambda v, r: [max(0.0, v - r), v + r]  # noqa: E731
        return {"tracker_hz": self.tracker_hz, "joint_hz": self.joint_hz,
                "tracker_latency_s": span(self.tracker_latency_s, rb),
                "joint_latency_s": span(self.joint_latency_s, rj),
                "action_delay_s": span(self.action_delay_s, ra),
                "jitter_s": [0.0, self.jitter_s], "drop_prob": [0.0, self.drop_prob]}

    def centre(self) -> "Timing":
        """This timing without its per-episode randomization: the profile a station plays."""
        return dataclasses.replace(self, delay_spread_s=0.0, action_delay_spread_s=None)

    def max_delay_s(self) -> float:
        """The longest latency or action delay an episode can draw (s)."""
        rb, rj, ra = self.spreads()
        return max(self.tracker_latency_s + rb, self.joint_latency_s + rj, self.action_delay_s + ra) + self.jitter_s


# Timing profiles (`--world.timing` presets, `ttmjx robot run --timing`). zero: ideal sensing.
# nominal: the paper's cell: tracker 125 Hz (stereo cameras), arm feedback ~240-250 Hz (EGM);
# the latencies are assumed (the paper gives none): one camera frame plus detection for the
# tracker, one EGM cycle for the feedback, two EGM cycles for a command. docs/DESIGN.md.
TIMING_PROFILES = {
    "zero": Timing(),
    "nominal": Timing(tracker_hz=125.0, tracker_latency_s=0.010, joint_hz=250.0, joint_latency_s=0.004,
                      action_delay_s=0.008, jitter_s=0.001),
}

# What every preset trains under (ideal timing is the explicit `--world.timing.ideal-timing`):
# the cell's `nominal` model, each latency and the command delay drawn per episode within +-10 ms
# of it, the ball's line followed up to 100 ms past its newest sample (Timing.extrapolate_s). A
# real cell's delays drift with load, cabling and firmware; a policy trained at fixed delays loses
# most of its success to 2 ms of extra command delay. A wider command-delay spread
# (`--world.timing.action-delay-spread-s 0.03`) buys tolerance to added command delay at a cost
# in success at the nominal timing (docs/RESULTS.md, "A policy that copes with delay").
CELL_TRAINING = dataclasses.replace(TIMING_PROFILES["nominal"], delay_spread_s=0.010)
IDEAL = Timing(ideal_timing=True)

CONTROL_RATES = (20, 60, 100)
MJX_IMPLS = ("jax", "warp")


@dataclasses.dataclass(frozen=True)
class World:
    """Everything that defines the task; saved with every run."""
    table: Table = Table()
    ball: Ball = Ball()
    contacts: Contacts = Contacts()
    robot: Robot = Robot()
    throws: Throws = Throws()
    physics_dt: float | None = None
    """Physics time step (s); None: the largest step <= max_physics_dt that divides the control
    period (1 ms at 20 and 100 Hz, 1/1020 s at 60 Hz). Contacts are calibrated near 1 ms."""
    control_hz: int = 100
    """Policy steps per second: 20 (the real robot), 60 or 100 (the paper's simulation)."""
    max_physics_dt: float = 0.001
    """Largest physics step (s) physics_dt may take when it is derived from control_hz."""
    episode_s: float = 1.6
    """Episode time limit (s) from the launch."""
    ball_velocity_obs: bool = False
    """True: 16-value observations with the ball velocity (the paper's original sim)."""
    frame_stack: int = 8
    """Frames in the observation stack (the frame-stack policy reads them)."""
    timing: Timing = Timing()
    """Sensor and actuation timing (default: ideal); TIMING_PROFILES names the lab's."""
    mjx_impl: str = "jax"
    """MJX's implementation on the mjx backend: jax (MJX in JAX) or warp (MuJoCo Warp through
    MJX, needs the `warp` extra: pip install 'ttmjx[warp]'). The same model and the same
    physics; docs/BENCHMARKS.md has their speeds on this scene."""

    def __post_init__(self):
        if not isinstance(self.control_hz, int) or self.control_hz <= 0:
            raise ValueError(f"control_hz must be a positive integer (20, 60 or 100), got {self.control_hz!r}")
        _number("world.max_physics_dt", self.max_physics_dt, 0.0, 0.1, low_open=True, what="time step in seconds")
        if self.physics_dt is not None:
            _number("world.physics_dt", self.physics_dt, 0.0, 0.1, low_open=True, what="time step in seconds")
        _number("world.episode_s", self.episode_s, 0.0, 60.0, low_open=True, what="time in seconds")
        if self.physics_dt is None:
            n = math.ceil(1.0 / (self.control_hz * self.max_physics_dt) - 1e-9)
            object.__setattr__(self, "physics_dt", 1.0 / (self.control_hz * n))
        physics_steps_per_sample(self.control_hz, self.physics_dt, "control_hz")
        if self.frame_stack < 1:
            raise ValueError(f"frame_stack must be >= 1, got {self.frame_stack}")
        if self.episode_s <= 0:
            raise ValueError(f"episode_s must be > 0, got {self.episode_s}")
        for name in ("tracker_hz", "joint_hz"):
            physics_steps_per_sample(getattr(self.timing, name), self.physics_dt, f"timing.{name}")
        shortest = min(self.sample_period_s("tracker_hz"), self.sample_period_s("joint_hz"))
        if self.timing.jitter_s and self.timing.jitter_s >= shortest:
            raise ValueError(f"timing.jitter_s={self.timing.jitter_s} must be below the shortest sample "
                             f"period ({shortest:.6g} s)")
        if self.mjx_impl not in MJX_IMPLS:
            raise ValueError(f"world.mjx_impl={self.mjx_impl!r}; expected one of {MJX_IMPLS}")
        check_world(self)

    def sample_period_s(self, name: str) -> float:
        """Sample period (s) of timing.tracker_hz or timing.joint_hz (a physics step if None)."""
        hz = getattr(self.timing, name)
        return self.physics_dt if hz is None else 1.0 / hz

    @property
    def substeps(self) -> int:
        """Physics steps per control step."""
        return physics_steps_per_sample(self.control_hz, self.physics_dt, "control_hz")

    @property
    def control_dt(self) -> float:
        return self.substeps * self.physics_dt

    @property
    def horizon(self) -> int:
        """Control steps per episode (time limit)."""
        return int(round(self.episode_s * self.control_hz))

    @property
    def obs_size(self) -> int:
        return 16 if self.ball_velocity_obs else 13

    def frame(self) -> dict:
        """The coordinate frame as reported in JSON."""
        return {"table_top_z": self.table.top_z,
                "table_x": [-self.table.half_length, self.table.half_length],
                "table_y": [-self.table.half_width, self.table.half_width]}

    def with_throws(self, name: str, **kw) -> "World":
        return dataclasses.replace(self, throws=dataclasses.replace(self.throws, name=name, **kw))

    def with_solver_caps(self, iterations: int | None = None, line_search: int | None = None) -> "World":
        """This world with the constraint solver's caps (Contacts.solver_iterations and
        line_search_iterations) replaced where given."""
        caps = {k: v for k, v in (("solver_iterations", iterations), ("line_search_iterations", line_search))
                if v is not None}
        return dataclasses.replace(self, contacts=dataclasses.replace(self.contacts, **caps))


def _flag(path: str) -> str:
    """The command-line flag of a World field path ('world.throws.narrow_speed' -> '--world.throws.narrow-speed')."""
    return "--" + path.replace("_", "-")


def _bad(path: str, value, expected: str) -> ValueError:
    shown = " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value) \
        if isinstance(value, (tuple, list)) else (f"{value:g}" if isinstance(value, float) else repr(value))
    return ValueError(f"{_flag(path)} {shown}: expected {expected}")


def _number(path: str, v, low: float | None = None, high: float | None = None, low_open: bool = False,
            high_open: bool = False, what: str = "a number") -> None:
    """v must be a finite real within [low, high] (open ends where asked)."""
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    if ok and low is not None:
        ok = v > low if low_open else v >= low
    if ok and high is not None:
        ok = v < high if high_open else v <= high
    if not ok:
        bound = []
        if low is not None:
            bound.append(f"{'>' if low_open else '>='} {low:g}")
        if high is not None:
            bound.append(f"{'<' if high_open else '<='} {high:g}")
        raise _bad(path, v, f"a finite {what}" + (f" {' and '.join(bound)}" if bound else ""))


def _numbers(path: str, v, n: int, **kw) -> None:
    if not isinstance(v, (tuple, list)) or len(v) != n:
        raise _bad(path, v if isinstance(v, (tuple, list)) else (v,),
                   f"{n} values, got {len(v) if isinstance(v, (tuple, list)) else 1}")
    for i, x in enumerate(v):
        try:
            _number(path, x, **kw)
        except ValueError:
            raise _bad(path, v, f"finite values{_range_words(**kw)}; value {i + 1} is {x!r}") from None


def _range_words(low=None, high=None, low_open=False, high_open=False, what=None) -> str:
    words = []
    if low is not None:
        words.append(f"{'>' if low_open else '>='} {low:g}")
    if high is not None:
        words.append(f"{'<' if high_open else '<='} {high:g}")
    return (" " + " and ".join(words)) if words else ""


def _interval(path: str, v, **kw) -> None:
    """A (lo, hi) range: two finite values, lo <= hi."""
    _numbers(path, v, 2, **kw)
    if v[0] > v[1]:
        raise _bad(path, v, f"a range LO HI with LO <= HI (reversed: {v[1]:g} {v[0]:g}?)")


def check_world(w: "World", prefix: str = "world") -> None:
    """Every physics, geometry and throw field of `w` at the door: finite, in range, the right
    length, ranges in order, and the relations MuJoCo's compiler or the thrower would otherwise
    trip over later (or that would make no throw valid). ValueError names the flag
    (--world.table.length), the value and what was expected."""
    t, b, c, r, th = w.table, w.ball, w.contacts, w.robot, w.throws
    for name in ("length", "width", "top_z", "thickness", "net_height", "net_length", "net_thickness"):
        _number(f"{prefix}.table.{name}", getattr(t, name), 0.0, low_open=True, what="length in metres")
    _number(f"{prefix}.ball.radius", b.radius, 0.0, 0.5, low_open=True, what="radius in metres")
    _number(f"{prefix}.ball.mass", b.mass, 0.0, low_open=True, what="mass in kg")
    for name in ("drag_coefficient", "magnus_coefficient", "angular_drag_coefficient", "air_density"):
        _number(f"{prefix}.ball.{name}", getattr(b, name), 0.0)
    for part in ("table", "paddle", "net"):
        _number(f"{prefix}.contacts.{part}_stiffness", getattr(c, f"{part}_stiffness"), 0.0, low_open=True)
        _number(f"{prefix}.contacts.{part}_damping", getattr(c, f"{part}_damping"), 0.0)
        _number(f"{prefix}.contacts.{part}_friction", getattr(c, f"{part}_friction"), 0.0)
    _number(f"{prefix}.contacts.impedance", c.impedance, 0.0, 1.0, low_open=True, high_open=True)
    rp = f"{prefix}.robot"
    for name in ("base_x", "base_y", "base_z"):
        _number(f"{rp}.{name}", getattr(r, name))
    _numbers(f"{rp}.lower", r.lower, 8)
    _numbers(f"{rp}.upper", r.upper, 8)
    for i, (lo, hi) in enumerate(zip(r.lower, r.upper)):
        if not lo < hi:
            raise ValueError(f"{_flag(rp + '.lower')} / {_flag(rp + '.upper')}: joint {JOINT_NAMES[i]} has lower "
                             f"{lo:g} >= upper {hi:g}; expected lower < upper for every joint")
    _numbers(f"{rp}.max_speed", r.max_speed, 8, low=0.0, low_open=True)
    _number(f"{rp}.speed_margin", r.speed_margin, 0.0, 1.0, low_open=True)
    _numbers(f"{rp}.link_masses", r.link_masses, 7, low=0.0, low_open=True)
    for name in ("gantry_mass", "paddle_mass", "extension", "blade_thickness", "servo_omega", "servo_damping"):
        _number(f"{rp}.{name}", getattr(r, name), 0.0, low_open=True)
    _numbers(f"{rp}.blade_half_size", r.blade_half_size, 2, low=0.0, low_open=True)
    _numbers(f"{rp}.armature", r.armature, 8, low=0.0)
    _numbers(f"{rp}.home", r.home, 8)
    _numbers(f"{rp}.home_noise", r.home_noise, 8, low=0.0)
    for i, (h, lo, hi) in enumerate(zip(r.home, r.lower, r.upper)):
        if not lo <= h <= hi:
            raise ValueError(f"{_flag(rp + '.home')}: joint {JOINT_NAMES[i]} at {h:g} is outside its limits "
                             f"[{lo:g}, {hi:g}]; expected a home pose within --world.robot.lower/upper")
    tp = f"{prefix}.throws"
    _number(f"{tp}.max_spin", th.max_spin, 0.0)
    _numbers(f"{tp}.narrow_launch", th.narrow_launch, 3)
    for name in ("narrow_aim_x", "narrow_aim_y", "any_launch_x", "any_launch_y", "any_launch_z", "any_aim_x",
                 "any_aim_y", "varied_yaw_deg", "varied_distance"):
        _interval(f"{tp}.{name}", getattr(th, name))
    for name in ("narrow_speed", "any_speed"):
        _interval(f"{tp}.{name}", getattr(th, name), low=0.0, low_open=True)
    _numbers(f"{tp}.varied_launch_x", th.varied_launch_x, 3)
    _numbers(f"{tp}.varied_launch_yz", th.varied_launch_yz, 2)
    _number(f"{tp}.varied_speed", th.varied_speed, 0.0, low_open=True, what="speed in m/s")
    _number(f"{tp}.max_pitch", th.max_pitch, 0.0, math.pi / 2, low_open=True, high_open=True, what="angle in rad")
    _number(f"{tp}.net_margin", th.net_margin, 0.0, what="margin in metres")
    _number(f"{tp}.solve_tol", th.solve_tol, 0.0, low_open=True, what="tolerance in metres")
    _number(f"{tp}.max_flight_s", th.max_flight_s, 0.0, low_open=True, what="time in seconds")
    # The fastest possible flight: the shortest horizontal distance from a launch to an aim at the
    # highest speed; a limit below it leaves no valid throw (every candidate redrawn forever).
    if th.name == "narrow":
        dist, speed, field = th.narrow_launch[0] - th.narrow_aim_x[1], th.narrow_speed[1], "narrow_speed"
    elif th.name == "any":
        dist, speed, field = th.any_launch_x[0] - th.any_aim_x[1], th.any_speed[1], "any_speed"
    else:
        dist, speed, field = th.varied_distance[0], th.varied_speed, "varied_speed"
    if dist > 0 and th.max_flight_s < dist / speed:
        raise _bad(f"{tp}.max_flight_s", th.max_flight_s,
                   f"at least {dist / speed:.3g} s: the fastest {th.name} throw ({_flag(f'{tp}.{field}')} up to "
                   f"{speed:g} m/s) needs that long to cover {dist:.3g} m, so no throw would be valid; raise one "
                   f"or the other")


def to_dict(cfg) -> dict:
    """A JSON-ready dict of a (nested) config dataclass."""
    return dataclasses.asdict(cfg)


def from_dict(cls, d: dict):
    """Inverse of to_dict for nested frozen dataclasses (tuples restored from lists)."""
    kwargs = {}
    fields = {f.name: f for f in dataclasses.fields(cls)}
    for k, v in d.items():
        if k not in fields:
            raise ValueError(f"unknown config field {cls.__name__}.{k}")
        ftype = fields[k].type
        sub = _DATACLASSES.get(ftype if isinstance(ftype, str) else getattr(ftype, "__name__", ""))
        if sub is not None and isinstance(v, dict):
            v = from_dict(sub, v)
        elif isinstance(v, list):
            v = tuple(tuple(x) if isinstance(x, list) else x for x in v)
        kwargs[k] = v
    return cls(**kwargs)


_DATACLASSES = {c.__name__: c for c in (Table, Ball, Contacts, Robot, Throws, Timing, World)}


def opponent_half(table: Table) -> np.ndarray:
    """[[xmin, xmax], [ymin, ymax]] of the opponent's half (goals live here)."""
    return np.array([[0.0, table.half_length], [-table.half_width, table.half_width]])
