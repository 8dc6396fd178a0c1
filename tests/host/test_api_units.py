"""A phi in degrees in a radian field is refused, never wrapped (commissioning audit
2026-11-26: `phi: 90` in a waypoint was accepted, wrapped and moved the segment to 116.6 deg)."""

from __future__ import annotations

import math

import pytest

from host.api.schema import RequestError, validate_points
from host.client_common import CliError
from host.client_motion import load_trajectory_file


def _point(phi: float) -> list[dict]:
    return [{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1.0, "phi": phi}}}]


@pytest.mark.parametrize("phi", [90.0, -180.0, 2 * math.pi + 1e-6])
def test_a_phi_beyond_a_full_turn_is_refused_with_the_radian_value(phi: float) -> None:
    with pytest.raises(RequestError) as err:
        validate_points(_point(phi))
    assert "phi is in rad" in str(err.value) and f"{math.radians(phi):.4f} rad" in str(err.value)


@pytest.mark.parametrize("phi", [0.0, math.pi, -2 * math.pi, 6.0])
def test_a_phi_within_a_turn_is_taken(phi: float) -> None:
    assert validate_points(_point(phi))[0]["segments"]["segment_1"]["phi"] == phi


def test_a_misspelt_phi_field_names_phi_deg_too() -> None:
    pts = [{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1.0, "phi_dg": 90}}}]
    with pytest.raises(RequestError, match="phi_deg"):
        validate_points(pts)


def test_a_trajectory_file_with_degrees_in_phi_is_refused(tmp_path) -> None:
    f = tmp_path / "wave.yaml"
    f.write_text("- time_from_start: 1.0\n  segments:\n    segment_1: {kappa: 2.0, phi: 90}\n")
    with pytest.raises(CliError, match="1.5708 rad"):
        load_trajectory_file(str(f))
