"""Serialise a :class:`ucrdf.model.Robot` as U(C)RDF XML.

Numbers are written with ``repr`` (the shortest text that reads back to the same float), so
parse -> write -> parse gives an equal Robot. Defaults are written explicitly where the spec leaves
them implicit (phi range, servo travel) to make a generated file self-describing. Visual, collision
and extension elements are re-inserted from the normalised XML the parser kept.
"""

from __future__ import annotations

import math
from pathlib import Path

from lxml import etree

from ucrdf.model import (
    Actuation,
    Bendable,
    Inertial,
    Interface,
    Joint,
    Link,
    ModelSpec,
    Origin,
    Robot,
    Ros2Control,
)

#: Written into an ``<actuation>`` without ``<servo>`` elements (``ucr flash`` refuses it).
NO_SERVOS_COMMENT = (
    " no <servo> declared: the servo ids, zero offsets, directions and ranges are unknown "
    "(a chain's descriptors do not report them). Add one <servo index= id= zero_offset= direction= "
    "min_angle= max_angle=/> per tendon: `ucr flash` refuses this segment until then "
)


def fmt(value: float) -> str:
    """A float as xs:double text that reads back exactly (INF/-INF/NaN spelt the XSD way)."""
    value = float(value)
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "INF" if value > 0 else "-INF"
    return repr(value)


def _vec(values: tuple[float, ...]) -> str:
    return " ".join(fmt(v) for v in values)


def _value(value: float | str) -> str:
    return value if isinstance(value, str) else fmt(value)


def _sub(parent: etree._Element, tag: str, **attrs: str) -> etree._Element:
    return etree.SubElement(parent, tag, {k: v for k, v in attrs.items()})


def _raw(parent: etree._Element, xml: str) -> None:
    parent.append(etree.fromstring(xml))


def _origin(parent: etree._Element, origin: Origin, always: bool = False) -> None:
    if always or not origin.is_identity():
        _sub(parent, "origin", xyz=_vec(origin.xyz), rpy=_vec(origin.rpy))


def _inertial(parent: etree._Element, inertial: Inertial) -> None:
    el = _sub(parent, "inertial")
    _origin(el, inertial.origin)
    _sub(el, "mass", value=fmt(inertial.mass))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    _sub(el, "inertia", **{n: fmt(v) for n, v in zip(names, inertial.inertia, strict=True)})


def _link(parent: etree._Element, link: Link) -> None:
    el = _sub(parent, "link", name=link.name)
    if link.inertial is not None:
        _inertial(el, link.inertial)
    for geometry in link.geometry:
        _raw(el, geometry.xml)
    for ext in link.extensions:
        _raw(el, ext)


def _joint(parent: etree._Element, joint: Joint) -> None:
    el = _sub(parent, "joint", name=joint.name, type=joint.type)
    _sub(el, "parent", link=joint.parent)
    _sub(el, "child", link=joint.child)
    _origin(el, joint.origin)
    if joint.axis != (1.0, 0.0, 0.0):
        _sub(el, "axis", xyz=_vec(joint.axis))
    if joint.limit is not None:
        lim = joint.limit
        _sub(
            el,
            "limit",
            lower=fmt(lim.lower),
            upper=fmt(lim.upper),
            effort=fmt(lim.effort),
            velocity=fmt(lim.velocity),
        )
    for ext in joint.extensions:
        _raw(el, ext)


def _model(parent: etree._Element, spec: ModelSpec) -> None:
    el = _sub(_sub(parent, "curvature"), "model", type=spec.type)
    for name, value in spec.params.items():
        _sub(el, "param", name=name, value=_value(value))
    lim = spec.limits
    attrs = {"kappa_max": fmt(lim.kappa_max)}
    if lim.kappa_rate_max is not None:
        attrs["kappa_rate_max"] = fmt(lim.kappa_rate_max)
    attrs["phi_min"] = fmt(lim.phi_min)
    attrs["phi_max"] = fmt(lim.phi_max)
    for name, value in lim.extra.items():
        attrs[name] = fmt(value)
    _sub(el, "limits", **attrs)
    bb = spec.backbone
    attrs = {"length": fmt(bb.length), "radius": fmt(bb.radius)}
    if bb.youngs_modulus is not None:
        attrs["youngs_modulus"] = fmt(bb.youngs_modulus)
    if bb.bending_stiffness is not None:
        attrs["bending_stiffness"] = fmt(bb.bending_stiffness)
    _sub(el, "backbone", **attrs)


