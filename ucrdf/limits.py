"""Effective limits: the bounds a robot accepts, its model's ``<limits>`` (a rigid joint's
``<limit>``) intersected with the ``min``/``max`` params of its ``<ros2_control>`` command
interfaces.

The one place that intersects them: FK and IK (ucrdf/fk.py, ucrdf/ik.py) check and solve within
the result, and the daemon (host/limits.py) enforces the same bounds. A bound looser than the
model's changes nothing. Imports nothing from host.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace

from ucrdf.model import CurvatureLimits, Robot
from ucrdf.models.base import ModelError

#: A command interface's declared (min, max); None where the param is not given.
Bounds = tuple[float | None, float | None]


def _number(value: object, what: str) -> float:
    if isinstance(value, bool):
        raise ModelError(f"{what} must be a finite number, got {value!r}")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ModelError(f"{what} must be a finite number, got {value!r}") from None
    if not math.isfinite(number):
        raise ModelError(f"{what} must be a finite number, got {value!r}")
    return number


def command_bounds(robot: Robot) -> dict[str, dict[str, Bounds]]:
    """Per ``<ros2_control>`` joint (a bendable or a rigid joint): command interface name ->
    its declared (min, max). ModelError for a min or max that is not a finite number."""
    out: dict[str, dict[str, Bounds]] = {}
    for block in robot.ros2_control:
        for joint in block.joints:
            for itf in joint.command_interfaces:
                where = f"ros2_control joint {joint.name!r}: command_interface {itf.name!r}"
                lo, hi = (
                    _number(itf.params[p], f"{where} param {p}") if p in itf.params else None
                    for p in ("min", "max")
                )
                out.setdefault(joint.name, {})[itf.name] = (lo, hi)
    return out


def narrow_curvature(limits: CurvatureLimits, bounds: Mapping[str, Bounds]) -> CurvatureLimits:
    """``limits`` (a bendable's ``<limits>``) narrowed by its command interfaces' bounds: the
    ``kappa`` max lowers kappa_max, the ``phi`` min/max narrow the phi range. ModelError for a
    kappa max <= 0 or min > 0 (kappa is a magnitude, commanded in [0, max]) and for an empty phi
    range. (A model's other variables: :func:`narrow_interval`.)"""
    kappa_lo, kappa_hi = bounds.get("kappa", (None, None))
    phi_lo, phi_hi = bounds.get("phi", (None, None))
    if kappa_hi is not None and kappa_hi <= 0.0:
        raise ModelError(f"command_interface 'kappa' max must be > 0 1/m, got {kappa_hi}")
    if kappa_lo is not None and kappa_lo > 0.0:
        raise ModelError(
            f"command_interface 'kappa' min {kappa_lo}: kappa is a magnitude; a minimum above 0 "
            "is not supported"
        )
    narrowed = replace(
        limits,
        kappa_max=limits.kappa_max if kappa_hi is None else min(limits.kappa_max, kappa_hi),
        phi_min=limits.phi_min if phi_lo is None else max(limits.phi_min, phi_lo),
        phi_max=limits.phi_max if phi_hi is None else min(limits.phi_max, phi_hi),
    )
    if narrowed.phi_min > narrowed.phi_max:
        raise ModelError(
            f"empty phi range [{narrowed.phi_min:g}, {narrowed.phi_max:g}]: the <limits> and the "
            "command_interface 'phi' min/max do not overlap"
        )
    return narrowed


def narrow_interval(lower: float, upper: float, bounds: Bounds | None) -> tuple[float, float]:
    """[lower, upper] (a joint's ``<limit>``, or a model variable's bounds) narrowed by a command
    interface's (min, max); ModelError when they do not overlap."""
    lo, hi = bounds if bounds is not None else (None, None)
    out = (lower if lo is None else max(lower, lo), upper if hi is None else min(upper, hi))
    if out[0] > out[1]:
        raise ModelError(
            f"empty range [{out[0]:g}, {out[1]:g}]: the limits [{lower:g}, {upper:g}] and the "
            f"command interface min/max do not overlap"
        )
    return out
