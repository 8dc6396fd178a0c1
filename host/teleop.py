"""Manual input for the cFFC (paper Fig. 5): gamepad, keyboard or a recorded stream -> ffc.input.

An input source turns what a person does into stick *deflections* per bendable, (ux, uy) each in
[-1, 1]; the daemon's cFFC integrates ``d(kx, ky)/dt = kappa_rate_max * gain * (ux, uy)``.
:class:`Teleop` samples the current deflections and streams them (default 50 Hz) while any stick
is deflected; on release it sends one zero command (the robot stops at once); when the input
itself stops (replay ends, gamepad unplugged) it simply stops sending and the daemon's deadman
stops the motion.

Sources: :class:`GamepadSource` (Linux evdev), :class:`KeyboardSource` (terminal in cbreak mode)
and :class:`ReplaySource` (JSON lines, what the tests use). :class:`Recorder` writes the same
format from a live session, so any session can be replayed.

Recorded stream format, one JSON object per line, ``t`` in seconds from the start::

    {"t": 0.0, "rates": {"seg1": [0.5, 0.0]}}    # set these sticks (others keep their value)
    {"t": 1.2, "stop": true}                     # all sticks to zero
    {"t": 2.0, "end": true}                      # input stops here (optional: end of file too)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from host.teleop_input import (
    KEY_HELP,
    Deflection,
    GamepadSource,
    InputEvent,
    InputSource,
    KeyboardSource,
    Recorder,
    ReplaySource,
    TeleopError,
    find_gamepad,
    normalise_axis,
    parse_keys,
    parse_recording,
)

__all__ = [
    "KEY_HELP",
    "Deflection",
    "GamepadSource",
    "InputEvent",
    "InputSource",
    "KeyboardSource",
    "Recorder",
    "ReplaySource",
    "Teleop",
    "TeleopError",
    "TeleopResult",
    "find_gamepad",
    "normalise_axis",
    "parse_keys",
    "parse_recording",
]


# --------------------------------------------------------------------------- streaming
@dataclass
class TeleopResult:
    """How a session ended and what it sent."""

    reason: str  # "quit" | "end" | "lost" (the device failed: cut off) | "error"
    sent: int = 0
    zeros_sent: int = 0
    duration_s: float = 0.0
    note: str = ""

    def summary(self) -> str:
        """One line for people."""
        why = f"{self.reason}: {self.note}" if self.note else self.reason
        if self.reason == "lost" and self.note:  # the note says it: "gamepad lost: ..."
            why = self.note
        return (
            f"teleop ended ({why}) after {self.duration_s:.1f} s; {self.sent} commands, "
            f"{self.zeros_sent} stops sent"
        )


class Teleop:
    """Streams the deflections of a source through ``send`` (e.g. ``Client.ffc_input``).

    Every ``1/rate_hz`` s while any stick is deflected the full set is sent (the cFFC replaces
    its input with each message). When all sticks return to zero one zero message is sent, then
    nothing until the next deflection. ``quit`` sends zero and ends; ``end`` (the input stopped)
    and ``lost`` (the device failed; the result says so, for a failing exit status) end without
    sending, leaving the stop to the daemon's deadman.
    """

    def __init__(
        self,
        send: Callable[[dict[str, Deflection]], Any],
        rate_hz: float = 50.0,
        on_event: Callable[[InputEvent], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (0 < rate_hz <= 500):
            raise TeleopError("teleop rate must be in (0, 500] Hz")
        self.send = send
        self.period = 1.0 / rate_hz
        self.on_event = on_event
        self.clock = clock
        self.current: dict[str, Deflection] = {}

    def _deflected(self) -> bool:
        return any(x or y for x, y in self.current.values())

    def run(self, source: InputSource, max_duration: float | None = None) -> TeleopResult:
        result = TeleopResult("end")
        t_start = self.clock()
        next_tick = t_start
        stopped = True  # nothing moving yet: no zero owed
        try:
            while True:
                now = self.clock()
                if max_duration is not None and now - t_start >= max_duration:
                    result.reason, result.note = "end", "time limit"
                    break
                events = source.read(max(0.0, next_tick - now))
                finished = None
                for ev in events:
                    if self.on_event is not None:
                        self.on_event(ev)
                    if ev.kind == "rates":
                        self.current.update(ev.rates)
                    elif ev.kind == "stop":
                        self.current = {k: (0.0, 0.0) for k in self.current}
                    elif ev.kind in ("quit", "end", "lost"):
                        finished = ev
                        break
                if finished is not None:
                    result.reason, result.note = finished.kind, finished.note
                    if finished.kind == "quit" and self.current:
                        self.current = {k: (0.0, 0.0) for k in self.current}
                        self.send(dict(self.current))
                        result.zeros_sent += 1
                    break
                now = self.clock()
                if now >= next_tick:
                    if self._deflected():
                        self.send(dict(self.current))
                        result.sent += 1
                        stopped = False
                    elif not stopped:
                        self.send(dict(self.current))  # released: stop now, not at deadman
                        result.zeros_sent += 1
                        stopped = True
                    next_tick += self.period
                    if next_tick < now - self.period:  # fell behind (slow send): resync
                        next_tick = now + self.period
        finally:
            result.duration_s = self.clock() - t_start
        return result
