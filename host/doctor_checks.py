"""The checks of ``ucr doctor`` (host/doctor.py runs them in order and prints them).

Read-only: DISCOVER, PARAM_GET and HEARTBEAT only. Each check returns ``Finding``s, each with the
fix where something is wrong (docs/commissioning.md). The chain against the U(C)RDF:
host/doctor_config.py.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

from protocol.constants import VERSION as _PROTOCOL_VERSION

# What this host expects of a segment. The firmware version's major.minor must match (a test
# keeps this equal to device/config.py FW_VERSION); the protocol version must be equal.
EXPECTED_FW_VERSION = "0.1.0"
EXPECTED_PROTOCOL_VERSION = _PROTOCOL_VERSION  # the one this host's protocol/ speaks

# parameter ids (docs/firmware.md)
P_WATCHDOG_MS = 0
P_CRC_ERRORS = 7
P_FRAMING_ERRORS = 8
P_DROPPED = 9
P_SERVO_FAULTS = 12
P_CYCLE_US = 13
P_OVERRUNS = 14
P_CONFIG_ERROR = 16
P_FAULT = 20
P_FAULT_COUNT = 21
P_SERVO_TELEMETRY = 22
P_CPU_LOAD = 23
P_TICK_MS = 24

# a segment's CPU load (PARAM 23, % of the last second not spent waiting): above this it has
# little slack left for frames arriving at once; at or above CPU_SATURATED_PCT its ticks and
# forwarding run late
CPU_WARN_PCT = 80
CPU_SATURATED_PCT = 98

# servo telemetry limits (Feetech STS defaults: 70 deg C cut-off, 6-14 V supply)
TEMP_WARN_C = 55.0
TEMP_ERROR_C = 65.0
VOLT_MIN_V = 6.0
VOLT_MAX_V = 14.0
LOAD_WARN = 0.8  # fraction of max torque, on a tendon no bend winds in (load_allowed)
#: spool angle (rad) below which the measured bend leaves a tendon as at rest
BEND_WIND_MIN = 0.05

SERVO_FAULT_NAMES = ("none", "no_reply", "stall", "overload", "error", "out_of_range")


@dataclass
class Finding:
    """One check's result. ``level``: ok | warning | error; ``fix`` says what to do about it."""

    check: str
    level: str
    message: str
    fix: str = ""
    position: int | None = None


def _version_tuple(text: Any) -> tuple[int, ...] | None:
    try:
        return tuple(int(x) for x in str(text).split(".")[:3])
    except ValueError:
        return None


def check_versions(pos: int, desc: dict) -> list[Finding]:
    """Firmware major.minor and protocol version against what this host expects."""
    out = []
    fw = desc.get("fw_version")
    have, want = _version_tuple(fw), _version_tuple(EXPECTED_FW_VERSION)
    if have is None or want is None or have[:2] != want[:2]:
        out.append(
            Finding(
                "firmware",
                "error",
                f"firmware {fw}, this host expects {EXPECTED_FW_VERSION}",
                "reflash the segment: "
                "`ucr flash --port <its USB port> --robot <robot> --segment <name>`",
                pos,
            )
        )
    else:
        out.append(Finding("firmware", "ok", f"firmware {fw}", position=pos))
    pv = desc.get("protocol_version")
    if pv != EXPECTED_PROTOCOL_VERSION:
        out.append(
            Finding(
                "protocol",
                "error",
                f"protocol version {pv}, this host speaks {EXPECTED_PROTOCOL_VERSION}",
                "reflash the segment with the firmware of this host's release, or update the host",
                pos,
            )
        )
    return out


def _param(link: Any, pos: int, pid: int, uid: str | None) -> Any:
    return link.param_get(pos, pid, uid, timeout=0.5)


