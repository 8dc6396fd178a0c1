"""Robot forward kinematics: transforms of every link frame for a configuration.

A configuration maps each bendable name to its model variables (``{"kappa": 1/m, "phi": rad}`` for
PCC) and each movable rigid joint name to its position (rad or m). Anything left out takes the
``initial_value`` of its ``<ros2_control>`` interface when declared, else the model variable's
default (0 for joints). Values are checked against the effective limits (ucrdf/limits.py): the
model's ``<limits>`` (a joint's ``<limit>``) narrowed by its ``<ros2_control>`` command interface
``min``/``max``, the bounds the daemon enforces. A joint with a URDF ``<mimic joint multiplier
offset>`` follows its master (position = multiplier * master + offset) and takes no value of its
own. Transforms are 4x4 numpy arrays in the root link frame.

:class:`RobotKinematics` precomputes the tree, the constant origin matrices and one model instance
per bendable, so repeated calls (the host's state publisher runs FK at 100+ Hz) only evaluate the
variable parts.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from lxml import etree

from ucrdf.limits import command_bounds, narrow_curvature, narrow_interval
from ucrdf.model import Joint, Robot
from ucrdf.models import create
from ucrdf.models.base import LIMIT_SLACK, CurvatureModel, ModelError
from ucrdf.models.pcc import PCCModel, pcc_transforms
from ucrdf.numtext import number

Config = Mapping[str, "Mapping[str, float] | float"]


class ConfigError(ModelError):
    """A configuration given to FK/IK names something unknown or holds a bad value."""


def axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (rad) about the unit vector ``axis`` (Rodrigues)."""
    x, y, z = axis
    c, s = math.cos(angle), math.sin(angle)
    v = 1.0 - c
    return np.array(
        [
            [c + x * x * v, x * y * v - z * s, x * z * v + y * s],
            [y * x * v + z * s, c + y * y * v, y * z * v - x * s],
            [z * x * v - y * s, z * y * v + x * s, c + z * z * v],
        ]
    )


@dataclass
class Element:
    """One edge of the kinematic tree: a rigid joint or a bendable, with its constant origin."""

    kind: str  # "joint" or "bendable"
    name: str
    parent: str
    child: str
    origin: np.ndarray  # 4x4
    joint_type: str = "fixed"  # for joints
    axis: np.ndarray | None = None  # unit axis, joints only
    lower: float = -math.inf
    upper: float = math.inf
    model: CurvatureModel | None = None  # bendables only


@dataclass(frozen=True)
class Mimic:
    """A joint's URDF ``<mimic joint multiplier offset>``: it follows ``joint``, its master."""

    joint: str
    multiplier: float = 1.0
    offset: float = 0.0

    def position(self, master: float) -> float:
        """The mimic joint's position (rad or m) for its master's position."""
        return self.multiplier * master + self.offset


def _mimic(joint: Joint) -> Mimic | None:
    """The ``<mimic>`` the parser kept among the joint's extension children, if any."""
    found = [etree.fromstring(x) for x in joint.extensions if x.startswith("<mimic")]
    found = [el for el in found if el.tag == "mimic"]
    if not found:
        return None
    where = f"joint {joint.name!r}: <mimic>"
    if len(found) > 1:
        raise ModelError(f"joint {joint.name!r} has more than one <mimic>")
    master = found[0].get("joint")
    if not master:
        raise ModelError(f"{where} needs a joint attribute naming the joint it follows")
    numbers = []
    for attr, default in (("multiplier", 1.0), ("offset", 0.0)):
        text = found[0].get(attr)
        value = default if text is None else number(text)  # the schema's spelling only
        if value is None or not math.isfinite(value):
            raise ModelError(f"{where} {attr} must be a finite number, got {text!r}")
        numbers.append(value)
    return Mimic(master, *numbers)


