"""The in-memory U(C)RDF robot description: plain dataclasses, SI units, no XML.

The parser builds these, the writer serialises them, every other part (kinematics, firmware
configuration, host daemon) reads them. Equality is structural, so parse -> write -> parse can be
compared with ``==``. ``line`` fields record where an element came from (for error messages) and are
excluded from equality.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

Vec3 = tuple[float, float, float]


@dataclass
class Origin:
    """A URDF ``<origin xyz rpy>``: translation (m) then fixed-axis roll-pitch-yaw (rad)."""

    xyz: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """4x4 homogeneous transform, R = Rz(yaw) Ry(pitch) Rx(roll) as URDF defines it."""
        r, p, y = self.rpy
        cr, sr, cp, sp, cy, sy = (
            math.cos(r),
            math.sin(r),
            math.cos(p),
            math.sin(p),
            math.cos(y),
            math.sin(y),
        )
        t = np.eye(4)
        t[:3, :3] = [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
        t[:3, 3] = self.xyz
        return t

    def is_identity(self) -> bool:
        return self.xyz == (0.0, 0.0, 0.0) and self.rpy == (0.0, 0.0, 0.0)


@dataclass
class Inertial:
    """``<inertial>``: mass (kg), centre of mass origin, inertia tensor (kg m^2) about it."""

    mass: float = 0.0
    origin: Origin = field(default_factory=Origin)
    # ixx, ixy, ixz, iyy, iyz, izz
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass
class Geometry:
    """A visual or collision element, kept as the XML text it came from (meshes not interpreted).

    ``kind`` is "visual" or "collision"; ``xml`` is the serialised element, normalised by the parser
    so that round trips compare equal.
    """

    kind: str
    xml: str
    line: int = field(default=0, compare=False)


@dataclass
class Link:
    name: str
    inertial: Inertial | None = None
    geometry: list[Geometry] = field(default_factory=list)
    line: int = field(default=0, compare=False)
    # Extension children (namespaced elements) kept verbatim as normalised XML text.
    extensions: list[str] = field(default_factory=list)


@dataclass
class JointLimit:
    """URDF ``<limit>``: position bounds (rad or m), effort (N or N m), velocity (rad/s or m/s)."""

    lower: float = 0.0
    upper: float = 0.0
    effort: float = 0.0
    velocity: float = 0.0


@dataclass
class Joint:
    """A rigid URDF joint: fixed, revolute, continuous, prismatic, floating or planar."""

    name: str
    type: str
    parent: str
    child: str
    origin: Origin = field(default_factory=Origin)
    axis: Vec3 = (1.0, 0.0, 0.0)
    limit: JointLimit | None = None
    line: int = field(default=0, compare=False)
    # Children not interpreted here (calibration, dynamics, mimic, safety_controller, namespaced
    # extensions) kept verbatim as normalised XML text so a rewrite loses nothing.
    extensions: list[str] = field(default_factory=list)

    @property
    def movable(self) -> bool:
        return self.type in ("revolute", "continuous", "prismatic")


@dataclass
class CurvatureLimits:
    """``<limits>`` inside ``<model>``: bounds of the configuration, SI units.

    kappa_max: largest curvature magnitude (1/m); kappa_rate_max: largest rate of change of the
    curvature vector (1/m/s); phi_min/phi_max: bending-plane angle range (rad), default the full
    circle. Model-specific extra limits (e.g. a PPC slope bound) go in ``extra``.
    """

    kappa_max: float
    kappa_rate_max: float | None = None
    phi_min: float = -math.pi
    phi_max: float = math.pi
    extra: dict[str, float] = field(default_factory=dict)


@dataclass
class Backbone:
    """``<backbone>``: the elastic core. length (m), radius (m), Young's modulus (Pa) and/or
    bending stiffness EI (N m^2). If only one of the two is given, the other follows from
    EI = E*pi*r^4/4."""

    length: float
    radius: float = 0.0
    youngs_modulus: float | None = None
    bending_stiffness: float | None = None

    def stiffness(self) -> float | None:
        """Bending stiffness EI (N m^2), derived from E and r when not given directly."""
        if self.bending_stiffness is not None:
            return self.bending_stiffness
        if self.youngs_modulus is not None and self.radius > 0:
            return self.youngs_modulus * math.pi * self.radius**4 / 4.0
        return None


@dataclass
class ModelSpec:
    """``<curvature><model type="…">``: which kinematic model and its parameters.

    ``params`` holds the model's own parameters (``<param name value>`` children), typed as float
    when numeric, else str. Limits and backbone live inside ``<model>`` as the paper prescribes.
    """

    type: str
    limits: CurvatureLimits
    backbone: Backbone
    params: dict[str, float | str] = field(default_factory=dict)


@dataclass
class Servo:
    """One actuator of a tendon: bus id (or PWM channel), zero offset (rad), direction (+1/-1),
    travel range (rad, relative to zero)."""

    id: int
    zero_offset: float = 0.0
    direction: int = 1
    min_angle: float = -math.pi
    max_angle: float = math.pi


#: The PWM pulse calibration a ``pwm`` driver runs when ``<pwm_pulse>`` does not say (the firmware's
#: defaults, device/servos/pwm.py ``_DEFAULT``): 500..2500 us span pi rad of raw servo angle.
PWM_MIN_US = 500.0
PWM_MAX_US = 2500.0
PWM_RANGE = math.pi


@dataclass
class PwmPulse:
    """``<pwm_pulse min_us max_us range/>``: the pulse widths (us) at the ends of a hobby servo's
    travel and the raw angle (rad) between them. Raw angle 0 (= ``zero_offset``) is the centre
    pulse, so a PWM servo reaches raw angles in [-range/2, range/2] and no further."""

    min_us: float = PWM_MIN_US
    max_us: float = PWM_MAX_US
    range: float = PWM_RANGE

    @property
    def half(self) -> float:
        """Largest raw angle (rad) either side of the centre pulse."""
        return self.range / 2.0


@dataclass
class Actuation:
    """``<actuation type="tendon">``: how the segment bends.

    Tendon i sits at angle ``angles[i]`` (rad) around the backbone, measured in the segment base
    frame from +x towards +y, at distance ``radius`` (m) from the backbone axis. Its length is
    l_i = l * (1 - radius * (kx*cos(sigma_i) + ky*sin(sigma_i))). Each tendon is wound on a spool of
    ``spool_radius`` (m) by ``servos[i]``. ``driver`` names the servo driver on the segment
    ("pwm", "feetech_sts", "emulated"); ``board``, ``uarts`` and ``pwm_pins`` its wiring.
    """

    type: str = "tendon"
    angles: list[float] = field(default_factory=list)
    radius: float = 0.0
    spool_radius: float = 0.0
    driver: str = "pwm"
    servos: list[Servo] = field(default_factory=list)
    #: board the segment runs on (``protocol/boards.py``); None = not said (esp32 by default)
    board: str | None = None
    #: wiring overrides by role ("upstream", "downstream", "servo_bus"): {id, tx, rx[, baud]}
    uarts: dict[str, dict[str, int]] = field(default_factory=dict)
    #: PWM pin per servo index (overrides the board's default pins)
    pwm_pins: dict[int, int] = field(default_factory=dict)
    #: PWM pulse calibration (``<pwm_pulse>``); None = the firmware's defaults (PwmPulse())
    pwm_pulse: PwmPulse | None = None

    def pulse(self) -> PwmPulse:
        """The PWM pulse calibration a ``pwm`` driver runs (declared, else the defaults)."""
        return self.pwm_pulse if self.pwm_pulse is not None else PwmPulse()

    @property
    def count(self) -> int:
        return len(self.angles)


@dataclass
class Bendable:
    """``<bendable>``: a continuum segment, joint and link at once (paper section IV)."""

    name: str
    parent: str
    child: str
    model: ModelSpec
    origin: Origin = field(default_factory=Origin)
    inertial: Inertial | None = None
    actuation: Actuation | None = None
    line: int = field(default=0, compare=False)

    @property
    def length(self) -> float:
        return self.model.backbone.length


@dataclass
class Interface:
    """A ros2_control command or state interface with its ``<param>`` children (initial_value, min,
    max as floats; anything else kept as given)."""

    name: str
    params: dict[str, float | str] = field(default_factory=dict)


@dataclass
class ControlJoint:
    """``<joint>`` inside ``<ros2_control>``: names a bendable or a rigid joint."""

    name: str
    command_interfaces: list[Interface] = field(default_factory=list)
    state_interfaces: list[Interface] = field(default_factory=list)
    line: int = field(default=0, compare=False)


@dataclass
class Ros2Control:
    """``<ros2_control name type>`` with ``<hardware>`` plugin and params."""

    name: str
    type: str = "system"
    plugin: str = ""
    hardware_params: dict[str, str] = field(default_factory=dict)
    joints: list[ControlJoint] = field(default_factory=list)
    line: int = field(default=0, compare=False)


@dataclass
class Robot:
    """A whole U(C)RDF robot. Dicts keep document order."""

    name: str
    links: dict[str, Link] = field(default_factory=dict)
    joints: dict[str, Joint] = field(default_factory=dict)
    bendables: dict[str, Bendable] = field(default_factory=dict)
    ros2_control: list[Ros2Control] = field(default_factory=list)
    source: str = field(default="", compare=False)
    # Top-level extension elements (<gazebo>, <transmission>, <material>, anything unknown) kept
    # verbatim as normalised XML text, in document order.
    extensions: list[str] = field(default_factory=list)

    def hardware_params(self) -> dict[str, str]:
        """Every ``<ros2_control><hardware><param>`` of the robot (a later block's value wins)."""
        return {k: v for block in self.ros2_control for k, v in block.hardware_params.items()}

    def root_link(self) -> str:
        """The one link that is nobody's child."""
        children = {j.child for j in self.joints.values()} | {
            b.child for b in self.bendables.values()
        }
        roots = [name for name in self.links if name not in children]
        if len(roots) != 1:
            raise ValueError(f"robot {self.name!r} has {len(roots)} root links: {roots}")
        return roots[0]
