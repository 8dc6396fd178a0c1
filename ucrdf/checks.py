"""Semantic checks of a U(C)RDF robot: what the XML Schema cannot express.

Cross references (links named by joints and bendables, ros2_control joints naming bendables or
joints), tree shape (one parent per link, no cycles, one root), physical ranges (positive lengths
and curvature limits, tendons that keep a positive length), consistency with the kinematic model
plugin (variables named by interfaces, the model's own ``validate()``, interface bounds inside the
model limits) and actuation (tendon/servo counts, servo direction ±1). Each bendable's segment
configuration (:func:`segment_config`) is also run through the segment firmware's own validation
(``device/config.py`` and the fixed-point set-up of ``device/mechanism.py``, loaded from the
source tree by :func:`firmware_refusal`), so whatever ``ucr check`` accepts the firmware runs
exactly, and whatever it would refuse is reported here with its reason.

:func:`check` returns every problem found, each as a :class:`ucrdf.errors.Diagnostic`; it never
raises on bad content. The parser passes its line table so each message points at the offending
element; for robots built in code (``ucrdf.compose``) the lines fall back to 0.
"""

from __future__ import annotations

import difflib
import importlib.util
import math
import re
import sys
from collections.abc import Callable
from functools import cache
from pathlib import Path
from types import ModuleType

import numpy as np

import ucrdf.models as registry
from protocol import constants as C
from ucrdf.boards import check as board_plans
from ucrdf.boards import plan as board_wiring
from ucrdf.boards import problems as board_problems
from ucrdf.errors import Diagnostic
from ucrdf.model import (
    Bendable,
    ControlJoint,
    Inertial,
    Interface,
    Joint,
    Robot,
    Ros2Control,
)
from ucrdf.models.base import CurvatureModel, ModelError
from ucrdf.numtext import number, shown, whole
from ucrdf.units import beyond_a_turn, degrees_hint

# Key of a line-number table entry: ("bendable", name, "limits"), ("ros2_control", 0, "joint", 2)…
LineKey = tuple[object, ...]
LineTable = dict[LineKey, int]

_PHI_SLACK = 1e-9  # rad: tolerance on the (-pi, pi] bending-plane range when written as decimals

#: Largest length or position (m) a description may give: origins, backbone length and radius,
#: spool radius, prismatic limits (a tendon radius is bounded by d*kappa_max < 1 already). No
#: robot comes near 1000 km; a larger value is a mistake, and where FK, IK and the export add and
#: square such values they overflow (1e308 + 1e308 is inf) into output that is no number at all.
MAX_LENGTH_M = 1e6


def _exceeds(value: float, bound: float) -> bool:
    return value > bound + 1e-9 * max(1.0, abs(bound))


def _below(value: float, bound: float) -> bool:
    return value < bound - 1e-9 * max(1.0, abs(bound))


def kappa_resolution_problem(value: float, unit: str = "1/m") -> str | None:
    """Why a positive curvature limit cannot run on a segment, or None: the wire and the
    firmware count kappa in units of 1/KAPPA_SCALE (1e-4 1/m), and a limit rounding to 0 units
    would be 0 there (device/config.py refuses it, and PARAM_SET)."""
    if value * C.KAPPA_SCALE < 0.5:  # int(value * scale + 0.5), the firmware's rounding, is 0
        return (
            f"{value:g} {unit} rounds to 0 in the segment's fixed point (units of "
            f"{1.0 / C.KAPPA_SCALE:g} {unit}): at least {0.5 / C.KAPPA_SCALE:g}"
        )
    return None


def _did_you_mean(name: str, known: object) -> str:
    """`` (did you mean 'x'?)`` for the closest known name, or ''."""
    close = difflib.get_close_matches(name, [str(k) for k in known], n=1)  # type: ignore[attr-defined]
    return f" (did you mean {close[0]!r}?)" if close else ""


def _names(items: object) -> str:
    listed = ", ".join(sorted(str(i) for i in items))  # type: ignore[attr-defined]
    return listed or "none"


def model_registry() -> tuple[Callable[[str], type[CurvatureModel]], Callable[[], list[str]]]:
    """``(get_model, available)`` from :mod:`ucrdf.models`; raises LookupError if the installed
    registry lacks them (a broken installation, reported as a diagnostic by :func:`check`)."""
    get_model = getattr(registry, "get_model", None)
    available = getattr(registry, "available", None)
    if get_model is None or available is None:
        raise LookupError("model registry ucrdf.models has no get_model()/available()")
    return get_model, available


#: Curvature rate limit (1/m/s) when the model's <limits> gives none: one value for the host, the
#: segment configuration and the firmware (protocol/constants.py).
DEFAULT_KAPPA_RATE_MAX = C.DEFAULT_KAPPA_RATE_MAX
_DEVICE = Path(__file__).resolve().parent.parent / "device"
#: Servo drivers of the ucr segment firmware (device/config.py): the only values of
#: ``<actuation driver>`` (docs/ucrdf.md); a bendable's configuration must be one the firmware runs.
FIRMWARE_DRIVERS = ("emulated", "pwm", "feetech_sts", "feetech_scs")

#: Relative slack on the inertia triangle inequality and on negative principal moments (fraction
#: of the largest principal moment): inertias written with 3 significant digits still pass.
INERTIA_SLACK = 1e-2

#: ros2_control interface names of a rigid joint (hardware_interface/types).
JOINT_INTERFACES = ("position", "velocity", "acceleration", "effort")

#: The hardware plugin of this project's segment chain, and the <hardware> params it takes (a
#: param ``<bendable>/uid`` besides): name -> meaning (docs/ucrdf.md).
SEGMENT_PLUGIN = "SoftRobotInterface"
SEGMENT_PLUGIN_PARAMS = (
    "model",
    "port",
    "baudrate",
    "watchdog_ms",
    "tick_ms",
    "hw_watchdog_ms",
    "fault_action",
)
#: what a segment does with its servos in FAULT (device/config.py ``fault_action``)
FAULT_ACTIONS = ("hold", "release")
#: Lowest UART speed accepted for the ``baudrate`` hardware param (bit/s, as host/config.py).
MIN_BAUDRATE = 1200


#: PWM pulse limits the segment firmware accepts (device/servos/pwm.py): a pulse shorter than
#: the 50 Hz period, a span of at most 4000 us; a range above 10*pi rad (5 turns) is taken for
#: degrees written for radians.
PWM_PERIOD_US = 20000
PWM_MAX_SPAN_US = 4000
PWM_MAX_RANGE = 10 * math.pi

#: Watchdog time (ms) when the robot does not say: the host cycle runs at 50–100 Hz, so 200 ms is
#: ten to twenty missed cycles.
DEFAULT_WATCHDOG_MS = 200
#: The control tick's period (ms) when the robot does not say (the firmware's config.py default)
DEFAULT_TICK_MS = 5

