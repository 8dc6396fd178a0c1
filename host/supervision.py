"""Per-cycle supervision of the chain (ACROSET SMCS), beside the control path: turns segment
EVENTs into readable events, notices a topology change (event, silent segment, a segment behind
the tip) and handles segments that hold on their own (watchdog or HOLD).

It decides and reports; it does not rebuild. :meth:`Supervisor.check` returns the reason for a
topology change, and the topology follower acts on it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from host.config import WatchdogConfig
from host.controllers.base import RobotState
from host.hwi import HardwareInterface

TOPOLOGY_EVENTS = {"DOWNSTREAM_UP", "DOWNSTREAM_DOWN", "BOOT"}


def describe_event(ev: dict, descriptors: list[dict]) -> str:
    """One readable line for a segment EVENT (which segment, what happened)."""
    pos, name, detail = ev.get("position"), ev.get("name", ""), ev.get("detail")
    who = f"position {pos}"
    if isinstance(pos, int) and pos < len(descriptors):
        who = f"{descriptors[pos].get('name') or '?'} (position {pos})"
    if name == "LIMIT_CLAMPED" and isinstance(detail, int):
        bits = [b for i, b in enumerate(("kappa", "rate", "servo range")) if detail >> i & 1]
        what = f"setpoint clamped by the segment ({', '.join(bits) or detail})"
    else:
        what = {
            "DOWNSTREAM_UP": "a segment appeared on its downstream port",
            "DOWNSTREAM_DOWN": "its downstream neighbour went silent",
            "WATCHDOG_TRIPPED": f"watchdog tripped (detail {detail}): holding",
            "WATCHDOG_CLEARED": "watchdog cleared",
            "SERVO_FAULT": f"servo {detail} reports a fault",
            "BOOT": "booted",
        }.get(name, f"{name} (detail {detail})")
    return f"{who}: {what}"


def is_news(event: str, position: Any, descriptors: list[dict]) -> bool:
    """Whether a segment event contradicts the topology we know (duplicates are not)."""
    if event not in TOPOLOGY_EVENTS:
        return False
    if event == "BOOT" or not isinstance(position, int):
        return True
    last = len(descriptors) - 1
    if event == "DOWNSTREAM_DOWN":
        return position < last  # we believed a segment was behind it
    return position >= last  # DOWNSTREAM_UP: we believed it was the tip


class Supervisor:
    """SMCS for one loop. ``emit_event(event, message, **fields)`` reports;
    ``rehold(state, message)`` makes the controllers hold the measured state."""

    def __init__(
        self,
        watchdog: WatchdogConfig,
        period: float,
        emit_event: Callable[..., None],
        rehold: Callable[[RobotState, str], None],
    ):
        self.watchdog = watchdog
        self.period = period
        self._emit = emit_event
        self._rehold = rehold
        self.silent = False  # the last reason was silence (no event): verify before aborting

    def check(
        self,
        hwi: HardwareInterface,
        state: RobotState,
        events: list[dict],
        descriptors: list[dict],
    ) -> str | None:
        """Return a reason when the topology changed; handle unexpected HOLDs."""
        reason = None
        self.silent = False
        for ev in events:
            name = ev.get("name", "")
            self._emit(
                name.lower(),
                message=describe_event(ev, descriptors),
                position=ev.get("position"),
                detail=ev.get("detail"),
                segment_t_ms=ev.get("t_ms"),
                source="segment",
            )
            if reason is None and is_news(name, ev.get("position"), descriptors):
                reason = f"{name} from position {ev.get('position')}"
        if reason is None:
            wd = self.watchdog
            limit = max(wd.missed_cycles, math.ceil(wd.silence_s / self.period))
            silent = [i for i, m in enumerate(hwi.missing) if m >= limit]
            if silent:
                names = ", ".join(f"{hwi.names[i]} (position {i})" for i in silent)
                reason = f"no STATE from {names} for {limit} cycles"
                self.silent = True
        if reason is None and hwi.raw_states and descriptors:
            tip = hwi.raw_states[-1]
            known_tip = descriptors[len(hwi.names) - 1]
            if (
                tip is not None
                and "DOWNSTREAM" in tip["status"]
                and known_tip.get("downstream_present") is False
            ):
                reason = f"a segment answers downstream of {hwi.names[-1]}"
        if reason is None:
            held = [
                hwi.names[i]
                for i, st in enumerate(hwi.raw_states)
                if st is not None and "HOLD" in st["status"]
            ]
            if held and not hwi.resume_pending:
                msg = f"segment(s) {', '.join(held)} holding (watchdog or HOLD)"
                self._rehold(state, msg)
                hwi.resume_pending = True
                self._emit(
                    "segments_held", message=msg + "; controllers re-held, resuming", segments=held
                )
        return reason
