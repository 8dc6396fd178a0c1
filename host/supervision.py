"""Per-cycle supervision of the chain (ACROSET SMCS), beside the control path: turns segment
EVENTs into readable events, notices a topology change (event, silent segment, a segment behind
the tip, a segment that applied another position's setpoint) and handles segments that hold on
their own (watchdog, HOLD or FAULT). Segments in FAULT are listed in :attr:`Supervisor.faults`
until their STATE shows the fault cleared (only an explicit CLEAR_FAULT does that).

It decides and reports; it does not rebuild. :meth:`Supervisor.check` returns the reason for a
topology change (and :attr:`Supervisor.position`, the chain index it concerns), and the topology
follower acts on it. Events carry 1-based positions, as every position a user sees.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from host.config import WatchdogConfig
from host.controllers.base import RobotState
from host.hwi import HardwareInterface
from host.positions import label
from protocol.constants import FAULT_NAMES

TOPOLOGY_EVENTS = {"DOWNSTREAM_UP", "DOWNSTREAM_DOWN", "BOOT"}


def gap_cycles(period: float, watchdog: Any) -> int:
    """Consecutive cycles without a STATE that make a gap (docs/daemon.md): the silence limit
    of supervision (``missed_cycles`` and ``silence_s``), so a gap and a silent segment are one
    notion."""
    return max(2, watchdog.missed_cycles, math.ceil(watchdog.silence_s / period - 1e-9))


def describe_event(ev: dict, descriptors: list[dict]) -> str:
    """One readable line for a segment EVENT (which segment, what happened)."""
    pos, name, detail = ev.get("position"), ev.get("name", ""), ev.get("detail")
    who = label(pos)
    if isinstance(pos, int) and pos < len(descriptors):
        who = f"{descriptors[pos].get('name') or '?'} ({label(pos)})"
    if name == "LIMIT_CLAMPED" and isinstance(detail, int):
        bits = [b for i, b in enumerate(("kappa", "rate", "servo range")) if detail >> i & 1]
        what = f"setpoint clamped by the segment ({', '.join(bits) or detail})"
    elif name == "FAULT":
        what = (
            f"FAULT {FAULT_NAMES.get(detail, detail)}: {ev.get('text') or 'no reason given'}; "
            "it holds until the fault is cleared (ucr clear-fault)"
        )
    elif name == "FAULT_CLEARED":
        what = f"fault {FAULT_NAMES.get(detail, detail)} cleared: holding until resumed"
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


def _after(t: Any, ref: Any) -> bool:
    """Segment time ``t`` (ms mod 2**30) is later than ``ref`` (unknown times: yes)."""
    if not isinstance(t, int) or not isinstance(ref, int):
        return True
    return 0 < (t - ref) % (1 << 30) < (1 << 29)


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


def _one_based(position: Any) -> Any:
    """A chain index as events carry it: counted from 1 (anything else as is)."""
    if isinstance(position, int) and not isinstance(position, bool):
        return position + 1
    return position


def _concerned(event: str, position: Any) -> int | None:
    """The chain index a topology event concerns: the segment that booted, or the neighbour
    behind the segment whose downstream port changed."""
    if not isinstance(position, int):
        return None
    return position if event == "BOOT" else position + 1


class Supervisor:
    """SMCS for one loop. ``emit_event(event, message, **fields)`` reports;
    ``rehold(state, message)`` makes the controllers hold the measured state."""

    def __init__(
        self,
        watchdog: WatchdogConfig,
        period: float,
        emit_event: Callable[..., None],
        rehold: Callable[..., None],
    ):
        self.watchdog = watchdog
        self.period = period
        self._emit = emit_event
        self._rehold = rehold
        self.silent = False  # the last reason was silence (no event): verify before aborting
        self.position: int | None = None  # 0-based index of the segment the last reason concerns
        self.rejoin = False  # the last reason lies only beyond the tip (a segment rejoins)
        # segments in FAULT: name -> {position, code, name, text}
        self.faults: dict[str, dict[str, Any]] = {}

    def check(
        self,
        hwi: HardwareInterface,
        state: RobotState,
        events: list[dict],
        descriptors: list[dict],
        rejoin_ready: Callable[[bool], bool] | None = None,
    ) -> str | None:
        """Return a reason when the topology changed; handle unexpected HOLDs.

        What lies only beyond the tip (a probe answered there, DOWNSTREAM_UP from the tip, a
        BOOT beyond it) is a *rejoin* (:attr:`rejoin`), taken only when no other reason came in
        the same cycle and ``rejoin_ready(probed)`` agrees (hysteresis, docs/daemon.md "Rejoin
        by itself"; ``probed``: a probe answered). A deferred rejoin suppresses nothing else:
        a BOOT, a cut or a misaddressed STATE in the same batch is the reason, and the
        unexpected-HOLD re-hold runs."""
        reason = None
        self.silent = False
        self.position = None
        self.rejoin = False
        tip = len(hwi.names)
        beyond: tuple[str, int] | None = None  # the first rejoin reason (reason, position)
        for ev in events:
            name = ev.get("name", "")
            extra = {"text": ev["text"]} if "text" in ev else {}
            self._emit(
                name.lower(),
                message=describe_event(ev, descriptors),
                position=_one_based(ev.get("position")),
                detail=ev.get("detail"),
                segment_t_ms=ev.get("t_ms"),
                source="segment",
                **extra,
            )
            if name == "FAULT":
                self._note_fault(hwi, ev)
            if reason is None and is_news(name, ev.get("position"), descriptors):
                why = f"{name} from {label(ev.get('position'))}"
                at = _concerned(name, ev.get("position"))
                if at != tip:
                    reason, self.position = why, at
                elif beyond is None:
                    beyond = (why, at)
        self._track_faults(hwi)
        if reason is None:
            reason = self._misaddressed(hwi)
        if reason is None:
            wd = self.watchdog
            limit = max(wd.missed_cycles, math.ceil(wd.silence_s / self.period))
            silent = [i for i, m in enumerate(hwi.missing) if m >= limit]
            if silent:
                names = ", ".join(f"{hwi.names[i]} ({label(i)})" for i in silent)
                reason = f"no STATE from {names} for {limit} cycles"
                self.silent = True
                self.position = silent[0]
        probed = bool(getattr(hwi, "extra_states", None))
        if reason is None and beyond is None and probed:
            last = hwi.names[-1] if hwi.names else "the host"
            beyond = (f"{len(hwi.extra_states)} segment(s) answer beyond {last} (rejoin)", tip)
        if reason is None and beyond is None and hwi.raw_states and descriptors:
            st = hwi.raw_states[-1]
            known_tip = descriptors[len(hwi.names) - 1]
            if (
                st is not None
                and "DOWNSTREAM" in st["status"]
                and known_tip.get("downstream_present") is False
            ):
                beyond = (f"a segment answers downstream of {hwi.names[-1]}", tip)
        if reason is None and beyond is not None and (rejoin_ready is None or rejoin_ready(probed)):
            reason, self.position = beyond
            self.rejoin = True
        if reason is None:
            held = [
                hwi.names[i]
                for i, st in enumerate(hwi.raw_states)
                if st is not None and "HOLD" in st["status"]
            ]
            if held and not hwi.resume_pending:
                msg = f"segment(s) {', '.join(held)} holding (watchdog, HOLD or FAULT)"
                self._rehold(state, msg, segments=held)
                hwi.resume_pending = True
                self._emit(
                    "segments_held", message=msg + "; controllers re-held, resuming", segments=held
                )
        return reason

    # -- FAULT and addressing ---------------------------------------------------------------------
    def _note_fault(self, hwi: HardwareInterface, ev: dict) -> None:
        pos = ev.get("position")
        if isinstance(pos, int) and 0 <= pos < len(hwi.names):
            code = ev.get("detail")
            self.faults[hwi.names[pos]] = {
                "position": pos + 1,  # counted from 1, like every position a user sees
                "code": code,
                "name": FAULT_NAMES.get(code, f"FAULT_{code}"),
                "text": ev.get("text", ""),
                "t_ms": ev.get("t_ms"),  # segment clock of the report
            }

    def _track_faults(self, hwi: HardwareInterface) -> None:
        """Keep :attr:`faults` in step with the FAULT status bit of every STATE."""
        for i, st in enumerate(hwi.raw_states):
            if st is None or i >= len(hwi.names):
                continue
            name = hwi.names[i]
            if "FAULT" in st["status"]:
                if name not in self.faults:  # the FAULT event not (yet) seen: the bit says it
                    self.faults[name] = {
                        "position": i + 1,
                        "code": None,
                        "name": "FAULT",
                        "text": "",
                        "t_ms": st.get("t_ms"),
                    }
            elif name in self.faults and _after(st.get("t_ms"), self.faults[name]["t_ms"]):
                del self.faults[name]  # a STATE made after the report shows it cleared

    def _misaddressed(self, hwi: HardwareInterface) -> str | None:
        """A STATE whose applied position (key 9) is not its own: that segment applied another
        segment's setpoint. Reported as a reason, so the chain is held and rediscovered."""
        for i, st in enumerate(hwi.raw_states):
            applied = None if st is None else st.get("applied_position")
            if applied is not None and applied != i:
                name = hwi.names[i] if i < len(hwi.names) else label(i)
                msg = (
                    f"{name} ({label(i)}) applied the setpoint of {label(applied)}: "
                    "misaddressed SYNC"
                )
                self._emit(
                    "misaddressed",
                    message=msg + "; holding",
                    position=i + 1,  # 1-based, like every position a user sees
                    applied=_one_based(applied),
                )
                self.position = i
                return msg
        return None
