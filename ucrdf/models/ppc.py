"""Piecewise polynomial curvature (PPC), here affine: the curvature vector varies linearly along
the backbone,

    kx(s) = kx0 + kx_slope * s,   ky(s) = ky0 + ky_slope * s      (1/m, slopes in 1/m^2),

still torsion-free. Variables: ``kappa`` and ``phi`` give the curvature at the segment base in the
usual interface form, ``kappa_x_slope`` and ``kappa_y_slope`` its rate of change along the arc.
Coordinates (for IK and Jacobians) are (kx0, ky0, kappa_x_slope, kappa_y_slope).

The frame g(s) along the backbone solves g' = g xi(s) with the body twist xi = (v, w),
v = e_z, w = (-ky(s), kx(s), 0). It is integrated with the 4th-order Magnus method on SE(3)
(two Gauss points per step, one exponential per step), ``steps`` fixed steps per segment
(``<param name="steps">``, default 16). Each step is exact when the slopes are 0, so PPC equals
PCC to round-off there; with slopes the global error falls as steps^-4 (docs/kinematics.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from ucrdf.models.base import (
    LIMIT_SLACK,
    CurvatureModel,
    ModelError,
    Variable,
    kappa_phi,
)
from ucrdf.models.pcc import pcc_functions, project_disc

DEFAULT_STEPS = 16
_G = math.sqrt(3.0) / 6.0  # Gauss points at h (1/2 -+ sqrt(3)/6)


def se3_exp(v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(N, 4, 4) exponentials of twists with linear part v (N, 3) and angular part w (N, 3)."""
    t = np.einsum("ni,ni->n", w, w)
    a, b, c, _, _ = pcc_functions(t)
    n = w.shape[0]
    wx = np.zeros((n, 3, 3))
    wx[:, 0, 1], wx[:, 0, 2] = -w[:, 2], w[:, 1]
    wx[:, 1, 0], wx[:, 1, 2] = w[:, 2], -w[:, 0]
    wx[:, 2, 0], wx[:, 2, 1] = -w[:, 1], w[:, 0]
    wx2 = wx @ wx
    eye = np.eye(3)
    out = np.zeros((n, 4, 4))
    out[:, :3, :3] = eye + a[:, None, None] * wx + b[:, None, None] * wx2
    vmat = eye + b[:, None, None] * wx + c[:, None, None] * wx2
    out[:, :3, 3] = np.einsum("nij,nj->ni", vmat, v)
    out[:, 3, 3] = 1.0
    return out


def ppc_transforms(
    kx0: np.ndarray,
    ky0: np.ndarray,
    sx: np.ndarray,
    sy: np.ndarray,
    s_end: float,
    steps: int = DEFAULT_STEPS,
) -> np.ndarray:
    """(N, 4, 4) base -> arc length ``s_end`` (m) transforms for affine curvature vectors,
    batched over the coefficient arrays (kx0, ky0 in 1/m; slopes sx, sy in 1/m^2)."""
    kx0, ky0, sx, sy = (
        np.atleast_1d(np.asarray(x, dtype=float)).ravel() for x in (kx0, ky0, sx, sy)
    )
    kx0, ky0, sx, sy = np.broadcast_arrays(kx0, ky0, sx, sy)
    n = kx0.size
    g = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if s_end == 0.0:
        return g
    h = s_end / steps
    cm = math.sqrt(3.0) / 12.0 * h * h
    ez = np.zeros((n, 3))
    ez[:, 2] = 1.0
    for k in range(steps):
        s1 = (k + 0.5 - _G) * h
        s2 = (k + 0.5 + _G) * h
        w1x, w1y = -(ky0 + sy * s1), kx0 + sx * s1
        w2x, w2y = -(ky0 + sy * s2), kx0 + sx * s2
        w = np.empty((n, 3))
        w[:, 0] = 0.5 * h * (w1x + w2x)
        w[:, 1] = 0.5 * h * (w1y + w2y)
        w[:, 2] = cm * (w1x * w2y - w1y * w2x)  # [xi1, xi2] angular part: w1 x w2
        v = h * ez
        v[:, 0] += cm * (w1y - w2y)  # linear part of [xi1, xi2]: (w1 - w2) x e_z
        v[:, 1] -= cm * (w1x - w2x)
        g = g @ se3_exp(v, w)
    return g


