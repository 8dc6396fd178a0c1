"""The cJTC path build is vectorised over pieces (issue 13: a 10,000-waypoint goal built piece by
piece in Python took seconds of the daemon process). These tests pin it to a plain per-piece
reference, so the speed-up changes no coefficient and no retiming decision."""

from __future__ import annotations

import numpy as np
import pytest

from host.controllers import trajectory
from host.controllers.trajectory import CurvatureTrajectory, quintic_coeffs


def _reference_coeffs(tr: CurvatureTrajectory) -> np.ndarray:
    """Per-piece quintics with the same boundary velocities as the build (slope average where
    the path keeps its direction, else 0; start state given; end at rest)."""
    P, d = tr.positions, tr.durations
    m = len(d)
    V = np.zeros_like(P)
    A = np.zeros_like(P)
    V[0], A[0] = tr.v0, tr.a0
    for i in range(1, m):
        s_in = (P[i] - P[i - 1]) / d[i - 1]
        s_out = (P[i + 1] - P[i]) / d[i]
        V[i] = np.where(np.sign(s_in) * np.sign(s_out) > 0, 0.5 * (s_in + s_out), 0.0)
    return np.stack(
        [
            quintic_coeffs(P[i], V[i], A[i], P[i + 1], V[i + 1], A[i + 1], float(d[i]))
            for i in range(m)
        ]
    )


def _reference_ratios(tr: CurvatureTrajectory) -> np.ndarray:
    """Per piece, sample by sample: max |v| / rate_max (the definition, one piece at a time)."""
    u = np.linspace(0.0, 1.0, trajectory._SAMPLES)
    out = []
    for i, T in enumerate(tr.durations):
        worst = 0.0
        for s in u * T:
            v = tr.coeffs[i] @ np.array([0.0, 1.0, 2 * s, 3 * s**2, 4 * s**3, 5 * s**4])
            worst = max(worst, float((np.hypot(v[:, 0], v[:, 1]) / tr.rate_max).max()))
        out.append(worst)
    return np.array(out)


def _random_goal(rng: np.random.Generator, n: int, joints: int) -> tuple:
    p0 = rng.normal(size=(joints, 2))
    v0 = rng.normal(size=(joints, 2)) * 0.1
    times = np.cumsum(0.02 + 0.2 * rng.random(n))
    knots = [(float(t), rng.normal(size=(joints, 2)) * 2.0) for t in times]
    return p0, v0, np.zeros((joints, 2)), knots, np.full(joints, 10.0)


@pytest.mark.parametrize(("n", "joints", "seed"), [(1, 1, 0), (2, 3, 1), (40, 3, 2), (300, 8, 3)])
def test_vectorised_build_equals_the_per_piece_reference(n: int, joints: int, seed: int) -> None:
    p0, v0, a0, knots, rate = _random_goal(np.random.default_rng(seed), n, joints)
    tr = CurvatureTrajectory(0.0, p0, v0, a0, knots, rate)
    np.testing.assert_allclose(tr.coeffs, _reference_coeffs(tr), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(tr._rate_ratios(), _reference_ratios(tr), rtol=1e-9, atol=1e-12)
    assert (tr._rate_ratios() <= 1.0 + 1e-9).all()  # the retimed path keeps the rate limit


def test_rate_check_spans_block_boundaries(monkeypatch: pytest.MonkeyPatch) -> None:
    """A goal longer than one block is checked piece for piece like a short one."""
    p0, v0, a0, knots, rate = _random_goal(np.random.default_rng(7), 50, 2)
    whole = CurvatureTrajectory(0.0, p0, v0, a0, knots, rate)
    monkeypatch.setattr(trajectory, "_BLOCK", 7)
    blocked = CurvatureTrajectory(0.0, p0, v0, a0, knots, rate)
    np.testing.assert_array_equal(whole.durations, blocked.durations)
    np.testing.assert_array_equal(whole._rate_ratios(), blocked._rate_ratios())


def test_a_ten_thousand_waypoint_goal_builds_and_ends_on_its_last_waypoint() -> None:
    p0, v0, a0, knots, rate = _random_goal(np.random.default_rng(11), 10_000, 3)
    tr = CurvatureTrajectory(0.0, p0, v0, a0, knots, rate)
    assert tr.coeffs.shape == (10_000, 3, 2, 6)
    np.testing.assert_allclose(tr.position(tr.duration + 1.0), knots[-1][1])
    assert (tr._rate_ratios() <= 1.0 + 1e-9).all()
