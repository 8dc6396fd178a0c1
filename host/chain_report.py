"""What the daemon says about the chain, as pure functions of the topology follower's state:
the topology report (API ``topology``, cRSP topology messages), the message after a rebuild, and
the warning when the loop rate asks more of a real UART chain than it can answer.

Kept apart from :mod:`host.topology_follower` (which decides and acts) so the wording can change
without touching the hot-plug logic, and each function is testable without a link.
"""

from __future__ import annotations

import math
from typing import Any

from host.floors import pipelined_rate_hz
from host.link import exchange_floor_s
from host.positions import label
from host.topology import Comparison, chain_bendables


def describe_chain(
    robot: Any,
    full_robot: Any,
    descriptors: list[dict],
    controlled: list[str],
    comparison: Comparison | None,
    cut: dict[str, Any] | None,
) -> dict[str, Any]:
    """The chain as discovered (``descriptors``), what is ``controlled``, the differences from
    ``full_robot`` (the description hot-plug compares against) and the cut, if any."""
    cmp = comparison
    names = chain_bendables(full_robot)
    controlling = set(controlled)
    segs = []
    for d in descriptors:
        pos = d.get("position", len(segs))
        segs.append(
            {
                "position": pos + 1,  # counted from 1, like every position a user sees
                "bendable": names[pos] if pos < len(names) else None,
                "name": d.get("name"),
                "uid": d.get("uid"),
                "model": d.get("model"),
                "length": d.get("length"),
                "kappa_max": d.get("kappa_max"),
                "kappa_rate_max": d.get("kappa_rate_max"),
                "fw_version": d.get("fw_version"),
                "watchdog_ms": d.get("watchdog_ms"),
                "controlled": pos < len(names) and names[pos] in controlling,
            }
        )
    return {
        "robot": robot.name,
        "file": full_robot.source or None,
        "expected": names,
        "segments": segs,
        "controlled": list(controlled),
        "matched": cmp.matched if cmp else 0,
        "ok": bool(cmp and cmp.ok),
        "differences": [d.as_dict() for d in cmp.differences] if cmp else [],
        "cut": cut,
    }


def rebuild_message(names: list[str], cut: dict[str, Any] | None, cmp: Comparison) -> str:
    """One line after a hot-plug rebuild: what is controlled now, where the chain is cut, and
    the blocking differences other than the count."""
    msg = f"now {len(names)} segment(s): {', '.join(names)}"
    if cut:
        msg += (
            # after_position is 1-based (as topology() shows it); label() takes the index
            f"; chain cut after {cut['after']} ({label(cut['after_position'] - 1)}): "
            f"{', '.join(cut['lost'])} unreachable"
        )
    extra = [d.message for d in cmp.differences if d.blocking and d.kind != "count"]
    if extra:
        msg += "; " + "; ".join(extra)
    return msg


def largest_rate_hz(n: int, baudrate: int, pipeline: bool = False) -> int:
    """The largest loop rate (Hz) whose reply window (0.8 x period; pipelined 1.8 x period, the
    STATEs are collected one cycle later) holds one exchange of ``n`` segments at ``baudrate``
    (``exchange_floor_s``: the store-and-forward floor, largest frames); pipelined, never
    above what link 0 carries one exchange per period of (``floors.pipelined_rate_hz``)."""
    if not pipeline:
        return math.floor(0.8 / exchange_floor_s(n, baudrate))
    return math.floor(min(1.8 / exchange_floor_s(n, baudrate), pipelined_rate_hz(n, baudrate)))


def rate_warning(
    n: int,
    baudrate: int,
    reply_timeout_s: float,
    configured_reply_timeout_s: float,
    rate_hz: float,
    pipeline: bool = False,
) -> str | None:
    """Why a real UART chain of ``n`` segments cannot answer within ``reply_timeout_s`` (and
    what to change), or None when it can. ``pipeline``: the daemon collects the STATEs one
    period later, so they have the period on top."""
    floor = exchange_floor_s(n, baudrate)
    extra = 1.0 / rate_hz if pipeline else 0.0  # pipelined: the STATEs have a period more
    window = reply_timeout_s + extra
    if floor <= window:
        return None
    max_rate = largest_rate_hz(n, baudrate, pipeline)
    if floor > configured_reply_timeout_s + extra:
        advice = (
            f"raise watchdog.reply_timeout_s above {floor:.3f} s and use rate_hz <= "
            f"{max_rate}, or a higher baudrate"
        )
    else:
        advice = f"use rate_hz <= {max_rate} or a higher baudrate"
    if not pipeline and largest_rate_hz(n, baudrate, True) >= rate_hz:
        advice += ", or pipeline: true (docs/daemon.md 'Pipelining')"
    return (
        f"{n} segment(s) at {baudrate} baud need at least {floor * 1e3:.1f} ms per exchange on "
        "a real UART chain (bounded as store-and-forward to allow for each segment's "
        "processing, docs/daemon.md), more than the "
        f"{window * 1e3:.1f} ms a {rate_hz:.0f} Hz loop"
        f"{' (pipelined)' if pipeline else ''} waits for their states: "
        f"states would arrive late or be missed; {advice}"
    )
