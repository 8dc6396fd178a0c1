"""The servo telemetry check of ``ucr doctor`` (host/doctor_checks.py runs it per segment):
supply voltage, temperature and load where the servos report them (PARAM 22). A servo's load is
judged against the bend the segment measures: a servo that winds its tendon in to hold a bend,
no further than the bend needs, is loaded by design; one wound in beyond that, one whose tendon
the bend pays out, and one at its torque limit are over-tension (docs/commissioning.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from host.doctor_base import P_SERVO_TELEMETRY, Finding, _param

# servo telemetry limits (Feetech STS defaults: 70 deg C cut-off, 6-14 V supply)
TEMP_WARN_C = 55.0
TEMP_ERROR_C = 65.0
VOLT_MIN_V = 6.0
VOLT_MAX_V = 14.0
LOAD_WARN = 0.8  # fraction of max torque, on a tendon no bend winds in (load_allowed)
LOAD_LIMIT = 0.95  # fraction of max torque: a servo at its limit warns whatever the bend
#: spool angle (rad) below which the measured bend leaves a tendon as at rest
BEND_WIND_MIN = 0.05
#: rad: a servo wound in beyond its tendon's share of the measured bend by more than this (or a
#: tenth of that share) is over-tensioned or off its zero; the bend does not explain its load
EXCESS_WIND_MAX = 0.1


@dataclass
class Bend:
    """A segment's measured bend as its tendons feel it: per tendon the spool angle (rad,
    + = wound in) the bend implies, a_i = l·d·κ·cos(φ − σ_i)/r (docs/firmware.md "Mapping"),
    the spool angles the servos measure (``servo_angles`` of its STATE), and the wind-in of the
    full bend (κ = kappa_max) towards one tendon."""

    kappa: float
    phi: float
    winds: list[float]
    measured: list[float]
    full: float

    @property
    def bent(self) -> bool:
        return max((abs(w) for w in self.winds), default=0.0) >= BEND_WIND_MIN

    def text(self) -> str:
        return f"kappa {self.kappa:.2f} 1/m, phi {math.degrees(self.phi):.0f} deg"

    def excess(self, i: int) -> float:
        """How far servo ``i`` is wound in beyond what the bend needs (rad): a servo wound in
        too far at rest makes the segment measure a bend towards its tendon, but the bend it
        measures then needs the other tendons paid out, and they are not."""
        return self.measured[i] - self.winds[i]

    def explains(self, i: int, load: float) -> bool:
        """The bend explains servo ``i``'s load: it winds that tendon in, the servo is wound in
        no further than the bend needs, and the load is within :func:`load_allowed`."""
        wind = self.winds[i]
        return (
            wind >= BEND_WIND_MIN
            and self.excess(i) <= max(EXCESS_WIND_MAX, 0.1 * wind)
            and load < load_allowed(wind, self.full)
        )


def _num(x: object) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def bend_of(desc: dict | None, state: dict | None) -> Bend | None:
    """The segment's :class:`Bend` from its descriptor's geometry and a STATE; None without
    either, or when the STATE lacks a spool angle per tendon."""
    if not isinstance(desc, dict) or not isinstance(state, dict):
        return None
    sig, measured = desc.get("tendon_angles"), state.get("servo_angles")
    nums = (
        state.get("kappa"),
        state.get("phi"),
        desc.get("length"),
        desc.get("tendon_radius"),
        desc.get("spool_radius"),
        desc.get("kappa_max"),
    )
    if not all(_num(x) for x in nums):
        return None
    kappa, phi, length, radius, spool, kappa_max = nums
    for seq in (sig, measured):
        if not isinstance(seq, list) or not all(_num(x) for x in seq):
            return None
    if len(measured) != len(sig) or not (spool > 0 and length * radius * kappa_max > 0):
        return None
    per_kappa = length * radius / spool
    winds = [per_kappa * kappa * math.cos(phi - x) for x in sig]
    return Bend(kappa, phi, winds, [float(a) for a in measured], per_kappa * kappa_max)


def load_allowed(wind: float, full: float) -> float:
    """The load (fraction of max torque) a servo whose tendon the bend winds in by ``wind``
    (rad) may show: LOAD_WARN plus the share of the full bend (a servo is sized to hold the
    segment's full bend), never LOAD_LIMIT or more (a servo at its limit always warns)."""
    return min(LOAD_LIMIT, LOAD_WARN + max(0.0, wind) / full)


def _load_finding(i: int, load: float, pos: int, bend: Bend | None) -> Finding:
    """Servo ``i``'s load, which the measured bend (if any) does not explain."""
    load = abs(load)
    fix = (
        "its tendon is caught or over-tensioned: free it, slacken it (loosen the spool) and "
        "check the zero offset"
    )
    if load >= LOAD_LIMIT:
        where = f" ({bend.text()})" if bend is not None and bend.bent else " at rest"
        return Finding(
            "load",
            "warning",
            f"servo {i} load {load:.0%} of max torque{where}: at its torque limit",
            f"{fix}; if the bend needs it, lower kappa_max or use a stronger servo",
            pos,
        )
    if bend is None or not bend.bent:
        return Finding(
            "load",
            "warning",
            f"servo {i} load {load:.0%} of max torque at rest",
            "tendon over-tensioned at rest: slacken it (loosen the spool) "
            "and check the zero offset",
            pos,
        )
    wind, excess = bend.winds[i], bend.excess(i)
    if excess > max(EXCESS_WIND_MAX, 0.1 * abs(wind)):
        what = (
            f"its servo wound in {excess:.2f} rad beyond what the bend ({bend.text()}) needs: "
            "over-tensioned or off its zero"
        )
    elif wind <= -BEND_WIND_MIN:
        what = (
            f"while the bend ({bend.text()}) pays its tendon out by {-wind:.2f} rad: that tendon "
            "should be slacker than at rest"
        )
    elif wind >= BEND_WIND_MIN:
        what = (
            f"more than the bend ({bend.text()}) explains: it winds this tendon in by "
            f"{wind:.2f} rad, up to {load_allowed(wind, bend.full):.0%}"
        )
    else:
        what = f"while the bend ({bend.text()}) leaves its tendon as at rest"
    return Finding("load", "warning", f"servo {i} load {load:.0%} of max torque, {what}", fix, pos)


def check_telemetry(
    link: Any, pos: int, uid: str | None, *, desc: dict | None = None, state: dict | None = None
) -> list[Finding]:
    """Servo voltage, temperature and load where the servos report them (PARAM 22). The load is
    judged against the bend the segment measures (``state``, with its geometry from ``desc``):
    a bent segment's servos that wind their tendons in, no further than the bend needs, hold that
    bend (:meth:`Bend.explains`)."""
    from host.link import LinkError  # noqa: PLC0415

    try:
        tel = _param(link, pos, P_SERVO_TELEMETRY, uid)
    except LinkError as exc:
        return [
            Finding("telemetry", "warning", f"not available: {exc}", "update the firmware", pos)
        ]
    if not isinstance(tel, list) or not any(isinstance(t, list) for t in tel):
        return [Finding("telemetry", "ok", "servos report no telemetry (e.g. PWM)", position=pos)]
    bend = bend_of(desc, state)
    out = []
    shown = []
    held = False
    for i, t in enumerate(tel):
        if not (
            isinstance(t, list) and len(t) == 3 and all(isinstance(x, (int, float)) for x in t)
        ):
            continue
        volt, temp, load = (float(x) for x in t)
        shown.append(f"{i}: {volt:.1f} V {temp:.0f} C load {load:.2f}")
        if temp >= TEMP_ERROR_C:
            out.append(
                Finding(
                    "temperature",
                    "error",
                    f"servo {i} at {temp:.0f} C (limit {TEMP_ERROR_C:.0f} C)",
                    "let it cool; slacken its tendon (it is holding too much load) or check for "
                    "a jammed horn",
                    pos,
                )
            )
        elif temp >= TEMP_WARN_C:
            out.append(
                Finding("temperature", "warning", f"servo {i} at {temp:.0f} C", "watch it", pos)
            )
        if not VOLT_MIN_V <= volt <= VOLT_MAX_V:
            out.append(
                Finding(
                    "voltage",
                    "error",
                    f"servo {i} supply {volt:.1f} V (expected {VOLT_MIN_V}-{VOLT_MAX_V} V)",
                    "check the servo power supply and its wiring",
                    pos,
                )
            )
        if abs(load) < LOAD_WARN:
            continue
        if bend is not None and i < len(bend.winds) and bend.explains(i, abs(load)):
            shown[-1] += " (holds the bend)"
            held = True
        else:
            known = bend is not None and i < len(bend.winds)
            out.append(_load_finding(i, load, pos, bend if known else None))
    head = "; ".join(shown) + (f" (bent: {bend.text()})" if held and bend else "")
    out.insert(0, Finding("telemetry", "ok", head, position=pos))
    return out
