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
into fixed joints instead (a static snapshot): the pseudo-rigid joints of every bendable and every
movable rigid joint (at its configured value, else its initial value / 0). N is 1..1000.

The rigid part is copied whole: links (inertial, visuals, collisions, extension children), joints
(origin, axis, limit, calibration, dynamics, mimic, safety_controller, extension children) and the
top-level extensions (global materials, gazebo, transmission, any other) in document order, the
part up to the last global material before the links. The bendables are replaced by their chains;
the ``<ros2_control>`` blocks are not written. What cannot be carried over is named in a warning
(``warn``, stderr by default), never dropped silently: a ``<mimic>`` of a joint the baked export
fixes. An extension that refers to a bendable by name is kept, with a warning.

Physics (:func:`distribute_inertial`): a bendable's mass is split evenly over its N subdivision
links so that, in the straight pose, their total mass, centre of mass and inertia about it equal
the segment's exactly. Limits of the pseudo-rigid joints: velocity = kappa_rate_max times the
largest rate of that joint's angle per unit curvature-vector rate (:func:`joint_rate_gains`, about
h = l/N since a subdivision bends by kappa * h), effort = EI * kappa_max (the backbone's bending
moment at full bend, the same at every joint of a constant-curvature arc) for the rx/ry joints
and the twist joint alike (the model has no torsion bound of its own; 0 would be a real limit of
0 for ros2_control). 0 when the U(C)RDF lacks the rate limit or the stiffness: ros2_control reads
that as a real limit of 0 too (docs/kinematics.md, "Joint limits"). Generated names that clash
with the robot's own links or joints are refused with a clear error.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Mapping

import numpy as np
from lxml import etree

from ucrdf.fk import Config, ConfigError, RobotKinematics, joint_motion
from ucrdf.model import Inertial, Origin, Robot
from ucrdf.models.base import CurvatureModel
from ucrdf.models.pcc import PCCModel, pcc_transforms
from ucrdf.writer import split_extensions


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


def frames_along(model: CurvatureModel, q: np.ndarray, s_values) -> np.ndarray:
    """(len(s_values), 4, 4) base -> arc length s transforms for model coordinates ``q``: one
    batched call for PCC, the model's own ``transform_coordinates`` otherwise."""
    if type(model) is PCCModel:
        return pcc_transforms(float(q[0]), float(q[1]), np.asarray(s_values, dtype=float))
    return np.array([model.transform_coordinates(q, float(s)) for s in s_values])


def subdivision_angles(
    model: CurvatureModel, q: np.ndarray, subdivisions: int
) -> tuple[list[tuple[float, float]], float]:
    """Universal-joint angles (about x, about y) per subdivision and the final twist (rad) that
    make the chain follow the model's backbone for coordinates ``q``."""
    n = subdivisions
    h = model.length / n
    r_chain = np.eye(3)
    angles: list[tuple[float, float]] = []
    along = frames_along(model, q, [(k + 1) * h for k in range(n)])
    for k in range(n):
        r_true = along[k][:3, :3]
        z = r_chain.T @ r_true[:, 2]
        b = math.asin(max(-1.0, min(1.0, float(z[0]))))
        a = math.atan2(-float(z[1]), float(z[2]))
        angles.append((a, b))
        r_chain = r_chain @ _rot_x(a) @ _rot_y(b)
    r_rel = r_chain.T @ along[-1][:3, :3]  # s = n*h: the tip
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


def _tensor(i) -> np.ndarray:
    ixx, ixy, ixz, iyy, iyz, izz = i
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]], dtype=float)


#: Rounding slack of the inertia split, relative to the largest principal moment of the tensors
#: involved (the segment's I_c and the spread J): a tensor sum of that size is exact to ~1e-16.
_INERTIA_RTOL = 1e-12


def _largest_moment(i: np.ndarray) -> float:
    return float(np.abs(np.linalg.eigvalsh(i)).max())


def _physical(i: np.ndarray, scale: float) -> bool:
    """An inertia tensor a rigid body can have: symmetric, eigenvalues >= 0 and each at most the
    sum of the other two (triangle inequality), up to _INERTIA_RTOL times ``scale`` (the largest
    principal moment of the tensors ``i`` was computed from: never an absolute slack, which would
    accept -1e-13 kg m^2 for a tensor whose moments are 1e-13)."""
    eig = np.linalg.eigvalsh(i)
    tol = _INERTIA_RTOL * scale
    return bool(eig.min() >= -tol and eig.max() <= eig.sum() - eig.max() + tol)