class PPCModel(CurvatureModel):
    """Affine curvature segment. Variables kappa (1/m), phi (rad) at the base and
    kappa_x_slope, kappa_y_slope (1/m^2). |curvature| <= kappa_max holds along the whole arc
    (it is enough to check both ends: the norm of an affine function is convex)."""

    type_name = "ppc"

    extra_limits = ("kappa_slope_max",)

    @classmethod
    def variables(cls) -> list[Variable]:
        return [
            Variable("kappa", "1/m", 0.0, 0.0, None),
            Variable("phi", "rad", 0.0, -math.pi, math.pi),
            Variable("kappa_x_slope", "1/m^2", 0.0),
            Variable("kappa_y_slope", "1/m^2", 0.0),
        ]

    def validate(self) -> None:
        params = dict(self.spec.params)
        steps = params.pop("steps", DEFAULT_STEPS)
        if params:
            raise ModelError(
                f"model 'ppc' accepts only <param name=\"steps\">, got: {', '.join(sorted(params))}"
            )
        if not (
            isinstance(steps, (int, float)) and float(steps).is_integer() and 1 <= steps <= 10000
        ):
            raise ModelError(f"ppc param steps must be an integer in 1..10000, got {steps!r}")
        self.steps = int(steps)
        self.check_total_bend("PPC")
        lim = self.spec.limits
        extra = set(lim.extra) - {"kappa_slope_max"}
        if extra:
            raise ModelError(
                f"unknown ppc limit(s) {', '.join(sorted(extra))} (known: kappa_slope_max 1/m^2)"
            )
        self.slope_max = float(lim.extra.get("kappa_slope_max", 2.0 * lim.kappa_max / self.length))
        if not self.slope_max >= 0.0:
            raise ModelError(f"kappa_slope_max must be >= 0 1/m^2, got {self.slope_max}")

    def limits(self) -> dict[str, tuple[float, float]]:
        out = super().limits()
        out["kappa_x_slope"] = (-self.slope_max, self.slope_max)
        out["kappa_y_slope"] = (-self.slope_max, self.slope_max)
        return out

    def check_config(self, config: Mapping[str, float]) -> dict[str, float]:
        out = super().check_config(config)
        q = self.to_coordinates(out)
        kmax = self.spec.limits.kappa_max
        end = math.hypot(q[0] + q[2] * self.length, q[1] + q[3] * self.length)
        if end > kmax * (1.0 + LIMIT_SLACK) + LIMIT_SLACK:
            raise ModelError(
                f"curvature at the segment tip {end:g} 1/m exceeds kappa_max {kmax:g} 1/m "
                "(kappa + slope * length must stay within the limit)"
            )
        slope = math.hypot(q[2], q[3])
        if slope > self.slope_max * (1.0 + LIMIT_SLACK) + LIMIT_SLACK:
            raise ModelError(f"curvature slope {slope:g} 1/m^2 exceeds {self.slope_max:g} 1/m^2")
        return out

    def coordinate_names(self) -> list[str]:
        return ["kx", "ky", "kappa_x_slope", "kappa_y_slope"]

    def to_coordinates(self, config: Mapping[str, float]) -> np.ndarray:
        kappa = float(config.get("kappa", 0.0))
        phi = float(config.get("phi", 0.0))
        return np.array(
            [
                kappa * math.cos(phi),
                kappa * math.sin(phi),
                float(config.get("kappa_x_slope", 0.0)),
                float(config.get("kappa_y_slope", 0.0)),
            ]
        )

    def from_coordinates(
        self, q: np.ndarray, previous: Mapping[str, float] | None = None
    ) -> dict[str, float]:
        return {
            **kappa_phi(float(q[0]), float(q[1]), previous),
            "kappa_x_slope": float(q[2]),
            "kappa_y_slope": float(q[3]),
        }

    def project(self, q: np.ndarray) -> np.ndarray:
        lim = self.spec.limits
        full = self.full_circle()
        kx, ky = project_disc(float(q[0]), float(q[1]), lim, full)
        sx, sy = float(q[2]), float(q[3])
        snorm = math.hypot(sx, sy)
        if snorm > self.slope_max:
            sx, sy = sx * self.slope_max / snorm, sy * self.slope_max / snorm
        ex, ey = project_disc(kx + sx * self.length, ky + sy * self.length, lim, True)
        return np.array([kx, ky, (ex - kx) / self.length, (ey - ky) / self.length])

    def transform(self, config: Mapping[str, float], s: float | None = None) -> np.ndarray:
        return self.transform_coordinates(self.to_coordinates(self.check_config(config)), s)

    def transform_coordinates(self, q: np.ndarray, s: float | None = None) -> np.ndarray:
        s_end = self.length if s is None else float(s)
        steps = max(1, math.ceil(self.steps * abs(s_end) / self.length - 1e-9))
        return ppc_transforms(q[0], q[1], q[2], q[3], s_end, steps)[0]