def check_segment(link: Any, pos: int, desc: dict, state: dict | None = None) -> list[Finding]:
    """Per-segment checks over PARAM_GET (read-only); ``state`` (its STATE answering a
    HEARTBEAT, if any) tells the load check how the segment is bent."""
    from host.link import LinkError  # noqa: PLC0415

    uid = desc.get("uid")
    out = check_versions(pos, desc)
    try:
        cfg_err = _param(link, pos, P_CONFIG_ERROR, uid)
        servo_faults = _param(link, pos, P_SERVO_FAULTS, uid)
        fault = _param(link, pos, P_FAULT, uid)
        fault_count = _param(link, pos, P_FAULT_COUNT, uid)
        watchdog = _param(link, pos, P_WATCHDOG_MS, uid)
        counters = {
            "crc_errors": _param(link, pos, P_CRC_ERRORS, uid),
            "framing_errors": _param(link, pos, P_FRAMING_ERRORS, uid),
            "dropped": _param(link, pos, P_DROPPED, uid),
            "overruns": _param(link, pos, P_OVERRUNS, uid),
        }
        cycle_us = _param(link, pos, P_CYCLE_US, uid)
    except LinkError as exc:
        out.append(
            Finding(
                "params",
                "error",
                f"parameters unreadable: {exc}",
                "check the cable to this segment",
                pos,
            )
        )
        return out
    if cfg_err:
        out.append(
            Finding(
                "config",
                "error",
                f"configuration refused: {cfg_err}",
                "fix the U(C)RDF (`ucr check`) and reflash: `ucr flash ... --segment <name>`",
                pos,
            )
        )
    else:
        out.append(
            Finding(
                "config",
                "ok",
                f"configured: {desc.get('model')} / driver {desc.get('servo_driver')}",
                position=pos,
            )
        )
    if isinstance(servo_faults, list):
        bad = [
            f"servo {i}: {SERVO_FAULT_NAMES[c] if 0 <= c < len(SERVO_FAULT_NAMES) else c}"
            for i, c in enumerate(servo_faults)
            if c
        ]
        missing = [i for i, c in enumerate(servo_faults) if c == 1]
        if missing:
            out.append(
                Finding(
                    "servos",
                    "error",
                    f"servo(s) {', '.join(map(str, missing))} do not answer",
                    "check each servo's cable and power, and that its bus id matches the "
                    "segment's config.json (servo_ids)",
                    pos,
                )
            )
        others = [
            f"servo {i}: {SERVO_FAULT_NAMES[c] if 0 <= c < len(SERVO_FAULT_NAMES) else c}"
            for i, c in enumerate(servo_faults)
            if c and c != 1
        ]
        if others:
            out.append(
                Finding(
                    "servos",
                    "error",
                    "; ".join(others),
                    "free the tendon or servo horn (stall/overload), check supply voltage",
                    pos,
                )
            )
        if not bad:
            out.append(
                Finding("servos", "ok", f"{len(servo_faults)} servo(s) answer", position=pos)
            )
    out += check_telemetry(link, pos, uid, desc=desc, state=state)
    if fault:
        out.append(
            Finding(
                "fault",
                "error",
                f"in FAULT: {fault} ({fault_count} fault(s) since boot)",
                "remove the cause, then `ucr clear-fault` (the segment leaves FAULT only then)",
                pos,
            )
        )
    elif fault_count:
        out.append(
            Finding(
                "fault",
                "warning",
                f"{fault_count} fault(s) since boot (cleared)",
                "see `ucr watch` events for their causes",
                pos,
            )
        )
    out.append(Finding("watchdog", "ok", f"watchdog {watchdog} ms", position=pos))
    errs = {k: v for k, v in counters.items() if isinstance(v, int) and v > 0}
    if errs:
        out.append(
            Finding(
                "counters",
                "warning",
                ", ".join(f"{k} {v}" for k, v in errs.items()),
                "crc/framing errors: check the cable, shorten it or lower the baud rate; "
                "overruns: the control cycle is late (lower the rate or the load)",
                pos,
            )
        )
    out.append(Finding("cycle", "ok", f"longest control cycle {cycle_us} us", position=pos))
    out.append(check_cpu(link, pos, uid))
    return out


def check_cpu(link: Any, pos: int, uid: str | None) -> Finding:
    """The segment's CPU load (PARAM 23: [% of the last second, peak %] not spent waiting)."""
    from host.link import LinkError  # noqa: PLC0415

    try:
        load = _param(link, pos, P_CPU_LOAD, uid)
    except LinkError as exc:
        return Finding("cpu", "ok", f"CPU load not reported ({exc})", position=pos)
    if not (
        isinstance(load, list)
        and len(load) == 2
        and all(isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= 100 for x in load)
    ):
        return Finding("cpu", "warning", f"CPU load unreadable: {load!r}", position=pos)
    now, peak = load
    msg = f"CPU busy {now} % of the last second (peak {peak} % since boot)"
    try:
        tick = _param(link, pos, P_TICK_MS, uid)
    except LinkError:
        tick = None  # firmware before PARAM 24
    if isinstance(tick, int) and not isinstance(tick, bool) and 0 < tick < 1000:
        msg += f", ticking every {tick} ms"
    fix = (
        "the segment's control tick and the host's rate leave it no slack: frames wait at this "
        "hop and ticks run late; lower the daemon's rate_hz (docs/daemon.md), slow the "
        "segment's tick (hardware param tick_ms, reflash) or use a faster board "
        '(docs/firmware.md, "CPU load")'
    )
    if now >= CPU_SATURATED_PCT:
        return Finding("cpu", "error", msg + ": saturated", fix, pos)
    if max(now, peak) >= CPU_WARN_PCT:
        return Finding("cpu", "warning", msg, fix, pos)
    return Finding("cpu", "ok", msg, position=pos)


