"""Manual input for the cFFC (paper Fig. 5): gamepad, keyboard or a recorded stream -> ffc.input.

An input source turns what a person does into stick *deflections* per bendable, (ux, uy) each in
[-1, 1]; the daemon's cFFC integrates ``d(kx, ky)/dt = kappa_rate_max * gain * (ux, uy)``.
:class:`Teleop` samples the current deflections and streams them (default 50 Hz) while any stick
is deflected; on release it sends one zero command (the robot stops at once); when the input
itself stops (replay ends, gamepad unplugged) it simply stops sending and the daemon's deadman
stops the motion. A refusal the caller calls transient (``unavailable``: the chain lost or being
rebuilt) does not end the session: nothing deflected is sent again until every stick has been
centred (re-arm), so a robot that comes back never resumes motion from a stick held meanwhile.

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
    refused: int = 0  # commands the daemon refused for a transient reason (the session went on)

    def summary(self) -> str:
        """One line for people."""
        why = f"{self.reason}: {self.note}" if self.note else self.reason
        if self.reason == "lost" and self.note:  # the note says it: "gamepad lost: ..."
            why = self.note
        line = (
            f"teleop ended ({why}) after {self.duration_s:.1f} s; {self.sent} commands, "
            f"{self.zeros_sent} stops sent"
        )
        return line + (f"; {self.refused} refused by the daemon" if self.refused else "")


class Teleop:
    """Streams the deflections of a source through ``send`` (e.g. ``Client.ffc_input``).

    Every ``1/rate_hz`` s while any stick is deflected the full set is sent (the cFFC replaces
    its input with each message). When all sticks return to zero one zero message is sent, then
    nothing until the next deflection. ``quit`` sends zero and ends; ``end`` (the input stopped)
    and ``lost`` (the device failed; the result says so, for a failing exit status) end without
    sending, leaving the stop to the daemon's deadman.

    ``transient(exc)``: whether an exception of ``send`` is a refusal to ride through (the
    daemon cannot act *now*); any other exception ends the session. After a transient refusal
    no deflection is sent until every stick is centred (``on_note`` says so, once per refusal
    streak and once when input goes through again); the zero of a release is still sent.
    """

    def __init__(
        self,
        send: Callable[[dict[str, Deflection]], Any],
        rate_hz: float = 50.0,
        on_event: Callable[[InputEvent], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        transient: Callable[[BaseException], bool] | None = None,
        on_note: Callable[[str], None] | None = None,
    ) -> None:
        if not (0 < rate_hz <= 500):
            raise TeleopError("teleop rate must be in (0, 500] Hz")
        self.send = send
        self.period = 1.0 / rate_hz
        self.on_event = on_event
        self.clock = clock
        self.transient = transient
        self.on_note = on_note
        self.current: dict[str, Deflection] = {}
        self.rearm = False  # a transient refusal happened: centre every stick before driving

    def _note(self, text: str) -> None:
        if self.on_note is not None:
            self.on_note(text)

    def _send(self, rates: dict[str, Deflection], result: TeleopResult, motion: bool) -> bool:
        """Send; False after a transient refusal (counted; a refused ``motion`` command is said
        once per streak and re-arms; a refused zero needs nothing: nothing was moving then)."""
        try:
            self.send(rates)
        except Exception as exc:
            if self.transient is None or not self.transient(exc):
                raise
            result.refused += 1
            if motion and not self.rearm:
                self._note(
                    f"daemon refused the input ({exc}); nothing moves: centre every stick "
                    "to drive again once it accepts input"
                )
            self.rearm = self.rearm or motion
            return False
        return True

    def _deflected(self) -> bool:
        return any(x or y for x, y in self.current.values())

    def run(self, source: InputSource, max_duration: float | None = None) -> TeleopResult:
        """Stream ``source``'s input until it ends (or ``max_duration`` s). Every run starts
        with every stick centred: a stick held when the last run ended moves nothing now."""
        self.current = {}
        self.rearm = False
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
                        if self._send(dict(self.current), result, False):
                            result.zeros_sent += 1
                    break
                now = self.clock()
                if now >= next_tick:
                    if self._deflected():
                        if not self.rearm and self._send(dict(self.current), result, True):
                            result.sent += 1
                        stopped = False
                    else:
                        if not stopped:  # released: stop now, not at deadman
                            if self._send(dict(self.current), result, False):
                                result.zeros_sent += 1
                            stopped = True
                        if self.rearm:
                            self.rearm = False
                            self._note("sticks centred: the next deflection is sent again")
                    next_tick += self.period
                    if next_tick < now - self.period:  # fell behind (slow send): resync
                        next_tick = now + self.period
        finally:
            result.duration_s = self.clock() - t_start
        return result
