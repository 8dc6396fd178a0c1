"""PCC model: the paper's equations, exact straight segments, continuity at kappa -> 0, batching,
analytic Jacobians, limits."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ucrdf.models import create
from ucrdf.models.base import ModelError
from ucrdf.models.pcc import SERIES_T, pcc_functions, pcc_tip_jacobians, pcc_transforms

from .conftest import KAPPA_MAX, SEGMENT_LENGTH, segment_spec

L = SEGMENT_LENGTH
curv = st.floats(-KAPPA_MAX, KAPPA_MAX, allow_nan=False)
angle = st.floats(-math.pi, math.pi, allow_nan=False)


def paper_equations(kappa: float, phi: float, length: float) -> np.ndarray:
    """Equations (2) and (3) of the U(C)RDF paper as printed, with q = kappa*l (the printed
    q = 1/kappa is a typo, see ARCHITECTURE.md)."""
    q = kappa * length
    c, s, cq, sq = math.cos(phi), math.sin(phi), math.cos(q), math.sin(q)
    rot = np.array(
        [
            [c * c * (cq - 1) + 1, s * c * (cq - 1), c * sq],
            [-s * c * (cq - 1), s * s * (cq - 1) + 1, s * sq],
            [-c * sq, -s * sq, cq],
        ]
    )
    pos = (length / q) * np.array([c * (1 - cq), s * (1 - cq), sq])
    return rot, pos


def rz(a):
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def ry(a):
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


@pytest.mark.parametrize("kappa,phi", [(0.5, 0.0), (2.0, 0.7), (3.3, -2.5), (1.0, math.pi)])
def test_matches_paper_equations_and_torsion_free_form(kappa, phi):
    t = pcc_transforms(kappa * math.cos(phi), kappa * math.sin(phi), L)[0]
    rot, pos = paper_equations(kappa, phi, L)
    assert np.allclose(t[:3, 3], pos, atol=1e-14)
    # the torsion-free form Rz(phi) Ry(theta) Rz(-phi) is the rotation we compute
    assert np.allclose(t[:3, :3], rz(phi) @ ry(kappa * L) @ rz(-phi), atol=1e-14)
    # every printed entry of eq. (3) agrees except R[1,0], whose printed sign is a second typo:
    mask = np.ones((3, 3), bool)
    mask[1, 0] = False
    assert np.allclose(t[:3, :3][mask], rot[mask], atol=1e-14)
    assert t[1, 0] == pytest.approx(-rot[1, 0], abs=1e-14)


def test_paper_rotation_as_printed_is_not_a_rotation():
    """Why R[1,0] differs: with the printed sign the matrix is not orthogonal."""
    rot, _ = paper_equations(2.0, 0.7, L)
    assert not np.allclose(rot @ rot.T, np.eye(3), atol=1e-3)


def test_straight_segment_is_exact():
    t = pcc_transforms(0.0, 0.0, L)[0]
    expected = np.eye(4)
    expected[2, 3] = L
    assert np.array_equal(t, expected)
    jv, jw = pcc_tip_jacobians(0.0, 0.0, L)
    assert np.allclose(jv[0], [[L * L / 2, 0], [0, L * L / 2], [0, 0]], atol=0)
    assert np.allclose(jw[0], [[0, -L], [L, 0], [0, 0]], atol=0)


@settings(max_examples=60, deadline=None)
@given(phi=angle, kappa=st.floats(0.0, 1e-3))
def test_continuous_as_kappa_goes_to_zero(phi, kappa):
    """Near straight the transform differs from straight by O(kappa) whatever phi is."""
    t = pcc_transforms(kappa * math.cos(phi), kappa * math.sin(phi), L)[0]
    straight = pcc_transforms(0.0, 0.0, L)[0]
    assert np.abs(t - straight).max() <= 1.01 * kappa * L + 1e-15
    assert np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-15)


def test_series_and_closed_forms_agree_at_the_switch():
    t = np.array([SERIES_T * (1 - 1e-12), SERIES_T * (1 + 1e-12)])
    for f in pcc_functions(t):
        assert f[0] == pytest.approx(f[1], rel=1e-10)


@settings(max_examples=40, deadline=None)
@given(kx=curv, ky=curv)
def test_batched_equals_single_and_model_api(kx, ky):
    batch = pcc_transforms(np.array([kx, 0.1, ky]), np.array([ky, -0.2, kx]), L)
    assert np.array_equal(batch[0], pcc_transforms(kx, ky, L)[0])
    model = create(segment_spec(kappa_max=2 * KAPPA_MAX))
    cfg = model.from_coordinates(np.array([kx, ky]))
    assert np.allclose(model.transform(cfg), batch[0], atol=1e-14)


@settings(max_examples=60, deadline=None)
@given(kx=curv, ky=curv, tiny=st.booleans())
def test_analytic_jacobians_match_finite_differences(kx, ky, tiny):
    if tiny:
        kx, ky = kx * 1e-3, ky * 1e-3
    jv, jw = pcc_tip_jacobians(kx, ky, L)
    h = 1e-6
    t0 = pcc_transforms(kx, ky, L)[0]
    for i, (dx, dy) in enumerate([(h, 0.0), (0.0, h)]):
        tp = pcc_transforms(kx + dx, ky + dy, L)[0]
        tm = pcc_transforms(kx - dx, ky - dy, L)[0]
        dv = (tp[:3, 3] - tm[:3, 3]) / (2 * h)
        dr = (tp[:3, :3] - tm[:3, :3]) / (2 * h) @ t0[:3, :3].T
        dw = 0.5 * np.array([dr[2, 1] - dr[1, 2], dr[0, 2] - dr[2, 0], dr[1, 0] - dr[0, 1]])
        assert np.allclose(jv[0][:, i], dv, atol=1e-8)
        assert np.allclose(jw[0][:, i], dw, atol=1e-8)


def test_transform_at_arc_length_and_backbone():
    model = create(segment_spec())
    cfg = {"kappa": 3.0, "phi": 1.0}
    assert np.allclose(model.transform(cfg, L), model.transform(cfg))
    half = model.transform(cfg, L / 2)
    assert np.allclose(half @ half, model.transform(cfg), atol=1e-14)  # constant curvature
    pts = model.backbone_curve(cfg, 11)
    assert pts.shape == (11, 3)
    assert np.allclose(pts[0], 0) and np.allclose(pts[-1], model.transform(cfg)[:3, 3])
    # every sample lies on the circle of radius 1/kappa around the bending centre
    centre = np.array([math.cos(1.0), math.sin(1.0), 0.0]) / 3.0
    assert np.allclose(np.linalg.norm(pts - centre, axis=1), 1 / 3.0)


def test_config_checks_name_the_problem():
    model = create(segment_spec())
    with pytest.raises(ModelError, match="kappa = 5 1/m is outside its limits"):
        model.transform({"kappa": 5.0})
    with pytest.raises(ModelError, match="unknown variable"):
        model.transform({"curvature": 1.0})
    with pytest.raises(ModelError, match="must be a number"):
        model.transform({"kappa": "x"})
    assert model.check_config({"phi": 3 * math.pi})["phi"] == pytest.approx(math.pi)


def test_validate_rejects_bad_specs():
    with pytest.raises(ModelError, match="exceeds the PCC bound of pi"):
        create(segment_spec(kappa_max=1.01 * math.pi / L))
    create(segment_spec(kappa_max=math.pi / L))  # exactly a half circle is allowed
    with pytest.raises(ModelError, match="takes no <param>"):
        create(segment_spec(params={"steps": 3}))
    with pytest.raises(ModelError, match="backbone length"):
        create(segment_spec(length=0.0))


def test_projection_respects_disc_and_phi_sector():
    spec = segment_spec()
    spec.limits.phi_min, spec.limits.phi_max = 0.0, math.pi / 2
    model = create(spec)
    kx, ky = model.project(np.array([10.0, 0.0]))
    assert math.hypot(kx, ky) == pytest.approx(KAPPA_MAX)
    kx, ky = model.project(np.array([-1.0, -0.1]))  # phi = -174 deg: 96 deg from 90, 174 from 0
    assert math.atan2(ky, kx) == pytest.approx(math.pi / 2)
    assert math.hypot(kx, ky) == pytest.approx(math.hypot(1.0, 0.1))
