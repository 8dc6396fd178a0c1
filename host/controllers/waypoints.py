"""Waypoints of a cJTC goal: validated against the bendables' limits and turned into knots
(time from start, (J, 2) curvature vectors in 1/m). A bad waypoint rejects the whole goal with a
reason naming the waypoint (counted from 1) and the bendable, every bad waypoint in one reason
(the first host.limits.MAX_REPORTED_PROBLEMS in full; docs/controllers.md); nothing moves.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence
from typing import Any

import numpy as np

from host.api.schema import MIN_POINT_GAP_S, TIME_EPS_S
from host.controllers.base import ControllerError
from host.limits import BendableLimits, Problems, kappa_exceeds

MAX_WAYPOINTS = 10_000  # what the API accepts (docs/api.md)
MIN_PIECE_S = MIN_POINT_GAP_S  # shortest time between waypoints (s): the API's own rule


_KEYS = frozenset({"time_from_start", "t", "segments"})


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


class Knots(Sequence):
    """A goal's knots as two arrays — ``times`` (m,) s from the start, ``positions`` (m, J, 2)
    curvature vectors 1/m — and, for whoever wants it so, a sequence of (time, (J, 2)) pairs."""

    def __init__(
        self, times: np.ndarray, positions: np.ndarray, named: frozenset[int] | None = None
    ) -> None:
        self.times = times
        self.positions = positions
        #: the columns (bendables) some point names; None: every one
        self.named = frozenset(range(positions.shape[1])) if named is None else named

    def __len__(self) -> int:
        return len(self.times)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [(float(t), p) for t, p in zip(self.times[i], self.positions[i], strict=True)]
        return float(self.times[i]), self.positions[i]


def distinct(a: float, b: float) -> tuple[str, str]:
    """``a`` and ``b`` with 4 significant digits, or as many more as it takes for them to read
    differently (a refusal must never say "3.314 exceeds 3.314")."""
    for digits in range(4, 18):
        ta, tb = f"{a:.{digits}g}", f"{b:.{digits}g}"
        if ta != tb:
            break
    return ta, tb


def parse_waypoints(
    points: Any,
    current: np.ndarray,
    joints: list[str],
    limits: dict[str, BendableLimits],
    controller: str,
) -> Knots:
    """Knots for ``points`` (see ``JointTrajectoryController.parse_points``); a bendable absent
    from a point keeps its previous value, starting from ``current`` ((J, 2), order of
    ``joints``); ``Knots.named`` tells which bendables some point names (the cJTC stops the
    others). Raises ControllerError. Pure: safe outside the daemon lock.

    It runs beside the control loop (a 10 000-waypoint goal: tens of ms of Python), so it holds
    the interpreter lock only in short pieces: plain floats per point, no numpy call per point,
    the arrays made at the end without a loop in C (``np.frombuffer``)."""
    index = {j: i for i, j in enumerate(joints)}
    if not isinstance(points, list | tuple) or not points:
        raise ControllerError("trajectory: expected a non-empty list of points")
    if len(points) > MAX_WAYPOINTS:
        raise ControllerError(f"trajectory: {len(points)} points, at most {MAX_WAYPOINTS}")
    # per bendable, read once: (index, kappa_max, full circle, phi_min, phi_max)
    lims = {
        name: (i, limits[name].kappa_max, limits[name].full_circle, limits[name].phi_min,
               limits[name].phi_max)
        for name, i in index.items()
    }  # fmt: skip
    prev_t = 0.0
    times = array("d")
    flat = array("d")
    row = [float(v) for v in np.asarray(current, dtype=float).reshape(-1)]
    problems = Problems()  # every bad point is reported, not only the first
    named: set[int] = set()
    for n, pt in enumerate(points, start=1):  # counted from 1, as a user counts a file's points
        if problems.full:
            break  # enough to say (Problems.text): the rest is not checked
        if not isinstance(pt, dict):
            problems.add(f"trajectory point {n}: expected a mapping")
            continue
        if not _KEYS.issuperset(pt):
            unknown = ", ".join(sorted(map(str, set(pt) - _KEYS)))
            problems.add(f"trajectory point {n}: unknown key(s) {unknown}")
        t = pt.get("time_from_start", pt.get("t"))
        if not _finite(t):
            problems.add(f"trajectory point {n}: 'time_from_start' (s) missing or not a number")
        elif t <= prev_t:
            problems.add(
                f"trajectory point {n}: time_from_start {t} s must be > {prev_t} s (strictly "
                "increasing, first > 0)"
            )
        elif t - prev_t < MIN_PIECE_S - TIME_EPS_S:  # exactly 1 ms written in decimals passes
            after = "the start" if prev_t == 0.0 else "the previous point"
            problems.add(
                f"trajectory point {n}: time_from_start {t} s is {(t - prev_t) * 1e3:.3g} ms "
                f"after {after}; at least {MIN_PIECE_S * 1e3:g} ms between points"
            )
        segs = pt.get("segments")
        if not isinstance(segs, dict) or not segs:
            problems.add(
                f"trajectory point {n}: 'segments' must map bendable names to {{kappa, phi}}"
            )
            segs = {}
        for name, val in segs.items():
            if problems.full:
                break
            lim = lims.get(name)
            if lim is None:
                known = ", ".join(joints) or "none"
                problems.add(
                    f"trajectory point {n}: bendable {name!r} is not commanded by "
                    f"{controller!r} (commanded: {known})"
                )
                continue
            i, kappa_max, full_circle, phi_min, phi_max = lim
            where = f"trajectory point {n}.{name}"  # only reached for a named bendable
            if not isinstance(val, dict):
                problems.add(f"{where}: expected {{kappa, phi}}")
                continue
            if "kx" in val or "ky" in val:
                if "kx" not in val or "ky" not in val or "kappa" in val or "phi" in val:
                    problems.add(f"{where}: give both kx and ky (1/m), or kappa and phi")
                    continue
                kx, ky = val["kx"], val["ky"]
                if not (_finite(kx) and _finite(ky)):
                    problems.add(f"{where}: kx/ky must be numbers (1/m)")
                    continue
                kappa = math.hypot(kx, ky)
            else:
                kappa = val.get("kappa")
                phi = val.get("phi", 0.0)
                if not _finite(kappa) or kappa < 0:
                    problems.add(f"{where}: kappa must be a number >= 0 (1/m)")
                    continue
                if not _finite(phi):
                    problems.add(f"{where}: phi must be a number (rad)")
                    continue
                kx, ky = kappa * math.cos(phi), kappa * math.sin(phi)
            if kappa_exceeds(kappa, kappa_max):
                k_txt, max_txt = distinct(kappa, kappa_max)
                problems.add(
                    f"{where}: kappa {k_txt} 1/m exceeds kappa_max "
                    f"{max_txt} 1/m (goal rejected; nothing moved)"
                )
                continue
            if not full_circle and kappa > 1e-9:
                ph = math.atan2(ky, kx)
                if not phi_min - 1e-9 <= ph <= phi_max + 1e-9:
                    problems.add(
                        f"{where}: phi {ph:.4g} rad outside [{phi_min:.4g}, {phi_max:.4g}] rad"
                    )
                    continue
            row[2 * i] = float(kx)
            row[2 * i + 1] = float(ky)
            named.add(i)
        if problems.count:  # the knots are thrown away: only keep checking
            if _finite(t):
                prev_t = t  # each point against the one before it: one typo is one problem
            continue
        times.append(float(t))
        flat.extend(row)
        prev_t = t
    if problems:
        raise ControllerError(
            problems.kept[0] if problems.count == 1
            else problems.text("trajectory rejected (goal rejected; nothing moved)")
        )  # fmt: skip
    m, j = len(times), len(joints)
    return Knots(
        np.frombuffer(times, dtype=float),
        np.frombuffer(flat, dtype=float).reshape(m, j, 2),
        frozenset(named),
    )
