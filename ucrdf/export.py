"""Export a U(C)RDF robot to plain URDF for tools that only know rigid joints (RViz, yourdfpy).

Each bendable ``<b>`` of length l becomes a pseudo-rigid-body (PRB) chain of N subdivisions of
length h = l/N:

    parent --[h/2]--> U_0 --[h]--> U_1 --[h]--> ... U_{N-1} --[h/2]--> twist --> child

U_k is a universal joint, two revolute joints ``<b>_prb<k>_rx`` (about x) then ``<b>_prb<k>_ry``
(about y; the link between them is ``<b>_prb<k>_cross``, the link after them ``<b>_prb<k>``),
sitting at the middle of subdivision k. The straight link after U_k stands for the chord between
the middles of subdivisions k and k+1, whose direction is the backbone tangent at s = (k+1)h; U_k
is therefore set so that the chain's z axis equals that tangent. Two joints cannot also follow the
(zero) torsion exactly, so a last joint ``<b>_prb_twist`` about z (after the fixed ``<b>_prb_end``
and link ``<b>_prb_end_link``) removes the residual roll and the child link frame gets exactly the
model's tip orientation; its position converges as O(1/N^2) (docs/kinematics.md gives figures).

``export_urdf(robot, N)`` writes movable joints (zero = straight); :func:`urdf_joint_positions`
gives their values for a configuration. ``export_urdf(robot, N, config)`` bakes the configuration
into fixed joints instead (a static snapshot). Rigid joints, links, inertials, visuals and
collisions are copied. A bendable's mass is spread evenly over its subdivision links, each with
its centre of mass at the subdivision's middle and 1/N of the segment's inertia tensor (an
approximation, good for display and rough dynamics). Generated names that clash with the robot's
own links or joints are refused with a clear error.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from lxml import etree

from ucrdf.fk import Config, ConfigError, RobotKinematics, joint_motion
from ucrdf.model import Inertial, Origin, Robot
from ucrdf.models.base import CurvatureModel


def _fmt(x: float) -> str:
    return repr(float(x)) if x != 0 else "0"


def _vec(v) -> str:
    return " ".join(_fmt(x) for x in v)


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(b: float) -> np.ndarray:
    c, s = math.cos(b), math.sin(b)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rpy(r: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw of a rotation (R = Rz(y) Ry(p) Rx(r))."""
    pitch = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-12:
        roll = math.atan2(r[2, 1], r[2, 2])
        yaw = math.atan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: put everything in yaw
        roll = 0.0
        yaw = math.atan2(-r[0, 1], r[1, 1])
    return roll, pitch, yaw


def subdivision_angles(
    model: CurvatureModel, q: np.ndarray, subdivisions: int
) -> tuple[list[tuple[float, float]], float]:
    """Universal-joint angles (about x, about y) per subdivision and the final twist (rad) that
    make the chain follow the model's backbone for coordinates ``q``."""
    n = subdivisions
    h = model.length / n
    r_chain = np.eye(3)
    angles: list[tuple[float, float]] = []
    for k in range(n):
        r_true = model.transform_coordinates(q, (k + 1) * h)[:3, :3]
        z = r_chain.T @ r_true[:, 2]
        b = math.asin(max(-1.0, min(1.0, float(z[0]))))
        a = math.atan2(-float(z[1]), float(z[2]))
        angles.append((a, b))
        r_chain = r_chain @ _rot_x(a) @ _rot_y(b)
    r_rel = r_chain.T @ model.transform_coordinates(q)[:3, :3]
    twist = math.atan2(r_rel[1, 0], r_rel[0, 0])
    return angles, twist


def urdf_joint_positions(
    robot: Robot | RobotKinematics, subdivisions: int, config: Config | None = None
) -> dict[str, float]:
    """Positions of every movable joint of ``export_urdf(robot, subdivisions)`` for ``config``
    (rad / m): the pseudo-rigid-body joints of each bendable and the robot's own rigid joints."""
    _check_subdivisions(subdivisions)
    kin = robot if isinstance(robot, RobotKinematics) else RobotKinematics(robot)
    coords, joints = kin.coordinates(config)
    out: dict[str, float] = dict(joints)
    for name, model in kin.models.items():
        angles, twist = subdivision_angles(model, coords[name], subdivisions)
        for k, (a, b) in enumerate(angles):
            out[f"{name}_prb{k}_rx"] = a
            out[f"{name}_prb{k}_ry"] = b
        out[f"{name}_prb_twist"] = twist
    return out