def mimics(robot: Robot) -> tuple[dict[str, Mimic], list[tuple[str, str]]]:
    """Every usable ``<mimic>`` (a movable joint following another movable joint, which follows
    nobody itself) and the problems of the others, as (joint name, message): FK refuses the
    first, ``ucr check`` reports each at its joint (ucrdf/checks.py), one rule for both."""
    out: dict[str, Mimic] = {}
    problems: list[tuple[str, str]] = []
    for j in robot.joints.values():
        try:
            mimic = _mimic(j)
        except ModelError as exc:
            problems.append((j.name, str(exc)))
            continue
        if mimic is None:
            continue
        where = f"joint {j.name!r}: <mimic joint={mimic.joint!r}>"
        master = robot.joints.get(mimic.joint)
        if j.type not in _MOVABLE:
            why = f"{where}: a {j.type} joint has no position to take from another"
        elif master is None:
            what = "a bendable" if mimic.joint in robot.bendables else "nothing in the robot"
            why = f"{where} names {what}: a joint can mimic a movable joint only"
        elif master.name == j.name:
            why = f"{where}: a joint cannot mimic itself"
        elif master.type not in _MOVABLE:
            why = f"{where} names a {master.type} joint, which does not move"
        else:
            out[j.name] = mimic
            continue
        problems.append((j.name, why))
    for name, mimic in list(out.items()):
        if mimic.joint in out:
            problems.append((name, (
                f"joint {name!r}: <mimic joint={mimic.joint!r}> names a joint that mimics "
                f"{out[mimic.joint].joint!r} itself: a chain of mimic joints is not supported"
            )))  # fmt: skip
    for name, _ in problems:
        out.pop(name, None)
    return out, problems


def joint_motion(el: Element, q: float) -> np.ndarray:
    t = np.eye(4)
    if el.joint_type in ("revolute", "continuous"):
        t[:3, :3] = axis_rotation(el.axis, q)
    elif el.joint_type == "prismatic":
        t[:3, 3] = el.axis * q
    return t


