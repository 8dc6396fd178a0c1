"""URDF export physics: in the straight pose the exported links of a bendable carry exactly the
segment's mass, centre of mass and inertia about it; joint limits come from the U(C)RDF's rate
limits and backbone stiffness. Read back through yourdfpy (a URDF parser nobody here wrote)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import yourdfpy

from ucrdf.checks import inertia_problem
from ucrdf.export import distribute_inertial, export_urdf, subdivision_angles
from ucrdf.fk import RobotKinematics
from ucrdf.model import Inertial, Origin
from ucrdf.parser import load as load_ucrdf

from .conftest import ROBOTS_DIR, chain_robot


def _rpy_matrix(rpy) -> np.ndarray:
    return Origin((0.0, 0.0, 0.0), tuple(rpy)).matrix()[:3, :3]


def _tensor(i) -> np.ndarray:
    ixx, ixy, ixz, iyy, iyz, izz = i
    return np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])


def _exported_mass_properties(urdf: yourdfpy.URDF, links, base_world: np.ndarray):
    """Total mass, centre of mass and inertia about it of ``links`` at the zero configuration,
    in the frame ``base_world`` (4x4 in the URDF root frame)."""
    inv = np.linalg.inv(base_world)
    parts = []
    for name in links:
        inertial = urdf.link_map[name].inertial
        t = inv @ urdf.get_transform(name, urdf.base_link) @ inertial.origin
        parts.append((inertial.mass, t[:3, 3], t[:3, :3] @ inertial.inertia @ t[:3, :3].T))
    mass = sum(m for m, _, _ in parts)
    com = sum(m * p for m, p, _ in parts) / mass
    inertia = np.zeros((3, 3))
    for m, p, i in parts:
        d = p - com
        inertia += i + m * (d @ d * np.eye(3) - np.outer(d, d))
    return mass, com, inertia


def _check_segment(tmp_path, robot, n: int) -> None:
    path = tmp_path / f"{robot.name}_{n}.urdf"
    path.write_text(export_urdf(robot, n))
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    urdf.update_cfg(np.zeros(len(urdf.actuated_joint_names)))
    for b in robot.bendables.values():
        links = [f"{b.name}_prb{k}" for k in range(n)]
        base = urdf.get_transform(b.parent, urdf.base_link) @ b.origin.matrix()
        mass, com, inertia = _exported_mass_properties(urdf, links, base)
        want_r = _rpy_matrix(b.inertial.origin.rpy)
        want_i = want_r @ _tensor(b.inertial.inertia) @ want_r.T
        assert mass == pytest.approx(b.inertial.mass, rel=1e-6)
        scale = np.linalg.norm(b.inertial.origin.xyz) or 1.0
        assert np.linalg.norm(com - np.array(b.inertial.origin.xyz)) <= 1e-6 * scale
        assert np.abs(inertia - want_i).max() <= 1e-6 * np.abs(want_i).max(), (inertia, want_i)


@pytest.mark.parametrize("n", [1, 2, 10])
def test_exported_links_carry_the_segment_mass_com_and_inertia(tmp_path, n):
    """Fails on the old export: each link carried 1/N of the segment's inertia about its own
    frame, so the chain's inertia about the centre of mass was +84 % off for N = 10."""
    _check_segment(tmp_path, load_ucrdf(ROBOTS_DIR / "softrobot3.ucrdf"), n)


def test_off_axis_rotated_inertial_is_preserved(tmp_path):
    """A centre of mass off the backbone and an inertia given in a rotated frame (products of
    inertia) survive the distribution exactly."""
    robot = chain_robot(2)
    for b in robot.bendables.values():
        b.inertial = Inertial(
            mass=0.4,
            origin=Origin((0.01, -0.02, 0.12), (0.3, -0.2, 0.7)),
            inertia=(0.004, 0.0001, -0.0002, 0.0035, 0.00015, 0.0012),
        )
    _check_segment(tmp_path, robot, 8)


def test_thin_segment_inertia_falls_back_to_a_physical_split(tmp_path):
    """A segment whose own inertia is smaller than the spread of point masses along it would
    need a negative link inertia; the export narrows the spread instead and stays exact."""
    robot = chain_robot(1)
    b = next(iter(robot.bendables.values()))
    b.inertial = Inertial(mass=0.3, origin=Origin((0.0, 0.0, b.model.backbone.length / 2)),
                          inertia=(1e-6, 0.0, 0.0, 1e-6, 0.0, 1e-7))  # fmt: skip
    _check_segment(tmp_path, robot, 10)
    text = export_urdf(robot, 10)
    urdf_path = tmp_path / "thin.urdf"
    urdf_path.write_text(text)
    urdf = yourdfpy.URDF.load(str(urdf_path), load_meshes=False)
    for k in range(10):
        eig = np.linalg.eigvalsh(urdf.link_map[f"{b.name}_prb{k}"].inertial.inertia)
        assert eig.min() >= -1e-15
        assert eig.max() <= eig.sum() - eig.max() + 1e-12  # triangle inequality