#: hardware params flashed into each segment's config.json: name -> (min, max, whole ms only,
#: the value a segment runs when the robot does not give it)
SEGMENT_MS_PARAMS: dict[str, tuple[int, int, bool, int]] = {
    "watchdog_ms": (10, 60000, False, DEFAULT_WATCHDOG_MS),
    "tick_ms": (2, 50, True, DEFAULT_TICK_MS),
    # the board's hardware watchdog (machine.WDT): 0 = off, else 50..60000 ms
    "hw_watchdog_ms": (0, 60000, True, 0),
}
HW_WATCHDOG_MIN_MS = 50  # device/config.py: an ESP32 watchdog shorter than this is refused
#: A hardware watchdog at least this long (ms) leaves room for the slowest frame handling, a
#: calibration being stored (docs/firmware.md "Hardware watchdog"); ``ucr check`` warns below it.
HW_WATCHDOG_STORE_MS = 1000


def segment_ms_param(name: str, value: object) -> int:
    """A segment hardware param (``SEGMENT_MS_PARAMS``) as the int ms flashed; ValueError with
    the reason if the firmware could not run it (``ucr check`` and ``ucr flash`` both use this)."""
    lo, hi, whole_ms, _ = SEGMENT_MS_PARAMS[name]
    try:  # the text of a <param>, as every reader of the file reads it (not 2_00)
        ms = number(value) if isinstance(value, str) else float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        ms = None
    if ms is None:
        shown_value = shown(value) if isinstance(value, str) else repr(value)
        raise ValueError(f"{name} must be a number of ms, got {shown_value}")
    if not (math.isfinite(ms) and lo <= ms <= hi):
        raise ValueError(f"{name} {ms:g} is outside {lo}..{hi} ms")
    if whole_ms and ms != int(ms):
        raise ValueError(f"{name} {ms:g} is not a whole number of ms")
    if name == "hw_watchdog_ms" and 0 < ms < HW_WATCHDOG_MIN_MS:
        raise ValueError(f"{name} {ms:g} must be 0 (off) or {HW_WATCHDOG_MIN_MS}..{hi} ms")
    return int(round(ms))


def segment_hardware_params(robot: Robot, b: Bendable) -> dict:
    """The segment keys the robot's hardware params give bendable ``b``, only those it gives:
    ``watchdog_ms``, ``tick_ms``, ``hw_watchdog_ms`` (int ms) and ``fault_action``, each from the
    bendable's model params, else from a ros2_control ``<hardware>`` param. ValueError with the
    reason for a value the firmware could not run. ``ucr flash`` writes them into config.json and
    ``ucr doctor`` hashes them as the segment does (protocol/confighash.py)."""
    out: dict = {}
    for name in (*SEGMENT_MS_PARAMS, "fault_action"):
        value = b.model.params.get(name)
        if value is None:
            value = next(
                (
                    rc.hardware_params[name]
                    for rc in robot.ros2_control
                    if name in rc.hardware_params
                ),
                None,
            )
        if value is None:
            continue
        if name != "fault_action":
            out[name] = segment_ms_param(name, value)
        elif value in FAULT_ACTIONS:
            out[name] = value
        else:
            raise ValueError(
                f"fault_action must be one of {', '.join(FAULT_ACTIONS)} (what the servos do in "
                f"FAULT), got {value!r}"
            )
    return out


def segment_config(b: Bendable, watchdog_ms: int = DEFAULT_WATCHDOG_MS) -> dict:
    """The segment configuration (``config.json`` contract, SI units) of bendable ``b`` with a
    tendon actuation; the one mapping from U(C)RDF to firmware keys (tools/segment_config.py
    adds its own checks and the watchdog time)."""
    act = b.actuation
    assert act is not None
    servos = [
        {
            "id": s.id,
            "zero_offset": s.zero_offset,
            "direction": s.direction,
            "min_angle": s.min_angle,
            "max_angle": s.max_angle,
        }
        for s in act.servos
    ] or [
        {"id": i, "zero_offset": 0.0, "direction": 1, "min_angle": -math.pi, "max_angle": math.pi}
        for i in range(len(act.angles))
    ]
    limits = b.model.limits
    rate = limits.kappa_rate_max if limits.kappa_rate_max is not None else DEFAULT_KAPPA_RATE_MAX
    return {
        "name": b.name,
        "length": b.model.backbone.length,
        "tendon_angles": list(act.angles),
        "tendon_radius": act.radius,
        "spool_radius": act.spool_radius,
        "kappa_max": limits.kappa_max,
        "kappa_rate_max": rate,
        "mass": b.inertial.mass if b.inertial is not None else 0.0,
        "backbone_radius": b.model.backbone.radius,
        "model": b.model.type,
        "servo_driver": act.driver,
        "servos": servos,
        "watchdog_ms": watchdog_ms,
        # the board and its wiring (ucrdf/boards.py) when the plan is possible (else reported
        # by the board check, and config_for refuses it)
        **({} if board_problems(act) else board_wiring(act)),
    }


@cache
def _firmware() -> tuple[ModuleType, ModuleType] | None:
    """(config, mechanism) modules of the segment firmware loaded by path from ``device/``, or
    None when the firmware sources are not installed beside this package."""
    if not (_DEVICE / "config.py").is_file():
        return None
    names = ("fxp", "config", "mechanism")  # mechanism imports fxp by its plain name
    saved = {n: sys.modules.get(n) for n in names}
    loaded: dict[str, ModuleType] = {}
    try:
        for name in names:
            spec = importlib.util.spec_from_file_location(name, _DEVICE / f"{name}.py")
            assert spec is not None and spec.loader is not None
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            spec.loader.exec_module(module)
            loaded[name] = module
    finally:
        for n, m in saved.items():
            if m is None:
                sys.modules.pop(n, None)
            else:
                sys.modules[n] = m
    return loaded["config"], loaded["mechanism"]


def firmware_refusal(config: dict) -> str | None:
    """Why the segment firmware would refuse ``config`` (and stay unable to move), or None if it
    runs it: the firmware's own validation, run on the host."""
    fw = _firmware()
    if fw is None:
        return None
    fw_config, fw_mechanism = fw
    try:
        cfg = fw_config.Config(dict(config), "emulated")
        fw_mechanism.Mechanism(cfg, 5)
    except (ValueError, TypeError, KeyError, ZeroDivisionError) as exc:
        return str(exc)
    return None


def check(robot: Robot, lines: LineTable | None = None) -> list[Diagnostic]:
    """All semantic problems of ``robot`` (empty list = the description is usable)."""
    checker = _Checker(robot, lines or {})
    checker.run()
    return checker.diagnostics


