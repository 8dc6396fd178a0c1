"""Waypoints of a cJTC goal: validated against the bendables' limits and turned into knots
(time from start, (J, 2) curvature vectors in 1/m). A bad waypoint rejects the whole goal with a
reason naming the waypoint and the bendable (docs/controllers.md); nothing moves.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from host.controllers.base import ControllerError
from host.limits import BendableLimits

MAX_WAYPOINTS = 10_000  # what the API accepts (docs/api.md)
MIN_PIECE_S = 1e-3  # shortest time between waypoints (s): shorter pieces are numerically unsound


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def parse_waypoints(
    points: Any,
    current: np.ndarray,
    joints: list[str],
    limits: dict[str, BendableLimits],
    controller: str,
) -> list[tuple[float, np.ndarray]]:
    """Knots for ``points`` (see ``JointTrajectoryController.parse_points``); a bendable absent
    from a point keeps its previous value, starting from ``current`` ((J, 2), order of
    ``joints``). Raises ControllerError. Pure: safe outside the daemon lock."""
    index = {j: i for i, j in enumerate(joints)}
    if not isinstance(points, list | tuple) or not points:
        raise ControllerError("trajectory: expected a non-empty list of points")
    if len(points) > MAX_WAYPOINTS:
        raise ControllerError(f"trajectory: {len(points)} points, at most {MAX_WAYPOINTS}")
    prev_t = 0.0
    knots = []
    for n, pt in enumerate(points):
        where = f"trajectory point {n}"
        if not isinstance(pt, dict):
            raise ControllerError(f"{where}: expected a mapping")
        unknown = set(pt) - {"time_from_start", "t", "segments"}
        if unknown:
            raise ControllerError(f"{where}: unknown key(s) {', '.join(sorted(map(str, unknown)))}")
        t = pt.get("time_from_start", pt.get("t"))
        if not _finite(t):
            raise ControllerError(f"{where}: 'time_from_start' (s) missing or not a number")
        if t <= prev_t:
            raise ControllerError(
                f"{where}: time_from_start {t} s must be > {prev_t} s (strictly increasing, "
                "first > 0)"
            )
        if t - prev_t < MIN_PIECE_S:
            raise ControllerError(
                f"{where}: time_from_start {t} s is {(t - prev_t) * 1e3:.3g} ms after the "
                f"previous point; at least {MIN_PIECE_S * 1e3:g} ms between points"
            )
        segs = pt.get("segments")
        if not isinstance(segs, dict) or not segs:
            raise ControllerError(f"{where}: 'segments' must map bendable names to {{kappa, phi}}")
        pos = current.copy()
        for name, val in segs.items():
            if name not in index:
                known = ", ".join(joints) or "none"
                raise ControllerError(
                    f"{where}: bendable {name!r} is not commanded by {controller!r} "
                    f"(commanded: {known})"
                )
            i = index[name]
            lim = limits[name]
            if not isinstance(val, dict):
                raise ControllerError(f"{where}.{name}: expected {{kappa, phi}}")
            if "kx" in val or "ky" in val:
                kx, ky = val.get("kx", 0.0), val.get("ky", 0.0)
                if not (_finite(kx) and _finite(ky)):
                    raise ControllerError(f"{where}.{name}: kx/ky must be numbers (1/m)")
                kappa, phi = math.hypot(kx, ky), math.atan2(ky, kx)
            else:
                kappa = val.get("kappa")
                phi = val.get("phi", 0.0)
                if not _finite(kappa) or kappa < 0:
                    raise ControllerError(f"{where}.{name}: kappa must be a number >= 0 (1/m)")
                if not _finite(phi):
                    raise ControllerError(f"{where}.{name}: phi must be a number (rad)")
                kx, ky = kappa * math.cos(phi), kappa * math.sin(phi)
            if kappa > lim.kappa_max + 1e-9:
                raise ControllerError(
                    f"{where}.{name}: kappa {kappa:.4g} 1/m exceeds kappa_max "
                    f"{lim.kappa_max:.4g} 1/m (goal rejected; nothing moved)"
                )
            if not lim.full_circle and kappa > 1e-9:
                ph = math.atan2(ky, kx)
                if not lim.phi_min - 1e-9 <= ph <= lim.phi_max + 1e-9:
                    raise ControllerError(
                        f"{where}.{name}: phi {ph:.4g} rad outside [{lim.phi_min:.4g}, "
                        f"{lim.phi_max:.4g}] rad"
                    )
            pos[i] = (kx, ky)
        knots.append((float(t), pos))
        current = pos
        prev_t = t
    return knots