def _check_subdivisions(subdivisions: int) -> None:
    if isinstance(subdivisions, bool) or not isinstance(subdivisions, int) or subdivisions < 1:
        raise ConfigError(f"subdivisions must be an integer >= 1, got {subdivisions!r}")


def _origin_el(parent: etree._Element, xyz, rpy=(0.0, 0.0, 0.0)) -> None:
    etree.SubElement(parent, "origin", xyz=_vec(xyz), rpy=_vec(rpy))


def _inertial_el(
    parent: etree._Element, inertial: Inertial, scale: float = 1.0, at_frame: bool = False
) -> None:
    """Copy of ``inertial`` with mass and inertia times ``scale``; ``at_frame`` puts the centre
    of mass at the link frame (used for the subdivisions of a bendable)."""
    el = etree.SubElement(parent, "inertial")
    if at_frame:
        _origin_el(el, (0.0, 0.0, 0.0), inertial.origin.rpy)
    else:
        _origin_el(el, inertial.origin.xyz, inertial.origin.rpy)
    etree.SubElement(el, "mass", value=_fmt(inertial.mass * scale))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    etree.SubElement(
        el, "inertia", {k: _fmt(v * scale) for k, v in zip(names, inertial.inertia, strict=True)}
    )


def _joint_el(
    root, name, jtype, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), axis=None, limit=None
):
    el = etree.SubElement(root, "joint", name=name, type=jtype)
    _origin_el(el, xyz, rpy)
    etree.SubElement(el, "parent", link=parent)
    etree.SubElement(el, "child", link=child)
    if axis is not None:
        etree.SubElement(el, "axis", xyz=_vec(axis))
    if limit is not None:
        etree.SubElement(el, "limit", {k: _fmt(v) for k, v in limit.items()})
    return el


