"""Teleop input sources: what a person does -> stick deflections per bendable, (ux, uy) each in
[-1, 1]. :class:`GamepadSource` (Linux evdev), :class:`KeyboardSource` (terminal in cbreak mode),
:class:`ReplaySource` (JSON lines, what the tests use) and :class:`Recorder` (writes the same format
from a live session). The streaming to the daemon is :mod:`host.teleop`; the recording format is
described there.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import select
import sys
import termios
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from host.api.schema import unique_keys
from host.extras import require

Deflection = tuple[float, float]


class TeleopError(RuntimeError):
    """An input source cannot be used (no device, bad recording); the message says why."""


@dataclass
class InputEvent:
    """What a source reports: new stick values, stop (all zero), quit (person ends), end (input
    stops: no more data), lost (the device failed mid-session: the session was cut off, which
    ``ucr teleop`` reports as a failure, not as an end the person chose)."""

    kind: str  # "rates" | "stop" | "quit" | "end" | "lost"
    rates: dict[str, Deflection] = field(default_factory=dict)
    note: str = ""


class InputSource(ABC):
    """Base class: ``read(timeout)`` returns the events available within ``timeout`` s."""

    names: list[str]

    @abstractmethod
    def read(self, timeout: float) -> list[InputEvent]:
        """Events that arrived within ``timeout`` s (empty list if none)."""

    def close(self) -> None:  # noqa: B027 - optional hook: most sources hold nothing to release
        """Release the device / restore the terminal."""

    def __enter__(self) -> InputSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _clip(v: float) -> float:
    return max(-1.0, min(1.0, v))


# --------------------------------------------------------------------------- replay
def parse_recording(
    lines: list[str], source: str = "<recording>"
) -> list[tuple[float, InputEvent]]:
    """Parse a JSON-lines recording into timed events; raises :class:`TeleopError` with the line."""
    events: list[tuple[float, InputEvent]] = []
    last_t = 0.0
    for n, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        where = f"{source}:{n}"
        try:  # a key given twice is refused, as in trajectory files: which one would count?
            obj = json.loads(text, object_pairs_hook=unique_keys)
        except json.JSONDecodeError as exc:
            raise TeleopError(f"{where}: not JSON ({exc})") from None
        except ValueError as exc:  # unique_keys: "duplicate key 'a' in an object"
            said = str(exc) if str(exc).startswith("duplicate key") else f"not JSON ({exc})"
            raise TeleopError(f"{where}: {said}") from None
        if not isinstance(obj, dict):
            raise TeleopError(f'{where}: expected an object like {{"t": 0.0, "rates": {{...}}}}')
        t = obj.get("t")
        if isinstance(t, bool) or not isinstance(t, int | float) or not math.isfinite(t) or t < 0:
            raise TeleopError(f"{where}: 't' (s from start) must be a number >= 0")
        if t < last_t:
            raise TeleopError(f"{where}: t = {t} s goes back in time (previous {last_t} s)")
        last_t = float(t)
        keys = set(obj) - {"t"}
        if keys == {"rates"}:
            rates = obj["rates"]
            if not isinstance(rates, dict) or not rates:
                raise TeleopError(f"{where}: 'rates' must map segment names to [ux, uy]")
            out: dict[str, Deflection] = {}
            for name, val in rates.items():
                ok = (
                    isinstance(val, list)
                    and len(val) == 2
                    and all(
                        not isinstance(v, bool)
                        and isinstance(v, int | float)
                        and math.isfinite(v)
                        and -1.0 <= v <= 1.0
                        for v in val
                    )
                )
                if not ok:
                    raise TeleopError(f"{where}: rates.{name} must be [ux, uy] within [-1, 1]")
                out[str(name)] = (float(val[0]), float(val[1]))
            events.append((float(t), InputEvent("rates", out)))
        elif keys in ({"stop"}, {"end"}, {"quit"}) and obj[next(iter(keys))] is True:
            events.append((float(t), InputEvent(next(iter(keys)))))
        else:
            raise TeleopError(
                f"{where}: expected exactly one of 'rates', 'stop': true, 'end': true, "
                f"'quit': true besides 't' (got {', '.join(sorted(keys)) or 'nothing'})"
            )
    return events


class ReplaySource(InputSource):
    """Plays a recorded stream in real time (``speed`` > 1 plays faster)."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        speed: float = 1.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        p = Path(path)
        try:
            lines = p.read_text(encoding="utf-8").splitlines()
        except OSError as exc:
            raise TeleopError(f"cannot read recording {p}: {exc.strerror or exc}") from None
        if not (speed > 0 and math.isfinite(speed)):
            raise TeleopError("replay speed must be a positive number")
        self.events = parse_recording(lines, str(p))
        if not self.events:
            raise TeleopError(f"{p}: the recording has no events")
        self.names = sorted({n for _, e in self.events for n in e.rates})
        self.speed = speed
        self.clock = clock
        self._t0: float | None = None
        self._i = 0

    def read(self, timeout: float) -> list[InputEvent]:
        now = self.clock()
        if self._t0 is None:
            self._t0 = now
        if self._i >= len(self.events):
            return [InputEvent("end", note="end of recording")]
        due = self._t0 + self.events[self._i][0] / self.speed
        if due > now:
            time.sleep(min(timeout, due - now))
            now = self.clock()
        out = []
        while self._i < len(self.events) and self._t0 + self.events[self._i][0] / self.speed <= now:
            out.append(self.events[self._i][1])
            self._i += 1
        return out


