"""Tendon mapping: configuration <-> tendon lengths, both directions and round trips."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from ucrdf.models.base import ModelError
from ucrdf.tendons import COLLINEAR_TOL, TendonMap, curvature_from_lengths, tendon_lengths

from .conftest import KAPPA_MAX, chain_robot

THREE = [0.0, 2 * math.pi / 3, 4 * math.pi / 3]


def test_lengths_follow_the_convention():
    """Bending towards +x (phi = 0) shortens the tendon at sigma = 0 and lengthens the others."""
    lengths = tendon_lengths(2.0, 0.0, 0.316, THREE, 0.06)
    assert lengths[0] == pytest.approx(0.316 * (1 - 0.06 * 2.0))
    assert lengths[1] == pytest.approx(0.316 * (1 + 0.06 * 1.0))
    assert lengths[2] == pytest.approx(lengths[1])
    tmap = TendonMap(0.316, THREE, 0.06)
    assert np.allclose(tmap.lengths_polar(2.0, 0.0), lengths)
    assert np.allclose(tmap.lengths(0.0, 0.0), 0.316)


@settings(max_examples=80, deadline=None)
@given(
    kappa=st.floats(0.0, KAPPA_MAX),
    phi=st.floats(-math.pi, math.pi),
    angles=st.lists(st.floats(0.0, 2 * math.pi), min_size=2, max_size=6),
)
def test_round_trip_configuration_lengths_configuration(kappa, phi, angles):
    spread = np.linalg.det(np.array([[math.cos(a), math.sin(a)] for a in angles]).T
                           @ np.array([[math.cos(a), math.sin(a)] for a in angles]))  # fmt: skip
    if spread / len(angles) ** 2 < COLLINEAR_TOL:
        with pytest.raises(ModelError, match="collinear"):
            TendonMap(0.316, angles, 0.05)
        return
    assume(spread / len(angles) ** 2 > 1e-3)  # nearly collinear sets amplify round-off
    tmap = TendonMap(0.316, angles, 0.05)
    kx, ky = kappa * math.cos(phi), kappa * math.sin(phi)
    lengths = tmap.lengths(kx, ky)
    bx, by = tmap.curvature(lengths)
    assert bx == pytest.approx(kx, abs=1e-9) and by == pytest.approx(ky, abs=1e-9)
    assert tmap.residual(lengths) < 1e-12


@settings(max_examples=40, deadline=None)
@given(lengths=st.lists(st.floats(0.25, 0.35), min_size=3, max_size=3))
def test_round_trip_lengths_curvature_lengths_is_a_projection(lengths):
    """Arbitrary (inconsistent) lengths map to the least-squares curvature; mapping that back and
    forth again changes nothing (the fit is idempotent)."""
    tmap = TendonMap(0.316, THREE, 0.06)
    kx, ky = tmap.curvature(lengths)
    fitted = tmap.lengths(kx, ky)
    assert np.allclose(tmap.curvature(fitted), (kx, ky), atol=1e-9)
    # the residual of the fit is orthogonal to the curvature directions
    assert np.allclose(tmap.directions.T @ (fitted - np.array(lengths)), 0.0, atol=1e-12)


def test_two_tendons_at_right_angles_suffice():
    assert curvature_from_lengths(
        tendon_lengths(1.0, -2.0, 0.3, [0.0, math.pi / 2], 0.04), 0.3, [0.0, math.pi / 2], 0.04
    ) == pytest.approx((1.0, -2.0))


@pytest.mark.parametrize(
    "angles,match",
    [([0.0], "at least 2 tendons"), ([0.0, math.pi], "collinear"), ([1.0, 1.0, 1.0], "collinear")],
)
def test_underdetermined_tendon_sets_are_rejected(angles, match):
    with pytest.raises(ModelError, match=match):
        TendonMap(0.316, angles, 0.06)


def test_bad_inputs_are_rejected():
    tmap = TendonMap(0.316, THREE, 0.06)
    with pytest.raises(ModelError, match="expected 3 tendon lengths"):
        tmap.curvature([0.3, 0.3])
    with pytest.raises(ModelError, match="finite"):
        tmap.curvature([0.3, float("nan"), 0.3])
    with pytest.raises(ModelError, match="radius"):
        TendonMap(0.316, THREE, 0.0)


def test_map_from_a_bendable():
    robot = chain_robot(1)
    tmap = TendonMap.for_bendable(robot.bendables["seg1"])
    assert tmap.radius == 0.06 and len(tmap.angles) == 3
    robot.bendables["seg1"].actuation = None
    with pytest.raises(ModelError, match="no tendon actuation"):
        TendonMap.for_bendable(robot.bendables["seg1"])
