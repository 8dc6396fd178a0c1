"""Configuration <-> tendon lengths for a tendon-driven constant-curvature segment.

Tendon i runs parallel to the backbone at distance ``radius`` d (m), at angle sigma_i (rad) in the
segment base frame, measured from +x towards +y (the U(C)RDF spec's convention). Bending with the
curvature vector (kx, ky) (1/m) shortens the tendons on the inside of the bend:

    l_i = l * (1 - d * (kx cos(sigma_i) + ky sin(sigma_i)))

The inverse solves that linear system in (kx, ky) by least squares, which needs at least two tendons
whose directions are not collinear (sigma_i and sigma_j not equal or opposite). With three or more
tendons the least-squares residual tells how inconsistent measured lengths are.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ucrdf.model import Bendable
from ucrdf.models.base import ModelError

#: Smallest acceptable |det(A^T A)| / n^2 of the direction matrix (1 = ideal spread, 0 = collinear).
COLLINEAR_TOL = 1e-6


class TendonMap:
    """The linear map between curvature vector and tendon lengths of one segment."""

    def __init__(self, length: float, angles: Sequence[float], radius: float):
        if not (math.isfinite(length) and length > 0.0):
            raise ModelError(f"segment length must be > 0 m, got {length}")
        if not (math.isfinite(radius) and radius > 0.0):
            raise ModelError(f"tendon radius must be > 0 m, got {radius}")
        angles = [float(a) for a in angles]
        if len(angles) < 2:
            raise ModelError(
                f"need at least 2 tendons to map curvature and tendon lengths, got {len(angles)}"
            )
        self.length = float(length)
        self.radius = float(radius)
        self.angles = np.array(angles)
        #: (n, 2) rows (cos sigma_i, sin sigma_i)
        self.directions = np.stack([np.cos(self.angles), np.sin(self.angles)], axis=1)
        gram = self.directions.T @ self.directions
        n = len(angles)
        if abs(np.linalg.det(gram)) / (n * n) < COLLINEAR_TOL:
            raise ModelError(
                "tendon angles are collinear (all equal or opposite: "
                f"{', '.join(f'{math.degrees(a):g} deg' for a in angles)}); the bending direction "
                "cannot be recovered from their lengths"
            )
        self._pinv = np.linalg.solve(gram, self.directions.T)  # (2, n) least-squares inverse

    @classmethod
    def for_bendable(cls, bendable: Bendable) -> TendonMap:
        """The map of a bendable with ``<actuation type="tendon">``."""
        act = bendable.actuation
        if act is None or act.type != "tendon":
            raise ModelError(f"bendable {bendable.name!r} has no tendon actuation")
        return cls(bendable.length, act.angles, act.radius)

    def max_curvature(self) -> float:
        """Curvature (1/m) at which the innermost tendon of some bending direction reaches zero
        length: a hard physical bound, 1/d."""
        return 1.0 / self.radius

    def lengths(self, kx: float | np.ndarray, ky: float | np.ndarray) -> np.ndarray:
        """Tendon lengths (m): shape (n,) for scalars, (..., n) for arrays of curvature vectors."""
        kx = np.asarray(kx, dtype=float)[..., None]
        ky = np.asarray(ky, dtype=float)[..., None]
        c, s = self.directions[:, 0], self.directions[:, 1]
        return self.length * (1.0 - self.radius * (kx * c + ky * s))

    def lengths_polar(self, kappa: float, phi: float) -> np.ndarray:
        """Tendon lengths (m) for the interface form (kappa 1/m, phi rad)."""
        return self.lengths(kappa * math.cos(phi), kappa * math.sin(phi))

    def curvature(self, lengths: Sequence[float] | np.ndarray) -> tuple[float, float]:
        """Least-squares curvature vector (kx, ky) (1/m) from tendon lengths (m)."""
        arr = self._check(lengths)
        k = self._pinv @ ((1.0 - arr / self.length) / self.radius)
        return float(k[0]), float(k[1])

    def residual(self, lengths: Sequence[float] | np.ndarray) -> float:
        """RMS difference (m) between the given lengths and those of the fitted curvature: how far
        the lengths are from any constant-curvature bend (0 for two tendons)."""
        arr = self._check(lengths)
        kx, ky = self.curvature(arr)
        return float(np.sqrt(np.mean((self.lengths(kx, ky) - arr) ** 2)))

    def _check(self, lengths: Sequence[float] | np.ndarray) -> np.ndarray:
        arr = np.asarray(lengths, dtype=float)
        if arr.shape != (len(self.angles),):
            raise ModelError(f"expected {len(self.angles)} tendon lengths, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise ModelError(f"tendon lengths must be finite, got {arr.tolist()}")
        return arr


def tendon_lengths(
    kx: float, ky: float, length: float, angles: Sequence[float], radius: float
) -> np.ndarray:
    """l_i = l (1 - d (kx cos sigma_i + ky sin sigma_i)) for every tendon (m)."""
    return TendonMap(length, angles, radius).lengths(kx, ky)


def curvature_from_lengths(
    lengths: Sequence[float], length: float, angles: Sequence[float], radius: float
) -> tuple[float, float]:
    """Least-squares (kx, ky) (1/m) from tendon lengths (m); ModelError if not determined."""
    return TendonMap(length, angles, radius).curvature(lengths)