def bend_wind_in(desc: dict | None, state: dict | None) -> tuple[list[float], float] | None:
    """Spool angle (rad, + = tendon wound in) the measured curvature implies per tendon,
    a_i = l·d·κ·cos(φ − σ_i)/r (docs/firmware.md "Mapping"), and the wind-in of the segment's
    full bend (κ = kappa_max) towards a tendon; None without its STATE or geometry."""
    if not isinstance(desc, dict) or not isinstance(state, dict):
        return None
    sig = desc.get("tendon_angles")
    nums = (
        state.get("kappa"),
        state.get("phi"),
        desc.get("length"),
        desc.get("tendon_radius"),
        desc.get("spool_radius"),
        desc.get("kappa_max"),
    )
    if not all(isinstance(x, (int, float)) and math.isfinite(x) for x in nums):
        return None
    kappa, phi, length, radius, spool, kappa_max = nums
    if not isinstance(sig, list) or not all(isinstance(x, (int, float)) for x in sig):
        return None
    if not (spool > 0 and length * radius * kappa_max > 0):
        return None
    per_kappa = length * radius / spool
    return [per_kappa * kappa * math.cos(phi - x) for x in sig], per_kappa * kappa_max


def load_allowed(wind: float, full: float) -> float:
    """The load (fraction of max torque) a servo may show before it is over-tension: LOAD_WARN,
    plus the share of the full bend its tendon is wound in by the measured bend (a servo is
    sized to hold the segment's full bend), so a bent segment's loaded tendons are expected."""
    return LOAD_WARN + max(0.0, wind) / full


def _load_finding(i: int, load: float, pos: int, bend: str, wind: float, full: float) -> Finding:
    """Servo ``i``'s load beyond what the measured bend explains: over-tension."""
    load = abs(load)
    if bend and wind >= BEND_WIND_MIN:
        what = (
            f"more than the bend ({bend}) explains: it winds this tendon in by {wind:.2f} rad, "
            f"up to {load_allowed(wind, full):.0%}"
        )
    elif bend and wind <= -BEND_WIND_MIN:
        what = (
            f"while the bend ({bend}) pays its tendon out by {-wind:.2f} rad: that tendon should "
            "be slacker than at rest"
        )
    else:  # straight, its tendon left as at rest by the bend, or the pose unknown
        return Finding(
            "load",
            "warning",
            f"servo {i} load {load:.0%} of max torque at rest",
            "tendon over-tensioned at rest: slacken it (loosen the spool) "
            "and check the zero offset",
            pos,
        )
    return Finding(
        "load",
        "warning",
        f"servo {i} load {load:.0%} of max torque, {what}",
        "its tendon is caught or over-tensioned: free it, slacken it (loosen the spool) and "
        "check the zero offset",
        pos,
    )


def check_telemetry(
    link: Any, pos: int, uid: str | None, *, desc: dict | None = None, state: dict | None = None
) -> list[Finding]:
    """Servo voltage, temperature and load where the servos report them (PARAM 22). The load is
    judged against the bend the segment measures (``state``, with its geometry from ``desc``):
    a bent segment's servos that wind their tendons in hold that bend (``load_allowed``)."""
    from host.link import LinkError  # noqa: PLC0415

    try:
        tel = _param(link, pos, P_SERVO_TELEMETRY, uid)
    except LinkError as exc:
        return [
            Finding("telemetry", "warning", f"not available: {exc}", "update the firmware", pos)
        ]
    if not isinstance(tel, list) or not any(isinstance(t, list) for t in tel):
        return [Finding("telemetry", "ok", "servos report no telemetry (e.g. PWM)", position=pos)]
    winds, full = bend_wind_in(desc, state) or ([], 0.0)
    bent = max((abs(w) for w in winds), default=0.0) >= BEND_WIND_MIN
    bend = (
        f"kappa {state['kappa']:.2f} 1/m, phi {math.degrees(state['phi']):.0f} deg"
        if bent and state
        else ""
    )
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
        wind = winds[i] if bent and i < len(winds) else 0.0
        if bent and abs(load) < load_allowed(wind, full):
            shown[-1] += " (holds the bend)"
            held = True
        else:
            out.append(_load_finding(i, load, pos, bend, wind, full))
    head = "; ".join(shown) + (f" (bent: {bend})" if held else "")
    out.insert(0, Finding("telemetry", "ok", head, position=pos))
    return out


def check_timing(link: Any, n: int, seconds: float) -> Finding:
    """HEARTBEAT round trips for ``seconds``: answers complete and the round-trip time."""
    rtts: list[float] = []
    missing = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        states = link.heartbeat(timeout=0.2, expected=n)
        dt = time.perf_counter() - t0
        if any(s is None for s in states):
            missing += 1
        else:
            rtts.append(dt)
        time.sleep(0.02)
    total = len(rtts) + missing
    if not rtts:
        return Finding(
            "timing", "error", f"no complete HEARTBEAT round trip in {total}", "check the chain"
        )
    rtts.sort()
    p50 = rtts[len(rtts) // 2] * 1000
    p99 = rtts[min(len(rtts) - 1, int(len(rtts) * 0.99))] * 1000
    msg = f"{total} round trips: median {p50:.1f} ms, p99 {p99:.1f} ms, {missing} incomplete"
    if missing:
        return Finding("timing", "warning", msg, "lost answers: check cables and counters above")
    return Finding("timing", "ok", msg)
