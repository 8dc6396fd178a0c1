"""``ucr calibrate``: the calibration steps of one segment over the chain (docs/commissioning.md).

Calibration talks to the chain directly (the port is opened exclusively, so the daemon must be
stopped): it is a bench step with one operator, it changes the segment's zero offsets while the
segment runs, and every motion it makes goes through the firmware's one motion path anyway. It
commands only (kappa, phi) setpoints by SYNC (limits, curvature slew and servo speed applied by
the segment, docs/firmware.md) and changes zero offsets and directions by CALIBRATE only while the
segment holds; the motion that follows starts from the measured position. A servo jog is a zero
offset change at kappa = 0: the servo travels there at servo speed. Any other segment of the chain
gets no setpoint (it holds). ``stop()`` (a key, Ctrl-C) sends HOLD at once and ends all motion;
the segment's watchdog holds it too if this process dies. Each step is logged to ``ucr.audit``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from host.positions import label
from protocol import calibration as cal
from protocol.constants import T_CALIBRATE, T_CALIBRATION

audit = logging.getLogger("ucr.audit")

P_SERVO_TELEMETRY = 22
CYCLE_S = 0.02  # SYNC period while calibrating (50 Hz; the watchdog is >= 10x longer)
MISSES = 5  # SYNC answers missed in a row before a step fails (and the segment is held)


class CalibrationError(RuntimeError):
    """A step could not be done (the message says why and what to do)."""


class Stopped(CalibrationError):
    """The operator stopped (key or Ctrl-C): the segment was told to HOLD."""


@dataclass
class Result:
    """What calibration found: per servo zero offset (rad) and direction, and the notes."""

    zero_offsets: list[float]
    directions: list[int]
    notes: list[str] = field(default_factory=list)


class Session:
    """Calibrate the segment at ``position`` of a chain of ``count`` (a ``host.link.ChainLink``).

    ``say`` receives one line per step (the CLI prints it, the TUI shows it)."""

    def __init__(
        self,
        link: Any,
        position: int,
        count: int,
        descriptor: dict,
        say: Callable[[str], None] = print,
    ) -> None:
        self.link = link
        self.who = f"the segment at {label(position)}"  # for messages: counted from 1
        self.position = position
        self.count = count
        self.desc = descriptor
        self.uid = descriptor.get("uid")
        self.say = say
        self.angles = list(descriptor.get("tendon_angles") or [])
        self.n = len(self.angles)
        self.setpoint = (0.0, 0.0)
        self.state: dict | None = None
        self._stop = threading.Event()
        got = self.calibration(cal.ACTION_READ)
        self.zeros = got["zero_offsets"]
        self.dirs = got["directions"]

    # -- chain access ---------------------------------------------------------------------------
    def calibration(self, action: int, zeros=None, dirs=None) -> dict:
        """CALIBRATE ``action``; the segment's CALIBRATION answer, decoded."""
        payload = cal.calibrate_payload(action, zeros, dirs, self.uid)
        try:
            reply = self.link.request(self.position, T_CALIBRATE, payload, T_CALIBRATION, 1.0)
            return cal.decode_calibration(reply)
        except ValueError as exc:  # LinkError is a RuntimeError; a bad reply a ValueError
            raise CalibrationError(f"{self.who}: bad CALIBRATION reply: {exc}") from exc

    def stop(self) -> None:
        """Hold now (from any thread): HOLD to the segment, no motion until ``resume()``."""
        self._stop.set()
        try:
            self.link.hold(self.position)
        finally:
            audit.info(
                "calibrate: HOLD segment at position %d (%s) by the operator",
                self.position + 1,
                self.uid,
            )

    def resume(self) -> None:
        self._stop.clear()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def _sync(self) -> dict:
        if self._stop.is_set():
            raise Stopped("stopped: the segment holds")
        sps: list[tuple[float, float] | None] = [None] * self.count
        sps[self.position] = self.setpoint
        st = None
        for _ in range(MISSES):  # a lost answer (a loaded host) is retried, never skipped over
            states = self.link.sync(sps, timeout=0.3, expected=self.count, resume=True)
            st = states[self.position] if self.position < len(states) else None
            if st is not None:
                break
        if st is None:
            self.stop()
            raise CalibrationError(f"{self.who} did not answer {MISSES} SYNCs")
        bad = {"FAULT", "SERVO_FAULT", "UNCONFIGURED"} & set(st.get("status", ()))
        if bad:
            self.stop()
            raise CalibrationError(f"{self.who} reports {', '.join(sorted(bad))}")
        self.state = st
        return st

    def keep(self, seconds: float) -> None:
        """Keep commanding the current setpoint for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._sync()
            time.sleep(CYCLE_S)

    def settle(self, timeout: float = 8.0) -> dict:
        """Command the setpoint until the servos stopped moving (or ``timeout`` s)."""
        last: list[float] | None = None
        quiet = 0
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            st = self._sync()
            joints = st.get("servo_angles") or []
            pairs = zip(joints, last or [], strict=False)
            if last is not None and all(abs(a - b) < 2e-4 for a, b in pairs):
                quiet += 1
                if quiet >= 5:
                    return st
            else:
                quiet = 0
            last = joints
            time.sleep(CYCLE_S)
        raise CalibrationError(f"{self.who} did not settle within {timeout:.0f} s")

    def loads(self) -> list[float | None]:
        """Load (fraction of max torque) per servo; None where the servo does not report it."""
        tel = self.link.param_get(self.position, P_SERVO_TELEMETRY, self.uid, timeout=0.5)
        out: list[float | None] = []
        for t in tel if isinstance(tel, list) else []:
            ok = isinstance(t, list) and len(t) == 3 and isinstance(t[2], (int, float))
            out.append(float(t[2]) if ok else None)
        return out + [None] * (self.n - len(out))

    # -- steps ----------------------------------------------------------------------------------
    def move(self, kappa: float, phi: float) -> dict:
        """Bend to (kappa 1/m, phi rad) and wait until there (the segment limits and slews)."""
        self.setpoint = (float(kappa), float(phi))
        audit.info(
            "calibrate: segment at position %d setpoint kappa=%.4f phi=%.4f",
            self.position + 1,
            kappa,
            phi,
        )
        return self.settle()

    def apply(self, zeros: list[float], dirs: list[int]) -> None:
        """Run a new calibration now: HOLD, CALIBRATE apply, then motion resumes from there."""
        zeros = [round(z, 4) for z in zeros]
        self.link.hold(self.position)
        got = self.calibration(cal.ACTION_APPLY, zeros, dirs)
        self.zeros, self.dirs = got["zero_offsets"], got["directions"]
        audit.info(
            "calibrate: segment at position %d applied zeros=%s dirs=%s",
            self.position + 1,
            zeros,
            dirs,
        )

    def identify(self, kappa: float = 0.5, times: int = 2) -> None:
        """A small wiggle (bend one way, the other, straight) to see which segment this is."""
        self.say(f"identify: {self.who} ({self.uid}) wiggles")
        for _ in range(times):
            self.move(kappa, 0.0)
            self.move(kappa, math.pi)
        self.move(0.0, 0.0)

    def jog(self, servo: int, delta: float) -> None:
        """Move servo ``servo`` by ``delta`` rad of its raw angle (its zero moves with it)."""
        self._servo(servo)
        zeros = list(self.zeros)
        zeros[servo] += delta
        self.apply(zeros, self.dirs)
        self.move(0.0, 0.0)
        self.say(f"jog: servo {servo} by {delta:+.3f} rad, zero now {self.zeros[servo]:+.4f} rad")

    def set_direction(self, servo: int, direction: int) -> None:
        self._servo(servo)
        if direction not in (1, -1):
            raise CalibrationError("direction must be 1 or -1")
        dirs = list(self.dirs)
        dirs[servo] = direction
        self.apply(self.zeros, dirs)
        self.say(f"direction: servo {servo} set to {direction:+d}")

    def check_directions(self, kappa: float = 0.4, min_change: float = 0.02) -> list[int]:
        """Bend towards each tendon and away from it; its servo's load must rise towards it.

        A reversed servo unwinds its tendon when the segment means to pull it: its load falls
        where it should rise. Found reversals are applied (RAM) and returned as servo indexes."""
        self.move(0.0, 0.0)
        reversed_: list[int] = []
        for i, sigma in enumerate(self.angles):
            self.move(kappa, sigma)
            towards = self.loads()[i]
            self.move(kappa, sigma + math.pi)
            away = self.loads()[i]
            self.move(0.0, 0.0)
            if towards is None or away is None:
                self.say(f"direction: servo {i} reports no load: check it by eye")
                continue
            change = towards - away
            if change >= min_change:
                self.say(f"direction: servo {i} ok (load {away:.2f} -> {towards:.2f})")
            elif change <= -min_change:
                self.say(f"direction: servo {i} REVERSED (load {away:.2f} -> {towards:.2f})")
                reversed_.append(i)
            else:
                raise CalibrationError(
                    f"servo {i}: no load response to a bend (load {away:.2f} / {towards:.2f}): "
                    f"its tendon is slack; jog it in (`jog {i} <rad>`) and check again"
                )
        if reversed_:
            dirs = [-d if i in reversed_ else d for i, d in enumerate(self.dirs)]
            self.apply(self.zeros, dirs)
            self.move(0.0, 0.0)
        return reversed_

    def tension(self, threshold: float, step: float = 0.01, travel: float = 0.6) -> None:
        """Wind each tendon in at kappa = 0 until its servo's load reaches ``threshold``; that
        position becomes the zero (straight, equally taut). Servos without load are skipped."""
        if not 0.0 < threshold < 0.8:
            raise CalibrationError("tension threshold must be in (0, 0.8) of max torque")
        if not 0.0 < step <= 0.1:
            raise CalibrationError("tension step must be in (0, 0.1] rad")
        self.move(0.0, 0.0)
        for i in range(self.n):
            load = self.loads()[i]
            if load is None:
                self.say(f"tension: servo {i} reports no load, skipped (tension it by hand)")
                continue
            moved = 0.0
            while load >= threshold:  # too tight: let it out first, then come back up
                moved += self._wind(i, -step)
                load = self._load(i)
                if abs(moved) > travel:
                    raise CalibrationError(
                        f"servo {i}: load stays {load:.2f} unwinding {travel} rad"
                    )
            while load < threshold:
                moved += self._wind(i, step)
                load = self._load(i)
                if abs(moved) > travel:
                    raise CalibrationError(
                        f"servo {i}: load {load:.2f} below {threshold} after winding {travel} rad "
                        "in: is its tendon attached, its direction right (`check-directions`)?"
                    )
            self.say(f"tension: servo {i} at load {load:.2f}, zero {self.zeros[i]:+.4f} rad")

    def _wind(self, i: int, delta: float) -> float:
        zeros = list(self.zeros)
        zeros[i] += self.dirs[i] * delta  # + winds the tendon in (docs/firmware.md)
        self.apply(zeros, self.dirs)
        self.move(0.0, 0.0)
        return delta

    def _load(self, i: int) -> float:
        v = self.loads()[i]
        if v is None:
            raise CalibrationError(f"servo {i} stopped reporting its load")
        return v

    def persist(self) -> Result:
        """Store the running calibration on the segment (survives a reboot)."""
        self.move(0.0, 0.0)
        self.link.hold(self.position)
        got = self.calibration(cal.ACTION_PERSIST, self.zeros, self.dirs)
        if not got["stored"]:
            raise CalibrationError("the segment did not confirm the stored calibration")
        audit.info(
            "calibrate: segment at position %d persisted %s %s",
            self.position + 1,
            self.zeros,
            self.dirs,
        )
        self.say(
            "persist: stored on the segment: zeros "
            + ", ".join(f"{z:+.4f}" for z in got["zero_offsets"])
            + " rad, directions "
            + ", ".join(f"{d:+d}" for d in got["directions"])
        )
        return Result(got["zero_offsets"], got["directions"])

    def _servo(self, i: int) -> None:
        if not isinstance(i, int) or not 0 <= i < self.n:
            raise CalibrationError(f"servo index must be 0..{self.n - 1}, got {i!r}")