class RobotKinematics:
    """Precomputed kinematic tree of a robot; ModelError if a model or the tree is unusable."""

    def __init__(self, robot: Robot):
        self.robot = robot
        try:
            self.root = robot.root_link()
        except ValueError as exc:
            raise ModelError(str(exc)) from None
        self.models: dict[str, CurvatureModel] = {}
        # narrowed by the command interfaces: the model / joint bounds as the file gives them
        self._file_models: dict[str, CurvatureModel] = {}
        self._file_bounds: dict[str, tuple[float, float]] = {}
        #: bendable -> variable -> (lower, upper) for variables other than kappa/phi whose command
        #: interface narrows the model's bounds (kappa and phi are narrowed in the model itself)
        self.variable_bounds: dict[str, dict[str, tuple[float, float]]] = {}
        bounds = command_bounds(robot)
        children: dict[str, list[Element]] = {}
        for b in robot.bendables.values():
            own = bounds.get(b.name, {})
            try:
                model = create(b.model)  # valid as the file gives it ...
                limits = narrow_curvature(b.model.limits, own)
                if limits != b.model.limits:  # ... and bounded as the daemon bounds it
                    self._file_models[b.name] = model
                    model = create(replace(b.model, limits=limits))
                for var, declared in own.items():
                    if var in ("kappa", "phi") or var not in _var_names(model):
                        continue
                    lo, hi = model.limits().get(var, (-math.inf, math.inf))
                    narrowed = narrow_interval(lo, hi, declared)
                    if narrowed != (lo, hi):
                        self.variable_bounds.setdefault(b.name, {})[var] = narrowed
            except ModelError as exc:
                raise ModelError(f"bendable {b.name!r}: {exc}") from None
            self.models[b.name] = model
            el = Element("bendable", b.name, b.parent, b.child, b.origin.matrix(), model=model)
            children.setdefault(b.parent, []).append(el)
        for j in robot.joints.values():
            el = self._joint_element(j)
            position = bounds.get(j.name, {}).get("position")
            if position is not None and el.joint_type in _MOVABLE:
                try:
                    lo, hi = narrow_interval(el.lower, el.upper, position)
                except ModelError as exc:
                    raise ModelError(f"joint {j.name!r}: {exc}") from None
                if (lo, hi) != (el.lower, el.upper):
                    self._file_bounds[j.name] = (el.lower, el.upper)
                    el.lower, el.upper = lo, hi
            children.setdefault(j.parent, []).append(el)
        #: mimic joint -> its <mimic>
        self.mimics = self._mimics(robot)
        # breadth-first order from the root: parents always before children
        self.order: list[Element] = []
        seen = {self.root}
        frontier = [self.root]
        while frontier:
            nxt = []
            for link in frontier:
                for el in children.get(link, []):
                    if el.child in seen:
                        raise ModelError(
                            f"{el.kind} {el.name!r} closes a loop at link {el.child!r}"
                        )
                    seen.add(el.child)
                    self.order.append(el)
                    nxt.append(el.child)
            frontier = nxt
        missing = [name for name in robot.links if name not in seen]
        if missing:
            raise ModelError(f"links not connected to root {self.root!r}: {', '.join(missing)}")
        self.elements = {el.name: el for el in self.order}
        self.by_child = {el.child: el for el in self.order}
        self.movable_joints = [
            el.name for el in self.order if el.kind == "joint" and el.joint_type in _MOVABLE
        ]
        self.defaults = self._initial_values()
        self._pcc = [n for n, m in self.models.items() if type(m) is PCCModel]
        self._pcc_len = np.array([self.models[n].length for n in self._pcc])

    @staticmethod
    def _mimics(robot: Robot) -> dict[str, Mimic]:
        """Every ``<mimic>``, checked (:func:`mimics`); ModelError for the first problem."""
        out, problems = mimics(robot)
        if problems:
            raise ModelError(problems[0][1])
        return out

    @staticmethod
    def _joint_element(j: Joint) -> Element:
        axis = np.asarray(j.axis, dtype=float)
        lower, upper = -math.inf, math.inf
        if j.type in _MOVABLE:
            norm = float(np.linalg.norm(axis))
            if not norm > 0.0:
                raise ModelError(f"joint {j.name!r} has a zero axis")
            axis = axis / norm
            if j.type != "continuous" and j.limit is not None:
                lower, upper = j.limit.lower, j.limit.upper
        return Element(
            "joint", j.name, j.parent, j.child, j.origin.matrix(), j.type, axis, lower, upper
        )

    def _initial_values(self) -> dict[str, dict[str, float]]:
        """Per bendable/joint: variable -> initial_value declared in <ros2_control> (command
        interfaces win over state interfaces)."""
        out: dict[str, dict[str, float]] = {}
        for rc in self.robot.ros2_control:
            for cj in rc.joints:
                for iface in list(cj.state_interfaces) + list(cj.command_interfaces):
                    value = iface.params.get("initial_value")
                    if isinstance(value, (int, float)):
                        var = iface.name.rsplit("/", 1)[-1]
                        out.setdefault(cj.name, {})[var] = float(value)
        return out

    # -- configuration ---------------------------------------------------------------------------
    def resolve(
        self, config: Config | None = None, *, strict: bool = True
    ) -> tuple[dict[str, dict[str, float]], dict[str, float]]:
        """Complete configuration: (bendable -> model variables, movable joint -> position,
        mimic joints included, each at its master's position times multiplier plus offset).

        Unknown names, a value for a mimic joint, non-numbers and (when ``strict``) values outside
        the effective limits raise ConfigError; missing entries take initial values / defaults."""
        config = config or {}
        if not isinstance(config, Mapping):
            raise ConfigError("configuration must be an object mapping names to values")
        for name in config:
            mimic = self.mimics.get(name)
            if mimic is not None:
                raise ConfigError(
                    f"joint {name!r} mimics {mimic.joint!r} (position = {mimic.multiplier:g} * "
                    f"{mimic.joint} + {mimic.offset:g}) and takes no value of its own: give "
                    f"{mimic.joint!r}"
                )
        unknown = [k for k in config if k not in self.models and k not in self.movable_joints]
        if unknown:
            fixed = [k for k in unknown if k in self.elements]
            if fixed:
                raise ConfigError(f"joint {fixed[0]!r} is not movable and takes no value")
            raise ConfigError(
                f"unknown name(s) in configuration: {', '.join(map(repr, unknown))} "
                f"(bendables: {', '.join(self.models) or '-'}; "
                f"movable joints: {', '.join(self.movable_joints) or '-'})"
            )
        bend: dict[str, dict[str, float]] = {}
        for name, model in self.models.items():
            given = config.get(name, {})
            if not isinstance(given, Mapping):
                raise ConfigError(
                    f"bendable {name!r} needs an object of variables "
                    f"({', '.join(v.name for v in model.variables())}), got {given!r}"
                )
            merged = {**self.defaults.get(name, {}), **given}
            merged = {k: v for k, v in merged.items() if k in given or k in _var_names(model)}
            try:
                if strict:
                    bend[name] = model.check_config(merged)
                    self.check_variable_bounds(name, bend[name])
                else:
                    unknown_vars = sorted(set(given) - _var_names(model))
                    if unknown_vars:
                        raise ModelError(f"unknown variable(s) {', '.join(unknown_vars)}")
                    bend[name] = {
                        v.name: _finite(merged.get(v.name, v.default), v.name)
                        for v in model.variables()
                    }
            except ModelError as exc:
                file_model = self._file_models.get(name)  # did only the interfaces refuse it?
                narrowed = file_model is not None and _accepts(file_model, merged)
                note = _NARROWED if narrowed and not str(exc).endswith(_NARROWED) else ""
                raise ConfigError(f"bendable {name!r}: {exc}{note}") from None
        values: dict[str, float] = {}
        for name in self.movable_joints:
            if name in self.mimics:
                continue
            default = self.defaults.get(name, {}).get("position", 0.0)
            raw = config.get(name, default)
            if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw):
                raise ConfigError(f"joint {name!r} needs a finite number, got {raw!r}")
            values[name] = float(raw)
        joints: dict[str, float] = {}
        for name in self.movable_joints:
            mimic = self.mimics.get(name)
            value = values[name] if mimic is None else mimic.position(values[mimic.joint])
            if strict:
                el = self.elements[name]
                lo, hi = self._file_bounds.get(name, (math.inf, -math.inf))
                note = _NARROWED if lo <= value <= hi else ""  # only the interfaces refuse it
                if mimic is not None:
                    note = (
                        f" (mimicking {mimic.joint!r}: {mimic.multiplier:g} * "
                        f"{values[mimic.joint]:g} + {mimic.offset:g}){note}"
                    )
                try:
                    _check_bound(f"joint {name!r}", value, el.lower, el.upper, note)
                except ModelError as exc:
                    raise ConfigError(str(exc)) from None
            joints[name] = value
        return bend, joints

    def check_variable_bounds(self, name: str, values: Mapping[str, float]) -> None:
        """ModelError if a variable of bendable ``name`` other than kappa and phi (which its model
        checks) lies outside the bounds of its command interface."""
        for var, (lo, hi) in self.variable_bounds.get(name, {}).items():
            _check_bound(var, values[var], lo, hi, _NARROWED)

    def coordinates(self, config: Config | None = None, *, strict: bool = True):
        """(bendable -> coordinate vector, joint -> position) for a configuration."""
        bend, joints = self.resolve(config, strict=strict)
        return {n: self.models[n].to_coordinates(c) for n, c in bend.items()}, joints

    # -- forward kinematics ----------------------------------------------------------------------
    def fk(self, config: Config | None = None, *, strict: bool = True) -> dict[str, np.ndarray]:
        """4x4 transform (root frame) of every link frame."""
        coords, joints = self.coordinates(config, strict=strict)
        return self.fk_coordinates(coords, joints)

    def fk_coordinates(
        self, coords: Mapping[str, np.ndarray], joints: Mapping[str, float] | None = None
    ) -> dict[str, np.ndarray]:
        """FK from model coordinates (e.g. PCC (kx, ky)) without checks: the fast path."""
        joints = joints or {}
        frames = {self.root: np.eye(4)}
        local: dict[str, np.ndarray] = {}
        if self._pcc:  # every PCC segment in one batched call
            q = np.array([coords[name] for name in self._pcc], dtype=float).reshape(-1, 2)
            for name, t in zip(self._pcc, pcc_transforms(q[:, 0], q[:, 1], self._pcc_len),
                               strict=True):  # fmt: skip
                local[name] = t
        for el in self.order:
            t = frames[el.parent] @ el.origin
            if el.kind == "bendable":
                seg = local.get(el.name)
                if seg is None:
                    seg = el.model.transform_coordinates(coords[el.name])
                t = t @ seg
            elif el.joint_type in _MOVABLE:
                mimic = self.mimics.get(el.name)
                q = (
                    joints.get(el.name, 0.0)
                    if mimic is None
                    else mimic.position(joints.get(mimic.joint, 0.0))
                )
                t = t @ joint_motion(el, q)
            frames[el.child] = t
        return frames

    def backbone_frames(
        self, config: Config | None = None, samples: int = 20, *, strict: bool = True
    ) -> dict[str, np.ndarray]:
        """Per bendable: (samples, 4, 4) frames along its backbone, base to tip, root frame."""
        if samples < 2:
            raise ConfigError(f"samples must be >= 2, got {samples}")
        coords, joints = self.coordinates(config, strict=strict)
        return self.backbone_frames_coordinates(coords, joints, samples)

    def backbone_frames_coordinates(
        self,
        coords: Mapping[str, np.ndarray],
        joints: Mapping[str, float] | None = None,
        samples: int = 20,
        frames: Mapping[str, np.ndarray] | None = None,
    ) -> dict[str, np.ndarray]:
        """Unchecked fast path of :meth:`backbone_frames` from model coordinates; pass ``frames``
        (from :meth:`fk_coordinates` of the same state) to skip recomputing the link frames."""
        if samples < 2:
            raise ConfigError(f"samples must be >= 2, got {samples}")
        if frames is None:
            frames = self.fk_coordinates(coords, joints)
        out: dict[str, np.ndarray] = {}
        for name, model in self.models.items():
            el = self.elements[name]
            base = frames[el.parent] @ el.origin
            arc = np.linspace(0.0, model.length, samples)
            if type(model) is PCCModel:
                q = coords[name]
                local = pcc_transforms(q[0], q[1], arc)
            else:
                local = np.array([model.transform_coordinates(coords[name], s) for s in arc])
            out[name] = base @ local
        return out


