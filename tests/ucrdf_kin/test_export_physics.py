"""URDF export physics: in the straight pose the exported links of a bendable carry exactly the
segment's mass, centre of mass and inertia about it; joint limits come from the U(C)RDF's rate
limits and backbone stiffness. Read back through yourdfpy (a URDF parser nobody here wrote)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import yourdfpy

from ucrdf.export import export_urdf, subdivision_angles
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
    """URDF reads 0 as 'not given'; the export writes 0 only when the U(C)RDF gives nothing."""
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
    assert math.isfinite(jl.lower) and jl.lower < 0 < jl.upper