def _clamp_psd(i: np.ndarray) -> np.ndarray:
    """``i`` with every principal moment below _INERTIA_RTOL times the largest (negative ones come
    from rounding, or from the INERTIA_SLACK the U(C)RDF check allows) raised to that floor, so
    that an eigensolver reading the written tensor back (its own rounding is ~1e-16 of the largest
    moment) still finds every moment >= 0; unchanged when none is below it (and the zero tensor
    stays 0). The diagonal of the result, sums of lambda_k v_jk^2 >= 0, is >= 0 too."""
    eig, vec = np.linalg.eigh(i)
    floor = _INERTIA_RTOL * float(np.abs(eig).max())
    if eig.min() >= floor:
        return i
    out = (vec * np.maximum(eig, floor)) @ vec.T
    return (out + out.T) / 2.0


def distribute_inertial(
    inertial: Inertial, length: float, subdivisions: int
) -> list[tuple[tuple[float, float, float], np.ndarray]]:
    """Centre of mass (m) and inertia about it (kg m^2, 3x3), both in the segment's base frame
    in the straight pose, of each of the ``subdivisions`` links (each of mass m/N).

    Link k's centre of mass is c + s * (z_k - l/2) e_z, with c the segment's centre of mass and
    z_k = (k + 1/2) h the middle of subdivision k: they average to c. Their spread adds
    J = s^2 * m h^2 (N^2 - 1)/12 to the inertia about x and y (parallel axes), so each link gets
    (I_c - J)/N about its own centre of mass and the sum is I_c exactly. s = 1 (point masses
    where the subdivisions are) unless I_c - J would not be a physical inertia (a segment thinner
    in its inertia than its own length implies): then s shrinks until it is (s = 0 is always).
    "Physical" is judged with a slack relative to the tensors (_INERTIA_RTOL), and a principal
    moment left negative by rounding is raised to a floor of _INERTIA_RTOL times the largest
    (:func:`_clamp_psd`), so every link's moments and diagonal are >= 0 (a segment with a mass but
    no inertia gives s = 0 and links of inertia exactly 0)."""
    n = subdivisions
    m = inertial.mass
    c = np.array(inertial.origin.xyz, dtype=float)
    r = inertial.origin.matrix()[:3, :3]
    i_c = r @ _tensor(inertial.inertia) @ r.T
    h = length / n
    spread = np.array([(k + 0.5) * h - length / 2 for k in range(n)])
    lateral = np.diag([1.0, 1.0, 0.0])
    j_full = m * h * h * (n * n - 1) / 12.0 * lateral
    i_c = (i_c + i_c.T) / 2.0
    scale_c = _largest_moment(i_c)
    scale_j = _largest_moment(j_full)
    s = 1.0
    for _ in range(60):
        if _physical(i_c - s * s * j_full, max(scale_c, s * s * scale_j)):
            break
        s *= 0.5
    else:
        s = 0.0
    own = (i_c - s * s * j_full) / n
    own = _clamp_psd((own + own.T) / 2.0)
    return [(c + s * dz * np.array([0.0, 0.0, 1.0]), own) for dz in spread]


def joint_rate_gains(
    model: CurvatureModel, kappa_max: float, subdivisions: int
) -> tuple[float, float]:
    """Largest rate of any universal-joint angle and of the twist (rad/s) per unit rate of the
    curvature vector (1/m/s), sampled over the disc |(kx, ky)| <= kappa_max (central differences,
    4 radii x 16 directions) with a 2 % margin. About h for the joints (x1.05 at N = 10, x1.64 at
    N = 1 near a 60 deg bend: the two axes of a universal joint share the bend unevenly)."""
    n = subdivisions
    eps = 1e-6 * max(kappa_max, 1.0)
    g_joint = g_twist = 0.0
    dim = len(model.coordinate_names())

    def angles(q: np.ndarray) -> tuple[np.ndarray, float]:
        ab, tw = subdivision_angles(model, q, n)
        return np.array(ab, dtype=float).ravel(), tw

    for radius in (0.0, 0.5 * kappa_max, 0.85 * kappa_max, kappa_max - eps):
        for phi in np.linspace(0.0, 2.0 * math.pi, 16, endpoint=False):
            q0 = np.zeros(dim)  # PCC: (kx, ky); other models: the curvature vector first
            q0[:2] = radius * math.cos(phi), radius * math.sin(phi)
            dj, dt = [], []
            for axis in np.eye(dim) * eps:
                (ja, ta), (jb, tb) = angles(q0 + axis), angles(q0 - axis)
                dj.append((ja - jb) / (2 * eps))
                dt.append((ta - tb) / (2 * eps))
            g_joint = max(g_joint, float(np.sqrt(np.sum(np.square(dj), axis=0)).max()))
            g_twist = max(g_twist, float(np.linalg.norm(dt)))
    return 1.02 * g_joint, 1.02 * g_twist