# --------------------------------------------------------------------------- keyboard
KEY_HELP = (
    "keys: w/s or Up/Down bend +y/-y, a/d or Left/Right bend -x/+x, 1-9 select segment, "
    "+/- speed, space stop, q quit"
)
_ARROWS = {b"A": "up", b"B": "down", b"C": "right", b"D": "left"}
_KEY_AXIS = {  # key -> (axis index, sign)
    "w": (1, 1.0),
    "up": (1, 1.0),
    "s": (1, -1.0),
    "down": (1, -1.0),
    "d": (0, 1.0),
    "right": (0, 1.0),
    "a": (0, -1.0),
    "left": (0, -1.0),
}


def parse_keys(data: bytes) -> list[str]:
    """Split terminal input bytes into key names ("w", "up", "space", "3", ...)."""
    keys: list[str] = []
    i = 0
    while i < len(data):
        b = data[i : i + 1]
        if b == b"\x1b" and data[i + 1 : i + 2] in (b"[", b"O") and i + 2 < len(data):
            keys.append(_ARROWS.get(data[i + 2 : i + 3], "esc"))
            i += 3
            continue
        if b == b" ":
            keys.append("space")
        elif b == b"\x03":
            keys.append("ctrl-c")
        else:
            keys.append(b.decode("latin-1").lower())
        i += 1
    return keys