def _check_no_negative_moment(urdf: yourdfpy.URDF, robot, n: int) -> None:
    """Every subdivision link: principal moments and written diagonal >= 0, accepted by the
    U(C)RDF inertia check; the chain keeps the segment's mass, centre of mass and inertia."""
    for b in robot.bendables.values():
        links = [f"{b.name}_prb{k}" for k in range(n)]
        for name in links:
            i = urdf.link_map[name].inertial.inertia
            assert np.linalg.eigvalsh(i).min() >= 0.0, (name, i)
            assert np.diag(i).min() >= 0.0, (name, i)
            assert inertia_problem((i[0, 0], i[0, 1], i[0, 2], i[1, 1], i[1, 2], i[2, 2])) is None
        base = urdf.get_transform(b.parent, urdf.base_link) @ b.origin.matrix()
        mass, com, inertia = _exported_mass_properties(urdf, links, base)
        want_r = _rpy_matrix(b.inertial.origin.rpy)
        want_i = want_r @ _tensor(b.inertial.inertia) @ want_r.T
        length = b.model.backbone.length
        assert mass == pytest.approx(b.inertial.mass, rel=1e-9)
        assert np.linalg.norm(com - np.array(b.inertial.origin.xyz)) <= 1e-9 * length
        # a point-mass segment (inertia 0) can only be compared on the scale of a thin rod
        scale = max(np.abs(want_i).max(), 1e-9 * b.inertial.mass * length**2)
        assert np.abs(inertia - want_i).max() <= 1e-6 * scale, (inertia, want_i)


@pytest.mark.parametrize("n", [2, 3, 10, 100])
def test_mass_without_inertia_exports_no_negative_moment(tmp_path, n):
    """Fails on the old export: robots/listing1.ucrdf gives the segment a mass but no inertia,
    the absolute 1e-12 slack of the physicality test stopped the halving of the spread early and
    every link was written with ixx = iyy = -4.3e-14 (N = 3), which Drake and MuJoCo refuse."""
    robot = load_ucrdf(ROBOTS_DIR / "listing1.ucrdf")
    path = tmp_path / "listing1.urdf"
    path.write_text(export_urdf(robot, n))
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    urdf.update_cfg(np.zeros(len(urdf.actuated_joint_names)))
    _check_no_negative_moment(urdf, robot, n)


@pytest.mark.parametrize(
    "inertia",
    [
        (1e-14, 0.0, 0.0, 1e-14, 0.0, 1e-15),  # far thinner than its own length implies
        (2e-13, 1e-14, 0.0, 3e-13, 0.0, 1e-13),
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    ],
)
def test_tiny_inertia_splits_without_negative_moment(inertia):
    """Fails on the old split: a slack of 1e-12 kg m^2 is not small next to a tensor of 1e-13,
    so the spread stopped shrinking while I_c - J was still negative."""
    inertial = Inertial(mass=0.3, origin=Origin((0.0, 0.0, 0.158), (0.2, -0.1, 0.4)),
                        inertia=inertia)  # fmt: skip
    for n in (2, 10, 64):
        parts = distribute_inertial(inertial, 0.316, n)
        for _, i in parts:
            assert np.linalg.eigvalsh(i).min() >= 0.0, (n, i)
            assert np.diag(i).min() >= 0.0, (n, i)
        c = np.mean([p for p, _ in parts], axis=0)
        assert np.linalg.norm(c - inertial.origin.xyz) <= 1e-12
        total = sum(i + 0.3 / n * ((p - c) @ (p - c) * np.eye(3) - np.outer(p - c, p - c))
                    for p, i in parts)  # fmt: skip
        r = _rpy_matrix(inertial.origin.rpy)
        want = r @ _tensor(inertia) @ r.T
        assert np.abs(total - want).max() <= 1e-6 * max(np.abs(want).max(), 1e-20), (n, total)


def _ros2_control_limits(limit) -> dict[str, float | bool]:
    """What ros2_control's joint_limits::getJointLimits(urdf::JointConstSharedPtr, JointLimits&)
    (joint_limits/include/joint_limits/joint_limits_urdf.hpp) makes of a URDF <limit>: velocity
    and effort limits are always "given", with max = |value| (0 is a real limit of 0)."""
    return {
        "has_velocity_limits": True,
        "max_velocity": abs(limit.velocity),
        "has_effort_limits": True,
        "max_effort": abs(limit.effort),
    }