#: Most subdivisions per bendable: the tip error is already ~0.06 mm at 32 (O(1/N^2)), and each
#: subdivision adds 2 links and 2 joints, so more only makes huge files and long runs.
MAX_SUBDIVISIONS = 1000


def _check_subdivisions(subdivisions: int) -> None:
    if (
        isinstance(subdivisions, bool)
        or not isinstance(subdivisions, int)
        or not 1 <= subdivisions <= MAX_SUBDIVISIONS
    ):
        raise ConfigError(
            f"subdivisions must be an integer in 1..{MAX_SUBDIVISIONS}, got {subdivisions!r}"
        )


def _origin_el(parent: etree._Element, xyz, rpy=(0.0, 0.0, 0.0)) -> None:
    etree.SubElement(parent, "origin", xyz=_vec(xyz), rpy=_vec(rpy))


def _inertial_el(parent: etree._Element, inertial: Inertial) -> None:
    """Copy of a rigid link's ``inertial``."""
    el = etree.SubElement(parent, "inertial")
    _origin_el(el, inertial.origin.xyz, inertial.origin.rpy)
    etree.SubElement(el, "mass", value=_fmt(inertial.mass))
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    etree.SubElement(
        el, "inertia", {k: _fmt(v) for k, v in zip(names, inertial.inertia, strict=True)}
    )


def _sub_inertial_el(
    parent: etree._Element, mass: float, com: np.ndarray, inertia: np.ndarray
) -> None:
    """``<inertial>`` of one subdivision link (its frame is parallel to the segment base)."""
    el = etree.SubElement(parent, "inertial")
    _origin_el(el, com)
    etree.SubElement(el, "mass", value=_fmt(mass))
    i = inertia
    values = (i[0, 0], i[0, 1], i[0, 2], i[1, 1], i[1, 2], i[2, 2])
    names = ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")
    etree.SubElement(el, "inertia", {k: _fmt(v) for k, v in zip(names, values, strict=True)})


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


def _stderr_warning(message: str) -> None:
    print(f"warning: URDF export: {message}", file=sys.stderr)


def _bendable_references(xml: str, robot: Robot) -> list[str]:
    """Bendables a top-level extension names as a ``reference`` (gazebo) or ``<joint name>``
    (transmission): the plain URDF has no link or joint of that name."""
    el = etree.fromstring(xml)
    names = [el.get("reference"), *(j.get("name") for j in el.iter("joint"))]
    return sorted({name for name in names if name in robot.bendables})


