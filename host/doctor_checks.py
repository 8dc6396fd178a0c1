"""The checks of ``ucr doctor`` (host/doctor.py runs them in order and prints them).

Read-only: DISCOVER, PARAM_GET and HEARTBEAT only. Each check returns ``Finding``s, each with the
fix where something is wrong (docs/commissioning.md). The chain against the U(C)RDF:
host/doctor_config.py; the servos' telemetry (voltage, temperature, load): host/doctor_telemetry.py.
"""

from __future__ import annotations

import time
from typing import Any

from host.doctor_base import (  # noqa: F401 - Finding and the ids re-exported (tests, doctor.py)
    P_CONFIG_ERROR,
    P_CPU_LOAD,
    P_CRC_ERRORS,
    P_CYCLE_US,
    P_DROPPED,
    P_FAULT,
    P_FAULT_COUNT,
    P_FRAMING_ERRORS,
    P_OVERRUNS,
    P_SERVO_FAULTS,
    P_SERVO_TELEMETRY,
    P_TICK_MS,
    P_WATCHDOG_MS,
    Finding,
    _param,
)
from host.doctor_telemetry import check_telemetry
from protocol.constants import VERSION as _PROTOCOL_VERSION

# What this host expects of a segment. The firmware version's major.minor must match (a test
# keeps this equal to device/config.py FW_VERSION); the protocol version must be equal.
EXPECTED_FW_VERSION = "0.1.0"
EXPECTED_PROTOCOL_VERSION = _PROTOCOL_VERSION  # the one this host's protocol/ speaks

# a segment's CPU load (PARAM 23, % of the last second not spent waiting): above this it has
# little slack left for frames arriving at once; at or above CPU_SATURATED_PCT its ticks and
# forwarding run late
CPU_WARN_PCT = 80
CPU_SATURATED_PCT = 98

SERVO_FAULT_NAMES = ("none", "no_reply", "stall", "overload", "error", "out_of_range")


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
                "remove the cause, then clear it: start the daemon and run `ucr clear-fault` "
                "(it sends CLEAR_FAULT through the daemon, which doctor needs stopped), or "
                "power-cycle the segment; it stays in FAULT until then",
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


def check_timing(link: Any, n: int, seconds: float) -> Finding:
    """HEARTBEAT round trips for ``seconds``: answers complete and the round-trip time. The port
    failing meanwhile (an adapter unplugged, a cable pulled) is a finding like the other checks'
    LinkErrors, not a traceback that loses the findings printed so far."""
    from host.link import LinkError  # noqa: PLC0415

    rtts: list[float] = []
    missing = 0
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        t0 = time.perf_counter()
        try:
            states = link.heartbeat(timeout=0.2, expected=n)
        except LinkError as exc:
            return Finding(
                "timing",
                "error",
                f"the chain failed after {len(rtts) + missing} round trip(s): {exc}",
                "check the port's adapter and the cable to the first segment (unplugged?), "
                "then run doctor again",
            )
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
