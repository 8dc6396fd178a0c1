"""Per-bendable interface limits: the model's ``<limits>`` intersected with the U(C)RDF
``<ros2_control>`` block (the intersection itself is ucrdf/limits.py, which FK and IK use too).
Shared by the configuration, the HWI and the controllers, so it imports neither of them (it sits
below both in the import order)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from host.errors import ConfigError
from protocol import constants as C
from ucrdf.limits import narrow_curvature
from ucrdf.models.base import ModelError


@dataclass
class BendableLimits:
    """Effective limits of one bendable: the model's ``<limits>`` intersected with the
    ``<ros2_control>`` command interface ``min``/``max``. Units 1/m, 1/m/s, rad."""

    name: str
    length: float
    kappa_max: float
    kappa_rate_max: float
    phi_min: float = -math.pi
    phi_max: float = math.pi
    kappa_initial: float = 0.0
    phi_initial: float = 0.0
    command_interfaces: tuple[str, ...] = ("kappa", "phi")
    state_interfaces: tuple[str, ...] = ("kappa", "phi")

    @property
    def full_circle(self) -> bool:
        return self.phi_min <= -math.pi + 1e-9 and self.phi_max >= math.pi - 1e-9


# 1/m/s, used when the U(C)RDF gives no kappa_rate_max: one value for host, segment and spec
DEFAULT_KAPPA_RATE_MAX = C.DEFAULT_KAPPA_RATE_MAX


# The one rule for "is this κ within kappa_max": the daemon's goal check (host.controllers.
# waypoints) and `ucr replay --execute`'s re-check of a recording both ask kappa_exceeds().
# KAPPA_EPS (1/m): float rounding, e.g. κ = |(κx, κy)| of a κ that was exactly kappa_max.
KAPPA_EPS = 1e-9
# A *measured* κ (a recording's /joint_states) is the segment's inverse of its servo positions:
# servo steps and the fixed-point path put it a little above kappa_max when the segment holds
# kappa_max. Up to this fraction of kappa_max it counts as kappa_max; beyond, the recording does
# not fit the robot file.
MEASURED_KAPPA_SLACK = 0.01


def kappa_exceeds(kappa: float, kappa_max: float, measured: bool = False) -> bool:
    """True if κ (1/m) lies above ``kappa_max``: beyond float rounding for a commanded κ, beyond
    :data:`MEASURED_KAPPA_SLACK` of ``kappa_max`` for a measured one."""
    slack = MEASURED_KAPPA_SLACK * kappa_max if measured else 0.0
    return kappa > kappa_max + slack + KAPPA_EPS


# The one rule for a restricted phi range [phi_min, phi_max] (a bendable whose bending plane may
# not turn all the way round): phi is an angle, so "outside" and "the nearer bound" are taken
# around the circle — never numerically, which sends phi = pi (just past phi_max = 3/4 pi) to
# phi_min and flips the bending plane. Used by the HWI (host/hwi.py), the cFFC and the cJTC's
# path check (host/controllers/).
PHI_EPS = 1e-9  # rad: float rounding at a bound


def phi_offset(phi: float, phi_min: float, phi_max: float) -> float:
    """How far (rad, >= 0) ``phi`` lies outside [phi_min, phi_max] around the circle: 0 inside,
    else the angle to the nearer bound."""
    span = phi_max - phi_min
    d = (phi - phi_min) % math.tau
    if d <= span + PHI_EPS:
        return 0.0
    return min(d - span, math.tau - d)


def clamp_phi(phi: float, phi_min: float, phi_max: float, prefer: float | None = None) -> float:
    """``phi`` (rad) inside [phi_min, phi_max]: itself (in that range's representation) when
    inside, else the bound nearer around the circle; midway between them, the bound nearer to
    ``prefer`` (the previous value: no flip), else phi_max."""
    span = phi_max - phi_min
    d = (phi - phi_min) % math.tau
    if d <= span + PHI_EPS:
        return min(phi_min + d, phi_max)
    to_max, to_min = d - span, math.tau - d
    if abs(to_max - to_min) <= PHI_EPS and prefer is not None:
        p = (prefer - phi_min) % math.tau
        to_max, to_min = abs(p - span), min(p, math.tau - p)
    return phi_max if to_max <= to_min else phi_min


def clamp_to_sector(
    kx: float, ky: float, phi_min: float, phi_max: float, prefer: tuple[float, float] | None = None
) -> tuple[float, float]:
    """The curvature vector (kx, ky) kept inside the sector phi_min <= phi <= phi_max: itself
    when inside (or straight), else its projection onto the nearer bounding ray (the nearest
    point of the sector: a step into the excluded sector slides along its edge, never across
    it). ``prefer``: the previous vector, which decides a tie."""
    kappa = math.hypot(kx, ky)
    if kappa <= KAPPA_EPS:
        return kx, ky
    phi = math.atan2(ky, kx)
    if phi_offset(phi, phi_min, phi_max) == 0.0:
        return kx, ky
    pref = math.atan2(prefer[1], prefer[0]) if prefer is not None and any(prefer) else None
    b = clamp_phi(phi, phi_min, phi_max, pref)
    along = max(0.0, kx * math.cos(b) + ky * math.sin(b))
    return along * math.cos(b), along * math.sin(b)


#: A check of many waypoints (a goal, a recording, a trajectory file) reports every problem it
#: finds in one go, not only the first: the first this many in full, then how many more.
MAX_REPORTED_PROBLEMS = 20
#: a check stops at this many problems (:attr:`Problems.full`): a goal of 10,000 bad waypoints
#: costs the daemon what 1,000 cost, not ten times a good goal's check
MAX_COUNTED_PROBLEMS = 1000


class Problems:
    """The problems one check found: counted up to ``count_max`` (then :attr:`full`: the check
    stops), the first ``limit`` kept in full. ``text(head)``: ``head`` with the count, then one
    indented line per problem kept."""

    def __init__(
        self, limit: int = MAX_REPORTED_PROBLEMS, count_max: int = MAX_COUNTED_PROBLEMS
    ) -> None:
        self.limit = limit
        self.count_max = count_max
        self.kept: list[str] = []
        self.count = 0

    def add(self, problem: str) -> None:
        self.count += 1
        if len(self.kept) < self.limit:
            self.kept.append(problem)

    @property
    def full(self) -> bool:
        """True once ``count_max`` problems are counted: the check stops there."""
        return self.count >= self.count_max

    def __bool__(self) -> bool:
        return self.count > 0

    def text(self, head: str) -> str:
        """``head: 1 problem: <it>`` for one, else ``head: N problems:`` and a line each."""
        if self.count == 1:
            return f"{head}: {self.kept[0]}"
        more = "at least " if self.full else ""
        lines = [f"{head}: {more}{self.count} problems:", *(f"  {p}" for p in self.kept)]
        if self.count > len(self.kept):
            stop = f" (the check stops at {self.count_max})" if self.full else ""
            lines.append(f"  ... and {more}{self.count - len(self.kept)} more{stop}")
        return "\n".join(lines)


def _fparam(params: dict, key: str, robot_src: str, where: str) -> float | None:
    if key not in params:
        return None
    try:
        v = float(params[key])
    except (TypeError, ValueError):
        raise ConfigError(
            robot_src, where + "." + key, f"expected a number, got {params[key]!r}"
        ) from None
    if not math.isfinite(v):
        raise ConfigError(robot_src, where + "." + key, f"must be finite, got {v!r}")
    return v


def bendable_limits(robot: Any) -> dict[str, BendableLimits]:
    """Per-bendable effective limits and interface names, in document order.

    A bendable listed in ``<ros2_control>`` exposes the interfaces declared there; one that is not
    listed gets the default kappa/phi pair (so a U(C)RDF without ``<ros2_control>`` still runs).
    ``max`` of the kappa command interface may only tighten ``kappa_max``; a looser one is an error.
    """
    src = getattr(robot, "source", "") or robot.name
    declared: dict[str, Any] = {}
    for block in getattr(robot, "ros2_control", []):
        for j in block.joints:
            declared[j.name] = j
    out: dict[str, BendableLimits] = {}
    for name, b in robot.bendables.items():
        lim = b.model.limits
        rate = lim.kappa_rate_max if lim.kappa_rate_max else DEFAULT_KAPPA_RATE_MAX
        for key, v in (("kappa_max", lim.kappa_max), ("kappa_rate_max", rate)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                # a robot built in code skips `ucr check`: the daemon refuses it here too
                raise ConfigError(
                    src, f"bendable[{name}].limits.{key}", f"must be a finite number > 0, got {v!r}"
                )
        bl = BendableLimits(
            name=name,
            length=b.length,
            kappa_max=float(lim.kappa_max),
            kappa_rate_max=float(rate),
            phi_min=lim.phi_min,
            phi_max=lim.phi_max,
        )
        cj = declared.get(name)
        if cj is not None:
            where = f"ros2_control.joint[{name}]"
            cmds = tuple(i.name for i in cj.command_interfaces)
            sts = tuple(i.name for i in cj.state_interfaces)
            for i in cmds + sts:
                if i not in ("kappa", "phi"):
                    raise ConfigError(
                        src,
                        f"{where}.{i}",
                        "a PCC bendable offers only 'kappa' and 'phi' interfaces",
                    )
            bl.command_interfaces = cmds
            bl.state_interfaces = sts or cmds
            bounds = {}
            for itf in cj.command_interfaces:
                w = f"{where}.command_interface[{itf.name}]"
                bounds[itf.name] = (
                    _fparam(itf.params, "min", src, w),
                    _fparam(itf.params, "max", src, w),
                )
                init = _fparam(itf.params, "initial_value", src, w)
                if init is not None and itf.name == "kappa":
                    bl.kappa_initial = init
                elif init is not None:
                    bl.phi_initial = init
            try:  # the intersection FK and IK use too (ucrdf/limits.py)
                narrowed = narrow_curvature(lim, bounds)
            except ModelError as exc:
                raise ConfigError(src, where, str(exc)) from None
            bl.kappa_max = float(narrowed.kappa_max)
            bl.phi_min, bl.phi_max = narrowed.phi_min, narrowed.phi_max
            if bl.phi_min >= bl.phi_max:
                raise ConfigError(src, where, f"empty phi range [{bl.phi_min}, {bl.phi_max}]")
            if not 0.0 <= bl.kappa_initial <= bl.kappa_max:
                raise ConfigError(
                    src,
                    where + ".kappa.initial_value",
                    f"{bl.kappa_initial} is outside [0, {bl.kappa_max}]",
                )
        out[name] = bl
    return out