def _actuation(parent: etree._Element, act: Actuation) -> None:
    el = _sub(
        parent,
        "actuation",
        type=act.type,
        count=str(act.count),
        radius=fmt(act.radius),
        spool_radius=fmt(act.spool_radius),
        driver=act.driver,
    )
    if act.board is not None:
        el.set("board", act.board)
    if not act.servos and act.angles:
        # e.g. a robot composed from a chain's descriptors (``ucr daemon --adopt``), which do
        # not report servo ids or calibration: say what is missing in the file itself
        el.append(etree.Comment(NO_SERVOS_COMMENT))
    for i, angle in enumerate(act.angles):
        _sub(el, "tendon", index=str(i), angle=fmt(angle))
    for i, servo in enumerate(act.servos):
        _sub(
            el,
            "servo",
            index=str(i),
            id=str(servo.id),
            zero_offset=fmt(servo.zero_offset),
            direction=str(servo.direction),
            min_angle=fmt(servo.min_angle),
            max_angle=fmt(servo.max_angle),
        )
    for role, u in act.uarts.items():
        _sub(el, "uart", role=role, **{k: str(v) for k, v in u.items()})
    for i, pin in sorted(act.pwm_pins.items()):
        _sub(el, "pwm", index=str(i), pin=str(pin))
    if act.pwm_pulse is not None:
        p = act.pwm_pulse
        _sub(el, "pwm_pulse", min_us=fmt(p.min_us), max_us=fmt(p.max_us), range=fmt(p.range))


def _bendable(parent: etree._Element, b: Bendable) -> None:
    el = _sub(parent, "bendable", name=b.name)
    _sub(el, "parent", link=b.parent)
    _sub(el, "child", link=b.child)
    _origin(el, b.origin)
    _model(el, b.model)
    if b.inertial is not None:
        _inertial(el, b.inertial)
    if b.actuation is not None:
        _actuation(el, b.actuation)


def _params(parent: etree._Element, params: dict[str, float | str] | dict[str, str]) -> None:
    for name, value in params.items():
        _sub(parent, "param", name=name).text = _value(value)


def _interface(parent: etree._Element, kind: str, iface: Interface) -> None:
    _params(_sub(parent, kind, name=iface.name), iface.params)


def _ros2_control(parent: etree._Element, control: Ros2Control) -> None:
    el = _sub(parent, "ros2_control", name=control.name, type=control.type)
    hardware = _sub(el, "hardware")
    _sub(hardware, "plugin").text = control.plugin
    _params(hardware, control.hardware_params)
    for joint in control.joints:
        jel = _sub(el, "joint", name=joint.name)
        for iface in joint.command_interfaces:
            _interface(jel, "command_interface", iface)
        for iface in joint.state_interfaces:
            _interface(jel, "state_interface", iface)


def split_extensions(extensions: list[str]) -> tuple[list[str], list[str]]:
    """Top-level extensions in document order, cut after the last global ``<material>``: the
    first part goes before the links (URDF readers resolve a visual's ``<material name>`` against
    materials defined earlier), the rest after everything else."""
    cut = 0
    for i, ext in enumerate(extensions):
        if etree.fromstring(ext).tag == "material":
            cut = i + 1
    return extensions[:cut], extensions[cut:]


def to_element(robot: Robot) -> etree._Element:
    """The robot as an lxml element tree (links, joints, bendables, ros2_control, extensions)."""
    root = etree.Element("robot", name=robot.name)
    leading, trailing = split_extensions(robot.extensions)
    for ext in leading:
        _raw(root, ext)
    for link in robot.links.values():
        _link(root, link)
    for joint in robot.joints.values():
        _joint(root, joint)
    for bendable in robot.bendables.values():
        _bendable(root, bendable)
    for control in robot.ros2_control:
        _ros2_control(root, control)
    for ext in trailing:
        _raw(root, ext)
    return root


def dumps(robot: Robot) -> str:
    """The robot as U(C)RDF text (UTF-8, with XML declaration, two-space indentation)."""
    root = to_element(robot)
    etree.indent(root, space="  ")
    body = etree.tostring(root, encoding="unicode")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + body + "\n"


def dump(robot: Robot, path: str | Path) -> None:
    """Write the robot to ``path`` (UTF-8)."""
    Path(path).write_text(dumps(robot), encoding="utf-8")