@pytest.mark.parametrize("n", [1, 10])
def test_twist_joint_gets_a_real_effort_limit(tmp_path, n):
    """Fails on the old export: the twist joint was written with effort="0", which ros2_control
    loads as has_effort_limits = true, max_effort = 0 (every effort command clamped to 0). It now
    gets the segment's moment bound EI * kappa_max, like the rx/ry joints, and a velocity > 0."""
    robot = load_ucrdf(ROBOTS_DIR / "softrobot3.ucrdf")
    path = tmp_path / "twist.urdf"
    path.write_text(export_urdf(robot, n))
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    for b in robot.bendables.values():
        want = b.model.backbone.stiffness() * b.model.limits.kappa_max
        joint = urdf.joint_map[f"{b.name}_prb_twist"]
        assert joint.type == "continuous"
        got = _ros2_control_limits(joint.limit)
        rx = _ros2_control_limits(urdf.joint_map[f"{b.name}_prb0_rx"].limit)
        assert got["max_effort"] == pytest.approx(want, rel=1e-12) == rx["max_effort"]
        assert got["max_effort"] > 0 and got["max_velocity"] > 0


@pytest.mark.parametrize("n", [1, 10])
def test_exported_joint_limits_follow_rate_limit_and_backbone_stiffness(tmp_path, n):
    """Velocity limits bound every joint's rate while the curvature vector moves at
    kappa_rate_max in any direction (checked here on a denser grid than the export samples);
    effort is the backbone's bending moment at kappa_max."""
    robot = load_ucrdf(ROBOTS_DIR / "softrobot3.ucrdf")
    kin = RobotKinematics(robot)
    path = tmp_path / "limits.urdf"
    path.write_text(export_urdf(robot, n))
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    for b in robot.bendables.values():
        h = b.model.backbone.length / n
        lim = b.model.limits
        ei = b.model.backbone.stiffness()
        model = kin.models[b.name]
        worst_joint = worst_twist = 0.0
        eps = 1e-7
        for radius in np.linspace(0.0, lim.kappa_max - 1e-6, 5):
            for phi in np.linspace(0.0, 2 * math.pi, 29):
                q = np.array([radius * math.cos(phi), radius * math.sin(phi)])
                for d in (np.array([eps, 0.0]), np.array([0.0, eps])):
                    a1, t1 = subdivision_angles(model, q + d, n)
                    a0, t0 = subdivision_angles(model, q - d, n)
                    rate = lim.kappa_rate_max / (2 * eps)
                    worst_joint = max(worst_joint, np.abs(np.subtract(a1, a0)).max() * rate)
                    worst_twist = max(worst_twist, abs(t1 - t0) * rate)
        for k in range(n):
            for axis in ("rx", "ry"):
                jl = urdf.joint_map[f"{b.name}_prb{k}_{axis}"].limit
                assert worst_joint <= jl.velocity <= 1.7 * lim.kappa_rate_max * h
                assert jl.effort == pytest.approx(ei * lim.kappa_max, rel=1e-12)
                assert jl.effort > 0
        twist = urdf.joint_map[f"{b.name}_prb_twist"].limit
        assert twist is not None and worst_twist <= twist.velocity


def test_segment_without_rate_limit_or_stiffness_exports_zero_meaning_unknown(tmp_path):
    """The export writes 0 only when the U(C)RDF gives nothing (ros2_control reads it as a real
    limit of 0, docs/kinematics.md says so); the twist joint then gets the same 0 effort."""
    robot = chain_robot(1)
    b = next(iter(robot.bendables.values()))
    b.model = dataclasses.replace(
        b.model,
        limits=dataclasses.replace(b.model.limits, kappa_rate_max=None),
        backbone=dataclasses.replace(b.model.backbone, youngs_modulus=None),
    )
    text = export_urdf(robot, 3)
    assert f'name="{b.name}_prb0_rx"' in text
    path = tmp_path / "none.urdf"
    path.write_text(text)
    urdf = yourdfpy.URDF.load(str(path), load_meshes=False)
    jl = urdf.joint_map[f"{b.name}_prb0_rx"].limit
    assert jl.velocity == 0.0 and jl.effort == 0.0
    tw = urdf.joint_map[f"{b.name}_prb_twist"].limit
    assert tw.velocity == 0.0 and tw.effort == 0.0
    assert math.isfinite(jl.lower) and jl.lower < 0 < jl.upper