def export_urdf(
    robot: Robot,
    subdivisions: int,
    config: Config | None = None,
    *,
    warn: Callable[[str], None] = _stderr_warning,
) -> str:
    """Plain URDF text of ``robot`` with every bendable as a ``subdivisions``-part pseudo-rigid
    chain: movable revolute joints when ``config`` is None, else fixed joints posed at it.
    ``warn`` gets one line per element that could not be carried over as it was."""
    _check_subdivisions(subdivisions)
    kin = RobotKinematics(robot)
    baked = config is not None
    coords, positions = kin.coordinates(config) if baked else ({}, {})
    root = etree.Element("robot", name=robot.name)
    root.append(etree.Comment(
        f" exported from U(C)RDF by ucrdf.export: {subdivisions} subdivisions per bendable, "
        + ("fixed pose " if baked else "movable universal joints ") + "(see docs/kinematics.md) "
    ))  # fmt: skip
    leading, trailing = split_extensions(robot.extensions)
    for xml in robot.extensions:
        for name in _bendable_references(xml, robot):
            tag = etree.QName(etree.fromstring(xml)).localname
            warn(
                f"top-level <{tag}> refers to bendable {name!r}, which the plain URDF replaces by "
                f"the joints {name}_prb…: copied unchanged, it names nothing there"
            )
    for xml in leading:
        root.append(etree.fromstring(xml))
    for link in robot.links.values():
        el = etree.SubElement(root, "link", name=link.name)
        if link.inertial is not None:
            _inertial_el(el, link.inertial)
        for xml in [g.xml for g in link.geometry] + link.extensions:
            el.append(etree.fromstring(xml))
    for joint in robot.joints.values():
        extensions = joint.extensions
        if baked and joint.name in positions:  # a movable joint posed at its configured value
            el = kin.elements[joint.name]
            t = el.origin @ joint_motion(el, positions[joint.name])
            jel = _joint_el(root, joint.name, "fixed", joint.parent, joint.child, tuple(t[:3, 3]),
                            _rpy(t[:3, :3]))  # fmt: skip
            mimic = kin.mimics.get(joint.name)
            if mimic is not None:  # a fixed joint follows nothing: its position is baked in
                extensions = [x for x in extensions if etree.fromstring(x).tag != "mimic"]
                warn(
                    f"joint {joint.name!r}: <mimic joint={mimic.joint!r}> not carried over: the "
                    f"fixed pose bakes its position ({positions[joint.name]:g}) into a fixed joint"
                )
        else:
            limit = None
            if joint.limit is not None:
                lim = joint.limit
                limit = {"lower": lim.lower, "upper": lim.upper, "effort": lim.effort,
                         "velocity": lim.velocity}  # fmt: skip
            axis = joint.axis if joint.type not in ("fixed",) else None
            jel = _joint_el(root, joint.name, joint.type, joint.parent, joint.child,
                            joint.origin.xyz, joint.origin.rpy, axis, limit)  # fmt: skip
        for xml in extensions:  # calibration, dynamics, mimic, safety_controller, namespaced
            jel.append(etree.fromstring(xml))
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
    gains: dict[tuple[str, int], tuple[float, float]] = {}
    for b in robot.bendables.values():
        model = kin.models[b.name]
        n = subdivisions
        h = model.length / n
        if baked:
            angles, twist = subdivision_angles(model, coords[b.name], n)
        else:
            angles, twist = [(0.0, 0.0)] * n, 0.0
        lims = b.model.limits
        amax = lims.kappa_max * h * (1.0 + 1e-6) + 1e-9
        rate = lims.kappa_rate_max or 0.0
        key = (repr(b.model), n)
        if key not in gains:  # identical segments share the sampling
            gains[key] = joint_rate_gains(model, lims.kappa_max, n) if rate else (0.0, 0.0)
        g_joint, g_twist = gains[key]
        ei = b.model.backbone.stiffness() or 0.0
        effort = ei * lims.kappa_max
        parts = distribute_inertial(b.inertial, model.length, n) if b.inertial else None
        radius = b.model.backbone.radius
        parent = b.parent
        base = b.origin.matrix() @ Origin((0.0, 0.0, h / 2)).matrix()
        xyz, rpy = tuple(base[:3, 3]), _rpy(base[:3, :3])
        for k, (a, bb) in enumerate(angles):
            mid = f"{b.name}_prb{k}_cross"
            sub = f"{b.name}_prb{k}"
            etree.SubElement(root, "link", name=mid)
            sub_el = etree.SubElement(root, "link", name=sub)
            if parts is not None:
                com, inertia = parts[k]
                z_k = (k + 0.5) * h  # the link frame's place along the straight segment
                _sub_inertial_el(sub_el, b.inertial.mass / n, com - (0.0, 0.0, z_k), inertia)
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
                lim = {"lower": -amax, "upper": amax, "effort": effort, "velocity": rate * g_joint}
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
            _joint_el(root, f"{b.name}_prb_twist", "continuous", tw_link, b.child, axis=(0, 0, 1),
                      limit={"effort": effort, "velocity": rate * g_twist})  # fmt: skip
    for xml in trailing:
        root.append(etree.fromstring(xml))
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