def warnings(robot: Robot, lines: LineTable | None = None) -> list[Diagnostic]:
    """What ``ucr check`` warns about in a usable description: a tendon actuation without
    ``<servo>`` elements, whose segment ``ucr flash`` refuses (its servo ids and calibration are
    unknown, and none are invented); a hardware watchdog shorter than HW_WATCHDOG_STORE_MS, which
    may reset a segment while it stores a calibration (docs/firmware.md "Hardware watchdog")."""
    lines = lines or {}
    out = []
    given = [(("bendable", n, "param"), b.model.params, b.line) for n, b in robot.bendables.items()]
    given += [
        (("ros2_control", i, "param"), rc.hardware_params, rc.line)
        for i, rc in enumerate(robot.ros2_control)
    ]
    for key, params, fallback in given:
        try:
            ms = segment_ms_param("hw_watchdog_ms", params.get("hw_watchdog_ms", 0))
        except ValueError:  # an error of check()
            continue
        if 0 < ms < HW_WATCHDOG_STORE_MS:
            out.append(
                Diagnostic(
                    robot.source or "<robot>",
                    lines.get((*key, "hw_watchdog_ms"), fallback),
                    f"warning: hardware param hw_watchdog_ms {ms} is below "
                    f"{HW_WATCHDOG_STORE_MS} ms: storing a calibration is estimated to take "
                    "150-390 ms on an ESP32 plus the flash erase, and may reset the segment "
                    "(it reboots in FAULT WDT_RESET)",
                )
            )
    for b in robot.bendables.values():
        act = b.actuation
        if act is None or not act.angles or act.servos:
            continue
        line = lines.get(("bendable", b.name, "actuation"), b.line)
        out.append(
            Diagnostic(
                robot.source or "<robot>",
                line,
                f"warning: bendable {b.name!r}: actuation declares no <servo>: add one <servo "
                "index= id= zero_offset= direction= min_angle= max_angle=/> per tendon; "
                "`ucr flash` refuses this segment until then",
            )
        )
    return out


def inertia_problem(inertia: tuple[float, ...]) -> str | None:
    """Why the inertia tensor (ixx, ixy, ixz, iyy, iyz, izz) in kg m^2 no rigid body has, or None:
    its principal moments must be >= 0 and each at most the sum of the other two (a slack of
    INERTIA_SLACK times the largest one absorbs rounding)."""
    ixx, ixy, ixz, iyy, iyz, izz = inertia
    tensor = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=float)
    moments = np.linalg.eigvalsh(tensor)
    slack = INERTIA_SLACK * float(np.abs(moments).max())
    text = ", ".join(f"{m:.4g}" for m in moments)
    if moments.min() < -slack:
        return f"a principal moment is negative (principal moments {text} kg m^2)"
    diag = {"ixx": ixx, "iyy": iyy, "izz": izz}
    for name, value in diag.items():
        others = sum(v for k, v in diag.items() if k != name)
        if value > others + slack:
            rest = " + ".join(k for k in diag if k != name)
            return f"{name} {value:g} exceeds {rest} = {others:g} (triangle inequality)"
    if moments[2] > moments[0] + moments[1] + slack:
        return (
            f"the largest principal moment {moments[2]:.4g} exceeds the sum of the other two "
            f"(principal moments {text} kg m^2; triangle inequality)"
        )
    return None