def export_urdf(robot: Robot, subdivisions: int, config: Config | None = None) -> str:
    """Plain URDF text of ``robot`` with every bendable as a ``subdivisions``-part pseudo-rigid
    chain: movable revolute joints when ``config`` is None, else fixed joints posed at it."""
    _check_subdivisions(subdivisions)
    kin = RobotKinematics(robot)
    baked = config is not None
    coords, _ = kin.coordinates(config) if baked else ({}, {})
    root = etree.Element("robot", name=robot.name)
    root.append(etree.Comment(
        f" exported from U(C)RDF by ucrdf.export: {subdivisions} subdivisions per bendable, "
        + ("fixed pose " if baked else "movable universal joints ") + "(see docs/kinematics.md) "
    ))  # fmt: skip
    for link in robot.links.values():
        el = etree.SubElement(root, "link", name=link.name)
        if link.inertial is not None:
            _inertial_el(el, link.inertial)
        for geom in link.geometry:
            el.append(etree.fromstring(geom.xml))
    for joint in robot.joints.values():
        limit = None
        if joint.limit is not None:
            lim = joint.limit
            limit = {"lower": lim.lower, "upper": lim.upper, "effort": lim.effort,
                     "velocity": lim.velocity}  # fmt: skip
        axis = joint.axis if joint.type not in ("fixed",) else None
        _joint_el(root, joint.name, joint.type, joint.parent, joint.child, joint.origin.xyz,
                  joint.origin.rpy, axis, limit)  # fmt: skip
    taken = set(robot.links) | set(robot.joints)
    for b in robot.bendables.values():
        made = {f"{b.name}_prb_{x}" for x in ("end_link", "end", "twist")}
        for k in range(subdivisions):
            made |= {f"{b.name}_prb{k}_cross", f"{b.name}_prb{k}", f"{b.name}_prb{k}_rx",
                     f"{b.name}_prb{k}_ry"}  # fmt: skip
        clash = sorted(made & taken)
        if clash:
            raise ConfigError(
                f"cannot export bendable {b.name!r}: generated name(s) {', '.join(clash)} already "
                "used by a link or joint of the robot"
            )
        taken |= made
    for b in robot.bendables.values():
        model = kin.models[b.name]
        n = subdivisions
        h = model.length / n
        if baked:
            angles, twist = subdivision_angles(model, coords[b.name], n)
        else:
            angles, twist = [(0.0, 0.0)] * n, 0.0
        amax = b.model.limits.kappa_max * h * (1.0 + 1e-6) + 1e-9
        radius = b.model.backbone.radius
        parent = b.parent
        base = b.origin.matrix() @ Origin((0.0, 0.0, h / 2)).matrix()
        xyz, rpy = tuple(base[:3, 3]), _rpy(base[:3, :3])
        for k, (a, bb) in enumerate(angles):
            mid = f"{b.name}_prb{k}_cross"
            sub = f"{b.name}_prb{k}"
            etree.SubElement(root, "link", name=mid)
            sub_el = etree.SubElement(root, "link", name=sub)
            if b.inertial is not None:
                _inertial_el(sub_el, b.inertial, 1.0 / n, at_frame=True)
            if radius > 0.0:
                vis = etree.SubElement(sub_el, "visual")
                _origin_el(vis, (0.0, 0.0, 0.0))
                geo = etree.SubElement(vis, "geometry")
                etree.SubElement(geo, "cylinder", radius=_fmt(radius), length=_fmt(h))
            if baked:
                r_x = (base[:3, :3] if k == 0 else np.eye(3)) @ _rot_x(a)
                _joint_el(root, f"{b.name}_prb{k}_rx", "fixed", parent, mid, xyz, _rpy(r_x))
                _joint_el(root, f"{b.name}_prb{k}_ry", "fixed", mid, sub, rpy=_rpy(_rot_y(bb)))
            else:
                lim = {"lower": -amax, "upper": amax, "effort": 0.0, "velocity": 0.0}
                _joint_el(root, f"{b.name}_prb{k}_rx", "revolute", parent, mid, xyz,
                          rpy if k == 0 else (0.0, 0.0, 0.0), (1, 0, 0), lim)  # fmt: skip
                _joint_el(
                    root, f"{b.name}_prb{k}_ry", "revolute", mid, sub, axis=(0, 1, 0), limit=lim
                )
            parent = sub
            xyz = (0.0, 0.0, h)
        tw_link = f"{b.name}_prb_end_link"
        etree.SubElement(root, "link", name=tw_link)
        if baked:
            _joint_el(root, f"{b.name}_prb_end", "fixed", parent, tw_link, (0.0, 0.0, h / 2))
            _joint_el(root, f"{b.name}_prb_twist", "fixed", tw_link, b.child, rpy=(0.0, 0.0, twist))
        else:
            _joint_el(root, f"{b.name}_prb_end", "fixed", parent, tw_link, (0.0, 0.0, h / 2))
            _joint_el(root, f"{b.name}_prb_twist", "continuous", tw_link, b.child, axis=(0, 0, 1))
    return etree.tostring(root, pretty_print=True, xml_declaration=True, encoding="utf-8").decode()


def exported_tip_error(
    robot: Robot, subdivisions: int, config: Mapping | None = None
) -> dict[str, float]:
    """Position error (m) of every original link frame of the movable export posed at ``config``
    against the exact FK, computed without any URDF library (for tests and docs)."""
    kin = RobotKinematics(robot)
    exact = kin.fk(config)
    q = urdf_joint_positions(kin, subdivisions, config)
    frames = {kin.root: np.eye(4)}
    h_of = {name: m.length / subdivisions for name, m in kin.models.items()}
    _, joints = kin.coordinates(config)
    for el in kin.order:
        t = frames[el.parent] @ el.origin
        if el.kind == "joint":
            t = t @ joint_motion(el, joints.get(el.name, 0.0))
        else:
            h = h_of[el.name]
            t = t @ Origin((0.0, 0.0, h / 2)).matrix()
            for k in range(subdivisions):
                r = np.eye(4)
                r[:3, :3] = _rot_x(q[f"{el.name}_prb{k}_rx"]) @ _rot_y(q[f"{el.name}_prb{k}_ry"])
                t = t @ r
                step = np.eye(4)
                step[2, 3] = h if k < subdivisions - 1 else h / 2
                t = t @ step
            tw = np.eye(4)
            c, s = math.cos(q[f"{el.name}_prb_twist"]), math.sin(q[f"{el.name}_prb_twist"])
            tw[:2, :2] = [[c, -s], [s, c]]
            t = t @ tw
        frames[el.child] = t
    return {name: float(np.linalg.norm(frames[name][:3, 3] - exact[name][:3, 3])) for name in exact}
