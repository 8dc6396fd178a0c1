"""Piecewise constant curvature (PCC), the paper's segment model (equations 1-3).

Torsion-free form T = [Rz(phi) Ry(theta) Rz(-phi), p] with theta = kappa*l, evaluated in the
curvature vector (kx, ky) = kappa (cos phi, sin phi). The tip rotation is the rotation vector
w = l (-ky, kx, 0) (|w| = theta), so with

    A = sin(theta)/theta,  B = (1 - cos(theta))/theta^2,  C = (theta - sin(theta))/theta^3

    R = I + A [w]x + B [w]x^2,   p = (kx l^2 B, ky l^2 B, l A).

A, B, C and their derivatives use Taylor series for theta^2 < SERIES_T, so a straight segment
(kx = ky = 0) is exact and phi is never needed. Every function here is batched over arrays.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ucrdf.model import CurvatureLimits
from ucrdf.models.base import (
    CurvatureModel,
    ModelError,
    Variable,
    kappa_phi,
    wrap_angle,
)

#: theta^2 below which the series are used (theta < 0.25 rad). Five terms keep the truncation
#: error below 1e-16; above it the closed forms lose at most ~eps/theta^2 < 2e-15 to cancellation.
SERIES_T = 0.0625


def _series(t: np.ndarray, coeffs: tuple[float, ...]) -> np.ndarray:
    out = np.full_like(t, coeffs[-1])
    for c in coeffs[-2::-1]:
        out = out * t + c
    return out


# Taylor coefficients in t = theta^2.
_A = (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880, -1 / 39916800)
_B = (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800, -1 / 479001600)
_C = (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800, -1 / 6227020800)
_DA = (-1 / 6, 2 / 120, -3 / 5040, 4 / 362880, -5 / 39916800, 6 / 6227020800)
_DB = (-1 / 24, 2 / 720, -3 / 40320, 4 / 3628800, -5 / 479001600, 6 / 87178291200)


def pcc_functions(t: np.ndarray) -> tuple[np.ndarray, ...]:
    """A, B, C, dA/dt, dB/dt of t = theta^2 (arrays), exact at t = 0."""
    t = np.asarray(t, dtype=float)
    small = t < SERIES_T
    th = np.sqrt(np.where(small, 1.0, t))
    ts = np.where(small, 1.0, t)
    s, c = np.sin(th), np.cos(th)
    one_c = 2.0 * np.sin(0.5 * th) ** 2  # 1 - cos(theta) without cancellation
    a = np.where(small, _series(t, _A), s / th)
    b = np.where(small, _series(t, _B), one_c / ts)
    cc = np.where(small, _series(t, _C), (th - s) / (ts * th))
    da = np.where(small, _series(t, _DA), (th * c - s) / (2.0 * ts * th))
    db = np.where(small, _series(t, _DB), (th * s - 2.0 * one_c) / (2.0 * ts * ts))
    return a, b, cc, da, db


def pcc_transforms(kx: np.ndarray, ky: np.ndarray, length: np.ndarray | float) -> np.ndarray:
    """(N, 4, 4) base -> arc-length ``length`` transforms for curvature vectors (kx, ky) (1/m).

    ``length`` (m) broadcasts against kx/ky: pass the segment length for tips or an array of arc
    lengths for points along the backbone."""
    kx, ky, ln = np.broadcast_arrays(
        np.asarray(kx, dtype=float), np.asarray(ky, dtype=float), np.asarray(length, dtype=float)
    )
    kx, ky, ln = kx.ravel(), ky.ravel(), ln.ravel()
    wx, wy = -ky * ln, kx * ln
    t = wx * wx + wy * wy
    a, b, _, _, _ = pcc_functions(t)
    out = np.zeros((kx.size, 4, 4))
    bwx, bwy = b * wx, b * wy
    out[:, 0, 0] = 1.0 - bwy * wy
    out[:, 0, 1] = bwx * wy
    out[:, 0, 2] = a * wy
    out[:, 1, 0] = bwx * wy
    out[:, 1, 1] = 1.0 - bwx * wx
    out[:, 1, 2] = -a * wx
    out[:, 2, 0] = -a * wy
    out[:, 2, 1] = a * wx
    out[:, 2, 2] = 1.0 - b * t
    out[:, 0, 3] = bwy * ln
    out[:, 1, 3] = -bwx * ln
    out[:, 2, 3] = a * ln
    out[:, 3, 3] = 1.0
    return out


def pcc_tip_jacobians(
    kx: np.ndarray, ky: np.ndarray, length: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """(Jv, Jw), each (N, 3, 2): d(tip position)/d(kx, ky) in m^2 and tip angular velocity per
    unit curvature change (m), both in the segment base frame (analytic)."""
    kx, ky, ln = np.broadcast_arrays(
        np.asarray(kx, dtype=float), np.asarray(ky, dtype=float), np.asarray(length, dtype=float)
    )
    kx, ky, ln = kx.ravel(), ky.ravel(), ln.ravel()
    l2 = ln * ln
    l3 = l2 * ln
    t = (kx * kx + ky * ky) * l2
    a, b, c, da, db = pcc_functions(t)
    jv = np.empty((kx.size, 3, 2))
    jv[:, 0, 0] = l2 * b + 2.0 * kx * kx * l2 * l2 * db
    jv[:, 0, 1] = 2.0 * kx * ky * l2 * l2 * db
    jv[:, 1, 0] = jv[:, 0, 1]
    jv[:, 1, 1] = l2 * b + 2.0 * ky * ky * l2 * l2 * db
    jv[:, 2, 0] = 2.0 * kx * l3 * da
    jv[:, 2, 1] = 2.0 * ky * l3 * da
    jw = np.empty((kx.size, 3, 2))
    jw[:, 0, 0] = -c * kx * ky * l3
    jw[:, 1, 0] = ln - c * ky * ky * l3
    jw[:, 2, 0] = -b * ky * l2
    jw[:, 0, 1] = -ln + c * kx * kx * l3
    jw[:, 1, 1] = c * kx * ky * l3
    jw[:, 2, 1] = b * kx * l2
    return jv, jw


def pcc_from_angles(kappa: float, phi: float, length: float) -> np.ndarray:
    """4x4 tip transform in the paper's own form (equations 2 and 3 with theta = kappa*l).

    Kept as an independent reference for tests; it divides by kappa, so kappa must be > 0."""
    q = kappa * length
    cp, sp, cq, sq = math.cos(phi), math.sin(phi), math.cos(q), math.sin(q)
    t = np.eye(4)
    t[:3, :3] = [
        [cp * cp * (cq - 1) + 1, sp * cp * (cq - 1), cp * sq],
        [sp * cp * (cq - 1), sp * sp * (cq - 1) + 1, sp * sq],
        [-cp * sq, -sp * sq, cq],
    ]
    t[:3, 3] = np.array([cp * (1 - cq), sp * (1 - cq), sq]) / kappa
    return t


class PCCModel(CurvatureModel):
    """Constant curvature segment: variables kappa (1/m, 0..kappa_max) and phi (rad).

    Coordinates are (kx, ky) (1/m). ``<limits kappa_max>`` must satisfy kappa_max*l <= pi."""

    type_name = "pcc"

    @classmethod
    def variables(cls) -> list[Variable]:
        return [
            Variable("kappa", "1/m", 0.0, 0.0, None),
            Variable("phi", "rad", 0.0, -math.pi, math.pi),
        ]

    def validate(self) -> None:
        lim = self.spec.limits
        if self.spec.params:
            raise ModelError(
                f"model 'pcc' takes no <param>, got: {', '.join(sorted(self.spec.params))}"
            )
        self.check_total_bend("PCC")
        if lim.phi_min > lim.phi_max:
            raise ModelError(f"phi_min {lim.phi_min} is larger than phi_max {lim.phi_max}")

    # -- coordinates -------------------------------------------------------------------------
    def coordinate_names(self) -> list[str]:
        return ["kx", "ky"]

    def to_coordinates(self, config: Mapping[str, float]) -> np.ndarray:
        kappa = float(config.get("kappa", 0.0))
        phi = float(config.get("phi", 0.0))
        return np.array([kappa * math.cos(phi), kappa * math.sin(phi)])

    def from_coordinates(
        self, q: np.ndarray, previous: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        return kappa_phi(float(q[0]), float(q[1]), previous)

    def project(self, q: np.ndarray) -> np.ndarray:
        return np.array(
            project_disc(float(q[0]), float(q[1]), self.spec.limits, self.full_circle())
        )

    # -- kinematics ----------------------------------------------------------------------------
    def transform(self, config: Mapping[str, float], s: float | None = None) -> np.ndarray:
        q = self.to_coordinates(self.check_config(config))
        return self.transform_coordinates(q, s)

    def transform_coordinates(self, q: np.ndarray, s: float | None = None) -> np.ndarray:
        return pcc_transforms(q[0], q[1], self.length if s is None else s)[0]

    def coordinate_jacobians(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        jv, jw = pcc_tip_jacobians(q[0], q[1], self.length)
        return jv[0], jw[0]

    def backbone_frames(self, config: Mapping[str, float], samples: int = 20) -> np.ndarray:
        q = self.to_coordinates(self.check_config(config))
        return pcc_transforms(q[0], q[1], np.linspace(0.0, self.length, samples))

    def backbone_curve(self, config: Mapping[str, float], samples: int = 20) -> np.ndarray:
        return self.backbone_frames(config, samples)[:, :3, 3]


def project_disc(
    kx: float, ky: float, limits: CurvatureLimits, full_circle: bool = True
) -> tuple[float, float]:
    """(kx, ky) moved to the nearest point with kappa <= kappa_max and, when the limits restrict
    phi, phi in [phi_min, phi_max] (the nearer bound is taken for angles outside)."""
    kmax = limits.kappa_max
    kappa = math.hypot(kx, ky)
    if kappa > kmax:
        scale = kmax / kappa
        kx, ky, kappa = kx * scale, ky * scale, kmax
    if not full_circle and kappa > 0.0:
        phi = math.atan2(ky, kx)
        lo, hi = limits.phi_min, limits.phi_max
        # compare on the circle: distance to each bound, wrapped
        if not (lo <= phi <= hi or lo <= phi + 2 * math.pi <= hi or lo <= phi - 2 * math.pi <= hi):
            d_lo = abs(wrap_angle(phi - lo))
            d_hi = abs(wrap_angle(phi - hi))
            phi = lo if d_lo <= d_hi else hi
            kx, ky = kappa * math.cos(phi), kappa * math.sin(phi)
    return kx, ky