_MOVABLE = ("revolute", "continuous", "prismatic")


def _finite(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ModelError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _var_names(model: CurvatureModel) -> set[str]:
    return {v.name for v in model.variables()}


#: Appended to a limit violation that only the command interface bounds make one.
_NARROWED = " (its <ros2_control> command interface bounds, tighter than the model's)"


def _check_bound(label: str, value: float, lo: float, hi: float, note: str = "") -> None:
    """ModelError unless ``value`` lies in [lo, hi] (with LIMIT_SLACK)."""
    slack = LIMIT_SLACK * max(1.0, abs(lo), abs(hi))
    if value < lo - slack or value > hi + slack:
        raise ModelError(f"{label} = {value:g} is outside its limits [{lo:g}, {hi:g}]{note}")


def _accepts(model: CurvatureModel, config: Mapping[str, float]) -> bool:
    try:
        model.check_config(config)
    except ModelError:
        return False
    return True


def robot_fk(robot: Robot, config: Config | None = None) -> dict[str, np.ndarray]:
    """Transforms (4x4, root frame) of every link of ``robot`` for ``config`` (checked)."""
    return RobotKinematics(robot).fk(config)


def bendable_frames(
    robot: Robot, config: Config | None = None, samples: int = 20
) -> dict[str, np.ndarray]:
    """Per bendable: (samples, 4, 4) backbone frames in the root frame, for drawing."""
    return RobotKinematics(robot).backbone_frames(config, samples)