class _Checker:
    def __init__(self, robot: Robot, lines: LineTable):
        self.robot = robot
        self.lines = lines
        self.diagnostics: list[Diagnostic] = []
        # bendable name -> constructed model (only for bendables whose model validated)
        self.models: dict[str, CurvatureModel] = {}
        self.model_classes: dict[str, type[CurvatureModel]] = {}

    def line(self, key: LineKey, fallback: int = 0) -> int:
        return self.lines.get(key, fallback)

    def error(self, line: int, message: str) -> None:
        self.diagnostics.append(Diagnostic(self.robot.source or "<robot>", line, message))

    # -------------------------------------------------------------------------------------------
    def run(self) -> None:
        robot = self.robot
        rline = self.line(("robot",))
        if not robot.name.strip():
            self.error(rline, "robot has an empty name")
        if not robot.links:
            self.error(rline, f"robot {robot.name!r} has no <link>; a robot needs at least one")
        for kind, items in (
            ("link", robot.links),
            ("joint", robot.joints),
            ("bendable", robot.bendables),
        ):
            for name, item in items.items():
                if not name.strip():
                    self.error(
                        self.line((kind, name), item.line),
                        f"{kind} name {name!r} is blank: a name needs a visible character",
                    )
        for name in robot.joints.keys() & robot.bendables.keys():
            b = robot.bendables[name]
            self.error(
                b.line,
                f"duplicate name {name!r}: a joint and a bendable share it "
                "(joints and bendables share one namespace)",
            )
        for link in robot.links.values():
            if link.inertial is not None:
                line = self.line(("link", link.name, "inertial"), link.line)
                self.inertial(
                    link.inertial,
                    f"link {link.name!r}",
                    line,
                    self.line(("link", link.name, "inertial", "origin"), line),
                )
        for joint in robot.joints.values():
            self.joint(joint)
        for bendable in robot.bendables.values():
            self.bendable(bendable)
        self.diagnostics += board_plans(robot, self.lines)  # ucrdf/boards.py: wiring per board
        self.tree()
        self.mimics()
        self.ros2_control()

    def mimics(self) -> None:
        """Each ``<mimic>`` FK cannot follow, at its joint: the rule of ucrdf/fk.py (``mimics``),
        so whatever ``ucr check`` accepts, ``ucr fk`` and the exports take."""
        from ucrdf.fk import mimics  # noqa: PLC0415 - numpy: only for a robot that has joints

        if not any(j.extensions for j in self.robot.joints.values()):
            return
        for name, message in mimics(self.robot)[1]:
            self.error(self.robot.joints[name].line, message)

    # -- kinematic tree ----------------------------------------------------------------------------
    def tree(self) -> None:
        robot = self.robot
        edges: list[tuple[str, str, str, str, int]] = []  # (kind, name, parent, child, line)
        for j in robot.joints.values():
            edges.append(("joint", j.name, j.parent, j.child, j.line))
        for b in robot.bendables.values():
            edges.append(("bendable", b.name, b.parent, b.child, b.line))
        edges.sort(key=lambda e: e[4])  # document order, so errors point at the later element
        parent_of: dict[str, tuple[str, str, str, int]] = {}  # child -> (kind, name, parent, line)
        for kind, name, parent, child, line in edges:
            ok = True
            for role, link in (("parent", parent), ("child", child)):
                if link not in robot.links:
                    self.error(
                        self.line((kind, name, role), line),
                        f"{kind} {name!r}: {role} link {link!r} is not defined "
                        f"(links: {_names(robot.links)})",
                    )
                    ok = False
            if not ok:
                continue
            if parent == child:
                self.error(line, f"{kind} {name!r} connects link {parent!r} to itself")
                continue
            if child in parent_of:
                other_kind, other_name, _, other_line = parent_of[child]
                self.error(
                    self.line((kind, name, "child"), line),
                    f"link {child!r} has two parents: {kind} {name!r} and {other_kind} "
                    f"{other_name!r} (line {other_line}); a link has at most one parent",
                )
                continue
            parent_of[child] = (kind, name, parent, line)

        # cycles: with one parent per link, following parents either reaches a root or loops.
        # One walk per link, colouring each link once (done / on the current walk), so the whole
        # check is linear in the number of links.
        done: set[str] = set()
        for start in robot.links:
            path: list[str] = []
            on_path: set[str] = set()
            node = start
            while node in parent_of and node not in done and node not in on_path:
                on_path.add(node)
                path.append(node)
                node = parent_of[node][2]
            if node in on_path:
                self.cycle(path[path.index(node) :], parent_of)
            done.update(path)

        # links that are the child of a joint/bendable already reported invalid (and left out)
        # are not roots: one problem, one report
        invalid = [k for k in self.lines if k[:1] == ("invalid",)]
        adopted = {k[4] for k in invalid if k[4] is not None}
        unknown_children = sum(1 for k in invalid if k[4] is None)  # e.g. a joint lacking <child>
        roots = [name for name in robot.links if name not in parent_of and name not in adopted]
        if len(roots) - unknown_children > 1:
            line = robot.links[roots[1]].line
            self.error(
                line,
                f"robot has {len(roots)} root links ({', '.join(roots)}); exactly one link may "
                "lack a parent — connect the others with a joint or bendable",
            )

    def cycle(self, cycle: list[str], parent_of: dict[str, tuple[str, str, str, int]]) -> None:
        """Report one kinematic cycle (links in child -> parent order)."""
        # parent -> child order, starting at the parent of the earliest edge in the file
        order = list(reversed(cycle))
        first = min(cycle, key=lambda n: parent_of[n][3])
        start_at = order.index(parent_of[first][2])
        order = order[start_at:] + order[:start_at]
        names = " -> ".join([*order, order[0]])
        line = parent_of[first][3]
        via = ", ".join(f"{parent_of[n][0]} {parent_of[n][1]!r}" for n in [*order[1:], order[0]])
        self.error(line, f"kinematic cycle {names} (through {via})")

    # -- rigid joints --------------------------------------------------------------------------
    def joint(self, joint: Joint) -> None:
        where = f"joint {joint.name!r}"
        line = joint.line
        oline = self.line(("joint", joint.name, "origin"), line)
        if not all(map(math.isfinite, (*joint.origin.xyz, *joint.origin.rpy))):
            self.error(line, f"{where}: origin has a non-finite value")
        else:
            self.rpy(joint.origin.rpy, where, oline)
            self.far(joint.origin.xyz, "origin xyz", where, oline)
        if joint.type in ("revolute", "prismatic") and joint.limit is None:
            self.error(
                line, f"{where}: a {joint.type} joint needs <limit lower upper effort velocity>"
            )
        if joint.limit is not None:
            lim = joint.limit
            lline = self.line(("joint", joint.name, "limit"), line)
            values = (lim.lower, lim.upper, lim.effort, lim.velocity)
            if not all(map(math.isfinite, values)):
                self.error(lline, f"{where}: <limit> has a non-finite value")
            elif lim.lower > lim.upper:
                self.error(lline, f"{where}: limit lower {lim.lower} > upper {lim.upper}")
            elif joint.type == "prismatic":
                self.far((lim.lower, lim.upper), "limit", where, lline)
            elif joint.type == "revolute":
                for attr, value in (("lower", lim.lower), ("upper", lim.upper)):
                    if beyond_a_turn(value):  # -135 for -2.356: degrees for radians
                        self.error(
                            lline,
                            f"{where}: limit {attr} {value:g} is beyond 2*pi: revolute limits are "
                            "radians "
                            + degrees_hint(value, "a joint without bounds is 'continuous'"),
                        )
            if lim.effort < 0 or lim.velocity < 0:
                self.error(lline, f"{where}: limit effort and velocity must be >= 0")
        if joint.type in ("revolute", "continuous", "prismatic", "planar"):
            self.axis(joint, where, self.line(("joint", joint.name, "axis"), line))

    def axis(self, joint: Joint, where: str, line: int) -> None:
        """A joint axis is a direction: finite, not (near) zero, and normalisable by a reader that
        divides by sqrt(x² + y² + z²) (urdfdom, numpy), whose squares must not overflow."""
        axis = joint.axis
        text = " ".join(f"{a:g}" for a in axis)
        if not all(map(math.isfinite, axis)):
            self.error(line, f"{where}: axis ({text}) is not finite")
            return
        norm = math.hypot(*axis)  # scaled: no overflow where the sum of squares has one
        if norm < 1e-12:
            self.error(line, f"{where}: axis ({text}) has no direction (zero length)")
        elif not math.isfinite(math.fsum(a * a for a in axis)):
            unit = " ".join(f"{a / norm:.6g}" for a in axis)
            self.error(
                line,
                f"{where}: axis ({text}) is too long to normalise (its squared length overflows); "
                f"write the unit vector ({unit})",
            )

    def far(self, values: tuple[float, ...], what: str, where: str, line: int) -> bool:
        """A length or position beyond ±MAX_LENGTH_M is reported (once for ``values``); True
        then."""
        for value in values:
            if abs(value) > MAX_LENGTH_M:
                self.error(
                    line,
                    f"{where}: {what} {value:g} m is beyond ±{MAX_LENGTH_M:g} m: no robot is that "
                    "large (a unit mistake?)",
                )
                return True
        return False

    def rpy(self, rpy: tuple[float, float, float], where: str, line: int) -> None:
        """An ``<origin rpy>`` beyond 2*pi is degrees written for radians (like revolute limits
        and tendon angles): refused with the radians to write."""
        for name, value in zip(("roll", "pitch", "yaw"), rpy, strict=True):
            if beyond_a_turn(value):  # 90 instead of 1.571
                self.error(
                    line,
                    f"{where}: origin rpy {name} {value:g} is beyond 2*pi: rpy is radians "
                    f"{degrees_hint(value)}",
                )

    def inertial(self, inertial: Inertial, where: str, line: int, oline: int = 0) -> None:
        mass = inertial.mass
        if not math.isfinite(mass) or mass < 0:
            self.error(line, f"{where}: mass must be a finite value >= 0 kg, got {mass}")
        values = (*inertial.origin.xyz, *inertial.origin.rpy, *inertial.inertia)
        if not all(map(math.isfinite, values)):
            self.error(line, f"{where}: <inertial> has a non-finite origin or inertia value")
            return
        self.rpy(inertial.origin.rpy, f"{where}: <inertial>", oline or line)
        self.far(inertial.origin.xyz, "<inertial> origin xyz", where, oline or line)
        problem = inertia_problem(inertial.inertia)
        if problem:
            self.error(line, f"{where}: <inertia> is not physically possible: {problem}")

    # -- bendables -----------------------------------------------------------------------------
    def bendable(self, b: Bendable) -> None:
        key = ("bendable", b.name)
        where = f"bendable {b.name!r}"
        spec = b.model
        oline = self.line((*key, "origin"), b.line)
        if not all(map(math.isfinite, (*b.origin.xyz, *b.origin.rpy))):
            self.error(b.line, f"{where}: origin has a non-finite value")
        else:
            self.rpy(b.origin.rpy, where, oline)
            self.far(b.origin.xyz, "origin xyz", where, oline)
        if b.inertial is not None:
            iline = self.line((*key, "inertial"), b.line)
            self.inertial(b.inertial, where, iline, self.line((*key, "inertial", "origin"), iline))

        sound = True
        bb = spec.backbone
        bline = self.line((*key, "backbone"), b.line)
        if not (math.isfinite(bb.length) and bb.length > 0):
            self.error(bline, f"{where}: backbone length must be > 0 m, got {bb.length}")
            sound = False
        elif self.far((bb.length,), "backbone length", where, bline):
            sound = False
        if not (math.isfinite(bb.radius) and bb.radius >= 0):
            self.error(bline, f"{where}: backbone radius must be >= 0 m, got {bb.radius}")
        else:
            self.far((bb.radius,), "backbone radius", where, bline)
        for attr, unit in (("youngs_modulus", "Pa"), ("bending_stiffness", "N m^2")):
            value = getattr(bb, attr)
            if value is not None and not (math.isfinite(value) and value > 0):
                self.error(bline, f"{where}: backbone {attr} must be > 0 {unit}, got {value}")

        lim = spec.limits
        lline = self.line((*key, "limits"), b.line)
        if not (math.isfinite(lim.kappa_max) and lim.kappa_max > 0):
            self.error(lline, f"{where}: kappa_max must be > 0 1/m, got {lim.kappa_max}")
            sound = False
        elif why := kappa_resolution_problem(lim.kappa_max):
            self.error(lline, f"{where}: kappa_max {why}")
            sound = False
        if lim.kappa_rate_max is not None and not (
            math.isfinite(lim.kappa_rate_max) and lim.kappa_rate_max > 0
        ):
            self.error(
                lline, f"{where}: kappa_rate_max must be > 0 1/m/s, got {lim.kappa_rate_max}"
            )
        elif lim.kappa_rate_max is not None and (
            why := kappa_resolution_problem(lim.kappa_rate_max, "1/m/s")
        ):
            self.error(lline, f"{where}: kappa_rate_max {why}")
        if not (math.isfinite(lim.phi_min) and math.isfinite(lim.phi_max)):
            self.error(lline, f"{where}: phi_min/phi_max must be finite")
            sound = False
        elif lim.phi_min >= lim.phi_max:
            self.error(lline, f"{where}: phi_min {lim.phi_min} must be < phi_max {lim.phi_max}")
            sound = False
        elif lim.phi_min < -math.pi - _PHI_SLACK or lim.phi_max > math.pi + _PHI_SLACK:
            self.error(
                lline,
                f"{where}: phi range [{lim.phi_min}, {lim.phi_max}] rad leaves [-pi, pi] "
                "(phi is the bending-plane angle, reported in (-pi, pi])",
            )
            sound = False
        for name, value in lim.extra.items():
            if not math.isfinite(value):
                self.error(lline, f"{where}: limit {name} must be finite, got {value}")
                sound = False

        if b.actuation is not None:
            self.actuation(b, sound)
        self.model(b, sound)

    def model(self, b: Bendable, sound: bool) -> None:
        key = ("bendable", b.name)
        where = f"bendable {b.name!r}"
        mline = self.line((*key, "model"), b.line)
        try:
            get_model, available = model_registry()
        except LookupError as exc:
            self.error(mline, f"{where}: cannot check model {b.model.type!r}: {exc}")
            return
        names = list(available())
        if b.model.type not in names:
            self.error(
                mline,
                f"{where}: unknown model type {b.model.type!r} (available: {', '.join(names)})",
            )
            return
        try:
            cls = get_model(b.model.type)
        except Exception as exc:  # a third-party plugin failing to load must not crash a check
            self.error(mline, f"{where}: model {b.model.type!r} failed to load: {exc}")
            return
        self.model_classes[b.name] = cls
        known_extra = tuple(getattr(cls, "extra_limits", ()))
        unknown = [name for name in b.model.limits.extra if name not in known_extra]
        if unknown:
            known = ("kappa_max", "kappa_rate_max", "phi_min", "phi_max", *known_extra)
            for name in unknown:
                self.error(
                    self.line((*key, "limits"), mline),
                    f"{where}: unknown <limits> attribute {name!r} for model {b.model.type!r}"
                    f"{_did_you_mean(name, known)} (known: {', '.join(known)})",
                )
            return  # the model would refuse the same limits again
        if not sound:
            return  # the generic range errors above already explain why the model would refuse
        try:
            self.models[b.name] = cls(b.model)
        except ModelError as exc:
            # point at the <param> the message names last ("…, got: name"), else at <limits>
            line = self.line((*key, "limits"), mline)
            text = str(exc)
            named = {
                p: m.start()
                for p in b.model.params
                for m in re.finditer(rf"\b{re.escape(p)}\b", text)
            }
            if named:
                culprit = max(named, key=lambda p: named[p])
                line = self.line((*key, "param", culprit), mline)
            self.error(line, f"{where}: model {b.model.type!r}: {exc}")
        except Exception as exc:  # noqa: BLE001 - plugin bug: report, never traceback
            self.error(
                mline, f"{where}: model {b.model.type!r} failed on these parameters: {exc!r}"
            )

    def actuation(self, b: Bendable, sound: bool) -> None:
        act = b.actuation
        assert act is not None
        key = ("bendable", b.name)
        where = f"bendable {b.name!r}: actuation"
        aline = self.line((*key, "actuation"), b.line)
        if act.type != "tendon":
            self.error(aline, f"{where}: type {act.type!r} is not supported (only 'tendon')")
        if not act.angles:
            self.error(aline, f"{where}: no tendons")
        if (
            act.servos
            and len(act.servos) != len(act.angles)
            and (*key, "servo_reported") not in self.lines  # the parser named the bad <servo>
        ):
            self.error(
                aline,
                f"{where}: {len(act.angles)} tendons but {len(act.servos)} servos "
                "(give one servo per tendon, or none)",
            )
        if not (math.isfinite(act.radius) and act.radius > 0):
            self.error(aline, f"{where}: tendon radius must be > 0 m, got {act.radius}")
        elif sound and act.radius * b.model.limits.kappa_max >= 1.0:
            self.error(
                aline,
                f"{where}: tendon radius {act.radius} m times kappa_max "
                f"{b.model.limits.kappa_max} 1/m is {act.radius * b.model.limits.kappa_max:.3g} "
                ">= 1: the inner tendon would reach zero length before the bend limit",
            )
        if not (math.isfinite(act.spool_radius) and act.spool_radius > 0):
            self.error(aline, f"{where}: spool radius must be > 0 m, got {act.spool_radius}")
        else:
            self.far((act.spool_radius,), "spool radius", where, aline)
        if not act.driver.strip():
            self.error(aline, f"{where}: empty servo driver name")
        elif act.driver not in FIRMWARE_DRIVERS:
            self.error(
                aline,
                f"{where}: unknown servo driver {act.driver!r}"
                f"{_did_you_mean(act.driver, FIRMWARE_DRIVERS)}; the segment firmware knows "
                f"{', '.join(FIRMWARE_DRIVERS)}",
            )
        seen: dict[float, int] = {}
        for i, angle in enumerate(act.angles):
            tline = self.line((*key, "tendon", i), aline)
            if not math.isfinite(angle):
                self.error(tline, f"{where}: tendon {i} angle is not finite")
                continue
            if beyond_a_turn(angle):  # 120 instead of 2.094: degrees given for radians
                self.error(
                    tline,
                    f"{where}: tendon {i} angle {angle:g} is beyond 2*pi: angles are radians "
                    f"{degrees_hint(angle)}",
                )
                continue
            wrapped = round(math.remainder(angle, math.tau), 9)
            if wrapped in seen:
                self.error(
                    tline, f"{where}: tendon {i} sits at the same angle as tendon {seen[wrapped]}"
                )
            seen[wrapped] = i
        pulse_ok = act.driver != "pwm" or self.pwm_pulse(b, aline)
        ids: dict[int, int] = {}
        # spool angle needed to pay out / wind the largest tendon length change, l*d*kappa_max
        travel = None
        if sound and act.radius > 0 and act.spool_radius > 0 and math.isfinite(act.spool_radius):
            lim = b.model.limits.kappa_max
            travel = b.model.backbone.length * act.radius * lim / act.spool_radius
        for i, servo in enumerate(act.servos):
            sline = self.line((*key, "servo", i), aline)
            if servo.direction not in (1, -1):
                self.error(
                    sline, f"{where}: servo {i} direction must be 1 or -1, got {servo.direction}"
                )
            if servo.id < 0:
                self.error(sline, f"{where}: servo {i} id must be >= 0, got {servo.id}")
            if servo.id in ids:
                self.error(
                    sline,
                    f"{where}: servo {i} has the same bus id {servo.id} as servo {ids[servo.id]}",
                )
            ids[servo.id] = i
            values = (servo.zero_offset, servo.min_angle, servo.max_angle)
            if not all(map(math.isfinite, values)):
                self.error(sline, f"{where}: servo {i} has a non-finite angle")
            elif servo.min_angle >= servo.max_angle:
                self.error(
                    sline,
                    f"{where}: servo {i} min_angle {servo.min_angle} must be < max_angle "
                    f"{servo.max_angle} rad",
                )
            elif act.driver == "pwm" and pulse_ok and self.beyond_pulse(b, i, sline):
                pass  # reported: the firmware would saturate there
            elif travel is not None and (
                _below(-travel, servo.min_angle) or _exceeds(travel, servo.max_angle)
            ):
                self.error(
                    sline,
                    f"{where}: servo {i} travel [{servo.min_angle:.4g}, {servo.max_angle:.4g}] rad "
                    f"cannot reach kappa_max: the spool must turn ±{travel:.4g} rad "
                    "(tendon radius * kappa_max * length / spool radius)",
                )
        if sound and act.type == "tendon" and act.angles and act.driver in FIRMWARE_DRIVERS:
            self.firmware(b, aline)

    def pwm_pulse(self, b: Bendable, aline: int) -> bool:
        """The PWM pulse calibration is one the firmware runs (device/servos/pwm.py); False after
        reporting why not."""
        act = b.actuation
        assert act is not None
        p = act.pulse()
        line = self.line(("bendable", b.name, "pwm_pulse"), aline)
        where = f"bendable {b.name!r}: <pwm_pulse>"
        if not all(map(math.isfinite, (p.min_us, p.max_us, p.range))):
            self.error(line, f"{where}: min_us, max_us and range must be finite")
            return False
        if not 0 < p.min_us < p.max_us < PWM_PERIOD_US:
            self.error(
                line,
                f"{where}: need 0 < min_us < max_us < {PWM_PERIOD_US} us, got min_us "
                f"{p.min_us:g}, max_us {p.max_us:g}",
            )
            return False
        if p.max_us - p.min_us > PWM_MAX_SPAN_US:
            self.error(
                line,
                f"{where}: max_us - min_us = {p.max_us - p.min_us:g} us is more than "
                f"{PWM_MAX_SPAN_US} us (pulse widths are microseconds)",
            )
            return False
        if not 0 < p.range <= PWM_MAX_RANGE:
            hint = f" {degrees_hint(p.range)}" if p.range > PWM_MAX_RANGE else ""
            self.error(
                line,
                f"{where}: range {p.range:g} must be > 0 and at most 10*pi rad: it is the raw "
                f"servo angle in radians between min_us and max_us{hint}",
            )
            return False
        return True

    def beyond_pulse(self, b: Bendable, i: int, sline: int) -> bool:
        """Servo ``i``'s declared travel leaves what its PWM pulse range can output (reported);
        the firmware outputs min_us/max_us there and the servo stops short."""
        act = b.actuation
        assert act is not None
        servo = act.servos[i]
        p = act.pulse()
        lo, hi = -p.half - servo.zero_offset, p.half - servo.zero_offset
        if not (_below(servo.min_angle, lo) or _exceeds(servo.max_angle, hi)):
            return False
        declared = "" if act.pwm_pulse is not None else " (the defaults: no <pwm_pulse>)"
        self.error(
            sline,
            f"bendable {b.name!r}: actuation: servo {i} travel [{servo.min_angle:.4g}, "
            f"{servo.max_angle:.4g}] rad leaves its PWM pulse range: {p.min_us:g}..{p.max_us:g} us "
            f"span {p.range:.4g} rad{declared}, i.e. raw ±{p.half:.4g} rad, so from zero_offset "
            f"{servo.zero_offset:g} only [{lo:.4g}, {hi:.4g}] rad is reached (the firmware "
            "saturates there). Declare the servo's real pulse range with <pwm_pulse min_us= "
            "max_us= range=/> in the <actuation>, or narrow min_angle/max_angle",
        )
        return True

    def firmware(self, b: Bendable, aline: int) -> None:
        """Run the firmware's own validation on the segment configuration of ``b``, unless an
        error above already explains the problem."""
        if any(f"bendable {b.name!r}" in d.message for d in self.diagnostics):
            return
        if ("bendable", b.name, "servo_reported") in self.lines:
            return  # the parser reported a bad <servo>, which the firmware would refuse too
        reason = firmware_refusal(segment_config(b))
        if reason is None:
            return
        line = aline
        m = re.search(r"servos\[(\d+)\]", reason)
        if m:
            line = self.line(("bendable", b.name, "servo", int(m.group(1))), aline)
        elif reason.startswith("name "):  # too long for the DESCRIPTOR (device/config.py)
            line = b.line
        self.error(
            line,
            f"bendable {b.name!r}: the segment firmware would refuse this configuration "
            f"(and not move): {reason}",
        )

    # -- ros2_control ----------------------------------------------------------------------------
    def ros2_control(self) -> None:
        robot = self.robot
        names: dict[str, int] = {}
        controlled: dict[str, int] = {}
        for c_index, control in enumerate(robot.ros2_control):
            ckey = ("ros2_control", c_index)
            cline = self.line(ckey, control.line)
            where = f"ros2_control {control.name!r}"
            if control.name in names:
                self.error(
                    cline,
                    f"duplicate ros2_control name {control.name!r} (line {names[control.name]})",
                )
            names[control.name] = cline
            if not control.plugin.strip():
                self.error(self.line((*ckey, "hardware"), cline), f"{where}: empty <plugin>")
            model_name = control.hardware_params.get("model")
            if model_name is not None:
                try:
                    available = model_registry()[1]()
                except LookupError:
                    available = None
                if available is not None and model_name not in available:
                    self.error(
                        self.line((*ckey, "param", "model"), cline),
                        f"{where}: hardware param model={model_name!r} is not a known model "
                        f"(available: {', '.join(available)})",
                    )
                else:
                    self.hardware_model(control, ckey, cline, model_name)
            if control.plugin.strip() == SEGMENT_PLUGIN:
                self.segment_plugin_params(control, ckey, cline)
            flashed: dict[str, int] = {}  # each ms param as the segments would run it
            for pname, (_, _, _, default) in SEGMENT_MS_PARAMS.items():
                if pname not in control.hardware_params:
                    flashed[pname] = default
                    continue
                try:
                    flashed[pname] = segment_ms_param(pname, control.hardware_params[pname])
                except ValueError as exc:
                    self.error(
                        self.line((*ckey, "param", pname), cline),
                        f"{where}: hardware param {exc} (the segments could not run it)",
                    )
            tick = flashed.get("tick_ms")
            dog, hw_dog = flashed.get("watchdog_ms"), flashed.get("hw_watchdog_ms")
            if tick is not None and dog is not None and dog < 2 * tick:
                self.error(
                    self.line((*ckey, "param", "watchdog_ms"), cline),
                    f"{where}: hardware param watchdog_ms {dog} is shorter than two ticks "
                    f"(tick_ms {tick}): the segments check it once per tick",
                )
            if tick is not None and hw_dog and hw_dog < 4 * tick:
                self.error(
                    self.line((*ckey, "param", "hw_watchdog_ms"), cline),
                    f"{where}: hardware param hw_watchdog_ms {hw_dog} is shorter than four ticks "
                    f"(tick_ms {tick}): the segments feed it once per clean tick",
                )
            for pname in control.hardware_params:
                target, sep, _ = pname.rpartition("/")
                if sep and target not in robot.bendables and target not in robot.joints:
                    self.error(
                        self.line((*ckey, "param", pname), cline),
                        f"{where}: hardware param {pname!r} names {target!r}, which is neither "
                        f"a bendable nor a joint (bendables: {_names(robot.bendables)})",
                    )
            for j_index, cjoint in enumerate(control.joints):
                jkey = (*ckey, "joint", j_index)
                jline = self.line(jkey, cjoint.line)
                if cjoint.name in controlled:
                    self.error(
                        jline,
                        f"joint {cjoint.name!r} is claimed by two ros2_control joints "
                        f"(first on line {controlled[cjoint.name]})",
                    )
                controlled.setdefault(cjoint.name, jline)
                self.control_joint(cjoint, jkey, jline)

    def hardware_model(
        self, control: Ros2Control, ckey: LineKey, cline: int, model_name: str
    ) -> None:
        """The hardware ``model`` param must be the model of the bendables it drives (those its
        joints name, else every bendable of the robot)."""
        robot = self.robot
        driven = [j.name for j in control.joints if j.name in robot.bendables] or list(
            robot.bendables
        )
        try:  # a bendable whose own model type is unknown was reported as such (model())
            known = set(model_registry()[1]())
        except LookupError:
            known = None
        other = [
            n
            for n in driven
            if robot.bendables[n].model.type != model_name
            and (known is None or robot.bendables[n].model.type in known)
        ]
        if other:
            types = sorted({robot.bendables[n].model.type for n in other})
            self.error(
                self.line((*ckey, "param", "model"), cline),
                f"ros2_control {control.name!r}: hardware param model={model_name!r} but "
                f"bendable(s) {', '.join(other)} use model {', '.join(map(repr, types))}",
            )

    def segment_plugin_params(self, control: Ros2Control, ckey: LineKey, cline: int) -> None:
        """The ``<hardware>`` params of SoftRobotInterface: known names only, valid values
        (watchdog_ms/tick_ms and model are checked by the caller)."""
        where = f"ros2_control {control.name!r}"
        for pname, value in control.hardware_params.items():
            pline = self.line((*ckey, "param", pname), cline)
            target, sep, what = pname.rpartition("/")
            if sep:
                if what != "uid":
                    self.error(
                        pline,
                        f"{where}: hardware param {pname!r}: {SEGMENT_PLUGIN} knows only "
                        f"'<bendable>/uid' per segment, not '<…>/{what}'",
                    )
                elif target in self.robot.joints:
                    self.error(
                        pline, f"{where}: hardware param {pname!r}: {target!r} is a rigid joint; "
                        "only a bendable (a segment) has a uid"
                    )  # fmt: skip
                elif not value or any(c.isspace() for c in value):
                    self.error(
                        pline,
                        f"{where}: hardware param {pname} must be the segment's unique id "
                        f"(e.g. a4cf12fe0b3c), got {value!r}",
                    )
                continue
            if pname not in SEGMENT_PLUGIN_PARAMS:
                self.error(
                    pline,
                    f"{where}: unknown hardware param {pname!r} for {SEGMENT_PLUGIN}"
                    f"{_did_you_mean(pname, SEGMENT_PLUGIN_PARAMS)} (known: "
                    f"{', '.join(SEGMENT_PLUGIN_PARAMS)}, <bendable>/uid)",
                )
            elif pname == "fault_action" and value not in FAULT_ACTIONS:
                self.error(
                    pline,
                    f"{where}: hardware param fault_action must be one of "
                    f"{', '.join(FAULT_ACTIONS)} (what the servos do in FAULT), got {value!r}",
                )
            elif pname == "port" and (not value or any(c.isspace() for c in value)):
                self.error(
                    pline,
                    f"{where}: hardware param port must be 'auto', a device path or a pyserial "
                    f"URL without spaces, got {value!r}",
                )
            elif pname == "baudrate":
                baud = whole(value)
                if baud is None or baud < MIN_BAUDRATE:
                    self.error(
                        pline,
                        f"{where}: hardware param baudrate must be a whole number of bit/s >= "
                        f"{MIN_BAUDRATE}, got {shown(value)}",
                    )

    def control_joint(self, cjoint: ControlJoint, jkey: LineKey, jline: int) -> None:
        robot = self.robot
        name = cjoint.name
        where = f"ros2_control joint {name!r}"
        if name in robot.bendables:
            bendable = robot.bendables[name]
            cls = self.model_classes.get(name)
            model = self.models.get(name)
            variables = [v.name for v in cls.variables()] if cls is not None else None
            bounds = model.limits() if model is not None else {}
            for kind, iface in self._interfaces(cjoint):
                iline = self.line((*jkey, kind, iface.name), jline)
                if variables is not None and iface.name not in variables:
                    self.error(
                        iline,
                        f"{where}: {kind} {iface.name!r} is not a variable of model "
                        f"{bendable.model.type!r} (variables: {', '.join(variables)})",
                    )
                    continue
                bound = bounds.get(iface.name)
                limit_text = f"the model limits of {iface.name!r}"
                self.interface_params(where, kind, iface, iline, bound, limit_text)
                if kind == "command_interface" and iface.name == "kappa":
                    self.kappa_command_max(where, iface, iline)
            return
        if name in robot.joints:
            joint = robot.joints[name]
            if joint.type == "fixed":
                self.error(jline, f"{where}: joint {name!r} is fixed and has nothing to control")
                return
            for kind, iface in self._interfaces(cjoint):
                iline = self.line((*jkey, kind, iface.name), jline)
                if iface.name not in JOINT_INTERFACES:
                    self.error(
                        iline,
                        f"{where}: {kind} {iface.name!r} is not an interface of a rigid joint"
                        f"{_did_you_mean(iface.name, JOINT_INTERFACES)} (known: "
                        f"{', '.join(JOINT_INTERFACES)})",
                    )
                    continue
                bound = None
                if (
                    iface.name == "position"
                    and joint.limit is not None
                    and joint.type != "continuous"
                ):
                    bound = (joint.limit.lower, joint.limit.upper)
                limit_text = f"the <limit> of joint {name!r}"
                self.interface_params(where, kind, iface, iline, bound, limit_text)
            return
        if any(k[:1] == ("invalid",) and k[2] == name for k in self.lines):
            return  # its joint/bendable was reported invalid and left out: not a second problem
        self.error(
            jline,
            f"{where} names neither a bendable nor a joint "
            f"(bendables: {_names(robot.bendables)}; joints: "
            f"{_names(j.name for j in robot.joints.values() if j.type != 'fixed')})",
        )

    def kappa_command_max(self, where: str, iface: Interface, line: int) -> None:
        """The rule host/limits.py applies to a bendable's kappa command max: > 0 (kappa is a
        magnitude, commanded in [0, max]), and not below the wire's resolution."""
        hi = iface.params.get("max")
        if hi is None or isinstance(hi, str) or not math.isfinite(hi):
            return  # reported by interface_params
        label = f"{where}: command_interface 'kappa'"
        lo = iface.params.get("min")
        if isinstance(lo, (int, float)) and lo > hi:
            return  # min > max: reported by interface_params
        if hi <= 0:
            self.error(line, f"{label}: param max must be > 0 1/m, got {hi}")
        elif why := kappa_resolution_problem(float(hi)):
            self.error(line, f"{label}: param max {why}")
        if isinstance(lo, (int, float)) and math.isfinite(lo) and 0 < lo <= hi:
            self.error(
                line,
                f"{label}: param min {lo:g} 1/m: kappa is a magnitude (commanded in [0, max]); a "
                "minimum above 0 is not supported (the daemon and ucr fk refuse it too)",
            )

    @staticmethod
    def _interfaces(cjoint: ControlJoint) -> list[tuple[str, Interface]]:
        return [("command_interface", i) for i in cjoint.command_interfaces] + [
            ("state_interface", i) for i in cjoint.state_interfaces
        ]

    def interface_params(
        self,
        where: str,
        kind: str,
        iface: Interface,
        line: int,
        bound: tuple[float, float] | None,
        limit_text: str,
    ) -> None:
        label = f"{where}: {kind} {iface.name!r}"
        values: dict[str, float] = {}
        for pname in ("initial_value", "min", "max"):
            if pname not in iface.params:
                continue
            value = iface.params[pname]
            if isinstance(value, str) or not math.isfinite(value):
                got = shown(value) if isinstance(value, str) else repr(value)
                self.error(line, f"{label}: param {pname} must be a finite number, got {got}")
                continue
            values[pname] = float(value)
        lo, hi = values.get("min"), values.get("max")
        if lo is not None and hi is not None and lo > hi:
            self.error(line, f"{label}: min {lo} > max {hi}")
        if bound is not None:
            if lo is not None and _below(lo, bound[0]):
                self.error(
                    line,
                    f"{label}: min {lo} is below {limit_text} [{bound[0]:.6g}, {bound[1]:.6g}]",
                )
            if hi is not None and _exceeds(hi, bound[1]):
                self.error(
                    line, f"{label}: max {hi} exceeds {limit_text} [{bound[0]:.6g}, {bound[1]:.6g}]"
                )
        init = values.get("initial_value")
        if init is not None:
            low = lo if lo is not None else (bound[0] if bound else None)
            high = hi if hi is not None else (bound[1] if bound else None)
            if (low is not None and _below(init, low)) or (
                high is not None and _exceeds(init, high)
            ):
                self.error(
                    line,
                    f"{label}: initial_value {init} lies outside [{low:.6g}, {high:.6g}]"
                    if low is not None and high is not None
                    else f"{label}: initial_value {init} lies outside its bounds",
                )