class KeyboardSource(InputSource):
    """Terminal keys: a held key (auto-repeat) keeps its axis deflected; release -> zero after
    ``hold_s`` (longer than the terminal's initial repeat delay). The terminal is put in cbreak
    mode (no echo, no line buffering) and restored by :meth:`close`."""

    def __init__(
        self,
        names: list[str],
        fd: int | None = None,
        hold_s: float = 0.6,
        gain: float = 0.5,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not names:
            raise TeleopError("the robot has no bendable segments to drive")
        self.names = list(names)
        self.fd = sys.stdin.fileno() if fd is None else fd
        self.hold_s = hold_s
        self.gain = gain
        self.clock = clock
        self.selected = 0
        self._axis_until = [0.0, 0.0]
        self._axis_value = [0.0, 0.0]
        self._saved: Any = None
        if os.isatty(self.fd):
            self._saved = termios.tcgetattr(self.fd)
            tty.setcbreak(self.fd)

    def close(self) -> None:
        if self._saved is not None:
            termios.tcsetattr(self.fd, termios.TCSADRAIN, self._saved)
            self._saved = None

    def _current(self) -> dict[str, Deflection]:
        out = {n: (0.0, 0.0) for n in self.names}
        out[self.names[self.selected]] = (self._axis_value[0], self._axis_value[1])
        return out

    def read(self, timeout: float) -> list[InputEvent]:
        events: list[InputEvent] = []
        ready, _, _ = select.select([self.fd], [], [], max(0.0, timeout))
        now = self.clock()
        changed = False
        if ready:
            data = os.read(self.fd, 64)
            if not data:
                return [InputEvent("end", note="keyboard input closed")]
            for key in parse_keys(data):
                if key in ("q", "ctrl-c"):
                    return [*events, InputEvent("quit")]
                if key == "space":
                    self._axis_value = [0.0, 0.0]
                    self._axis_until = [0.0, 0.0]
                    events.append(InputEvent("stop"))
                elif key in _KEY_AXIS:
                    axis, sign = _KEY_AXIS[key]
                    self._axis_value[axis] = sign * self.gain
                    self._axis_until[axis] = now + self.hold_s
                    changed = True
                elif key.isdigit() and 1 <= int(key) <= len(self.names):
                    self.selected = int(key) - 1
                    self._axis_value = [0.0, 0.0]
                    events.append(
                        InputEvent(
                            "rates", self._current(), note=f"segment {self.names[self.selected]}"
                        )
                    )
                elif key in ("+", "="):
                    self.gain = min(1.0, round(self.gain + 0.1, 2))
                    events.append(InputEvent("rates", self._current(), note=f"speed {self.gain}"))
                elif key in ("-", "_"):
                    self.gain = max(0.1, round(self.gain - 0.1, 2))
                    events.append(InputEvent("rates", self._current(), note=f"speed {self.gain}"))
        for axis in (0, 1):
            if self._axis_value[axis] and now > self._axis_until[axis]:
                self._axis_value[axis] = 0.0  # key released (no auto-repeat any more)
                changed = True
        if changed:
            events.append(InputEvent("rates", self._current()))
        return events


# --------------------------------------------------------------------------- gamepad
def _evdev() -> Any:
    """evdev (the 'gamepad' extra, Linux only) is imported when a gamepad is actually used;
    without it the user gets one line saying what to install (:class:`MissingPart`)."""
    if not sys.platform.startswith("linux"):
        raise TeleopError("gamepad input uses Linux evdev; on this system use --keyboard")
    return require("evdev", extra="gamepad")


def find_gamepad() -> str:
    """Path of the first input device with two analog sticks (ABS_X/Y and ABS_RX/RY)."""
    evdev = _evdev()
    ecodes = evdev.ecodes
    need = {ecodes.ABS_X, ecodes.ABS_Y, ecodes.ABS_RX, ecodes.ABS_RY}
    paths = evdev.list_devices()
    for path in sorted(paths):
        try:
            dev = evdev.InputDevice(path)
        except OSError:
            continue
        try:
            axes = {code for code, _info in dev.capabilities().get(ecodes.EV_ABS, [])}
            if need <= axes:
                return path
        finally:
            dev.close()
    hint = "" if paths else " (no readable /dev/input/event*: are you in the 'input' group?)"
    raise TeleopError(f"no gamepad with two analog sticks found{hint}; try --keyboard")


def normalise_axis(value: int, lo: int, hi: int, deadzone: float) -> float:
    """Raw evdev axis value -> [-1, 1] around the centre, deadzone removed and rescaled."""
    if hi <= lo:
        return 0.0
    centre = (lo + hi) / 2.0
    v = _clip((value - centre) / ((hi - lo) / 2.0))
    mag = abs(v)
    if mag <= deadzone:
        return 0.0
    return math.copysign((mag - deadzone) / (1.0 - deadzone), v)


class GamepadSource(InputSource):
    """Linux gamepad through evdev. Left stick bends the selected segment, right stick the next
    one; LB/RB (BTN_TL/BTN_TR) move the selection; while A (BTN_SOUTH) is held every stick
    reads zero (hold); START quits. Stick up = +y, right = +x."""

    def __init__(
        self, names: list[str], path: str | None = None, deadzone: float = 0.1, device: Any = None
    ) -> None:
        """``device``: an already open evdev ``InputDevice`` (or an object with the same
        ``capabilities()``, ``fd``, ``read()``, ``name``, ``close()``); else ``path`` or the
        first gamepad found is opened."""
        if not names:
            raise TeleopError("the robot has no bendable segments to drive")
        evdev = _evdev()
        self._ecodes = evdev.ecodes
        self.names = list(names)
        if device is not None:
            self.dev = device
            self.path = path or getattr(device, "path", "<device>")
        else:
            self.path = path or find_gamepad()
            try:
                self.dev = evdev.InputDevice(self.path)
            except OSError as exc:
                raise TeleopError(f"cannot open {self.path}: {exc.strerror or exc}") from None
        e = self._ecodes
        self._ranges: dict[int, tuple[int, int]] = {}
        for code, info in self.dev.capabilities().get(e.EV_ABS, []):
            self._ranges[code] = (info.min, info.max)
        if not {e.ABS_X, e.ABS_Y} <= set(self._ranges):
            self.dev.close()
            raise TeleopError(f"{self.path} ({self.dev.name}) has no analog stick")
        self.deadzone = deadzone
        self.selected = 0
        self.holding = False
        self._axes = {e.ABS_X: 0.0, e.ABS_Y: 0.0, e.ABS_RX: 0.0, e.ABS_RY: 0.0}

    @property
    def device_name(self) -> str:
        return f"{self.dev.name} ({self.path})"

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.dev.close()

    def _current(self) -> dict[str, Deflection]:
        e = self._ecodes
        out = {n: (0.0, 0.0) for n in self.names}
        if self.holding:
            return out
        out[self.names[self.selected]] = (self._axes[e.ABS_X], -self._axes[e.ABS_Y])
        if self.selected + 1 < len(self.names):
            out[self.names[self.selected + 1]] = (self._axes[e.ABS_RX], -self._axes[e.ABS_RY])
        return out

    def read(self, timeout: float) -> list[InputEvent]:
        e = self._ecodes
        try:
            ready, _, _ = select.select([self.dev.fd], [], [], max(0.0, timeout))
            if not ready:
                return []
            raw = list(self.dev.read())
        except BlockingIOError:
            return []
        except OSError as exc:
            return [InputEvent("lost", note=f"gamepad lost: {exc.strerror or exc}")]
        changed = False
        for ev in raw:
            if ev.type == e.EV_ABS and ev.code in self._axes:
                lo, hi = self._ranges.get(ev.code, (-32768, 32767))
                self._axes[ev.code] = normalise_axis(ev.value, lo, hi, self.deadzone)
                changed = True
            elif ev.type == e.EV_KEY:
                if ev.code == e.BTN_START and ev.value == 1:
                    return [InputEvent("quit")]
                if ev.code == e.BTN_SOUTH:
                    self.holding = ev.value != 0
                    changed = True
                elif ev.code == e.BTN_TR and ev.value == 1:
                    self.selected = min(self.selected + 1, len(self.names) - 1)
                    changed = True
                elif ev.code == e.BTN_TL and ev.value == 1:
                    self.selected = max(self.selected - 1, 0)
                    changed = True
        return [InputEvent("rates", self._current())] if changed else []


# --------------------------------------------------------------------------- recording
class Recorder(InputSource):
    """Wraps a source and writes its events as a replayable JSON-lines recording."""

    def __init__(
        self, inner: InputSource, out: IO[str], clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.inner = inner
        self.names = inner.names
        self.out = out
        self.clock = clock
        self._t0 = clock()

    def read(self, timeout: float) -> list[InputEvent]:
        events = self.inner.read(timeout)
        t = round(self.clock() - self._t0, 4)
        for ev in events:
            if ev.kind == "rates":
                line: dict[str, Any] = {
                    "t": t,
                    "rates": {k: [round(v[0], 4), round(v[1], 4)] for k, v in ev.rates.items()},
                }
            else:  # a lost device ends the recording's input there, as end does
                line = {"t": t, "end" if ev.kind == "lost" else ev.kind: True}
            self.out.write(json.dumps(line) + "\n")
        self.out.flush()
        return events

    def close(self) -> None:
        self.inner.close()
