"""Angles written in degrees where radians are expected: the one test and the one hint every
check uses (``ucr check``, ``ucr fk/ik/export-urdf --config``, the API's waypoints).

A value beyond a full turn (2*pi, with a hair of slack) cannot be meant as radians in any of
these fields: it is refused with the radian value to write. Importing this module costs nothing
(no numpy, no lxml): the API process uses it.
"""

from __future__ import annotations

import math

__all__ = ["beyond_a_turn", "degrees_hint", "phi_beyond_a_turn"]


def beyond_a_turn(value: float) -> bool:
    """More than a full turn: degrees written for radians (120 for 2.094)."""
    return abs(value) > math.tau + 1e-9


def degrees_hint(value: float, more: str = "") -> str:
    """``(if 90 is degrees, write 1.570796327)``: the radians to write instead (``more``: a
    further remark inside the brackets, after a semicolon)."""
    tail = f"; {more}" if more else ""
    return f"(if {value:g} is degrees, write {math.radians(value):.10g}{tail})"


def phi_beyond_a_turn(phi: float) -> str | None:
    """Why a commanded phi (rad) is refused, or None: beyond a turn it is degrees."""
    if not beyond_a_turn(phi):
        return None
    return (
        f"{phi:g} is more than a full turn: phi is in rad (if you meant {phi:g} degrees, that "
        f"is {math.radians(phi):.4f} rad)"
    )
