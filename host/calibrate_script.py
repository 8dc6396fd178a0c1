"""``ucr calibrate --script FILE``: the calibration steps as a text file, one per line.

Commands (``#`` starts a comment; angles in rad unless said; docs/commissioning.md)::

    identify [KAPPA]              wiggle the segment (default 0.5 1/m)
    straight                      bend to kappa = 0
    jog SERVO RAD                 move one servo (its zero offset moves with it)
    direction SERVO 1|-1          set a servo's direction
    check-directions [KAPPA]      bend towards / away from each tendon, fix reversed servos
    tension LOAD [STEP]           wind each tendon in to LOAD (fraction of max torque)
    bend KAPPA PHI_DEG            a test bend (1/m, degrees)
    wait SECONDS                  keep holding the current setpoint
    persist                       store the calibration on the segment (and in the robot file)

The whole file is checked before anything moves: errors are ``FILE:LINE: message``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from host.calibrate import CalibrationError, Result, Session

#: command -> (minimum, maximum) number of arguments
_ARITY = {
    "identify": (0, 1),
    "straight": (0, 0),
    "jog": (2, 2),
    "direction": (2, 2),
    "check-directions": (0, 1),
    "tension": (1, 2),
    "bend": (2, 2),
    "wait": (1, 1),
    "persist": (0, 0),
}


class ScriptError(ValueError):
    """A script line is wrong: ``FILE:LINE: message``."""


@dataclass
class Step:
    line: int
    command: str
    args: list[float]


def parse(text: str, source: str = "<script>") -> list[Step]:
    """Every step of a script, checked (names, argument counts, numbers, ranges)."""
    steps = []
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        words = line.split()
        cmd, rest = words[0].lower(), words[1:]
        where = f"{source}:{no}"
        if cmd not in _ARITY:
            raise ScriptError(f"{where}: unknown command {cmd!r} (one of {', '.join(_ARITY)})")
        lo, hi = _ARITY[cmd]
        if not lo <= len(rest) <= hi:
            want = str(lo) if lo == hi else f"{lo}..{hi}"
            raise ScriptError(f"{where}: {cmd} takes {want} argument(s), got {len(rest)}")
        try:
            args = [float(w) for w in rest]
        except ValueError:
            raise ScriptError(f"{where}: {cmd}: arguments must be numbers: {rest}") from None
        if any(not math.isfinite(a) for a in args):
            raise ScriptError(f"{where}: {cmd}: arguments must be finite")
        if cmd in ("jog", "direction") and args[0] != int(args[0]):
            raise ScriptError(f"{where}: {cmd}: the servo index must be an integer")
        if cmd == "direction" and args[1] not in (1.0, -1.0):
            raise ScriptError(f"{where}: direction must be 1 or -1")
        if cmd == "jog" and abs(args[1]) > 0.5:
            raise ScriptError(f"{where}: jog at most 0.5 rad at a time")
        if cmd == "wait" and not 0 <= args[0] <= 60:
            raise ScriptError(f"{where}: wait 0..60 s")
        steps.append(Step(no, cmd, args))
    if not steps:
        raise ScriptError(f"{source}: the script has no step")
    return steps


def run(session: Session, steps: list[Step], source: str = "<script>") -> Result | None:
    """Run the steps in order; a failing step raises CalibrationError naming its line."""
    result = None
    for st in steps:
        a = st.args
        try:
            if st.command == "identify":
                session.identify(*(a or [0.5]))
            elif st.command == "straight":
                session.move(0.0, 0.0)
            elif st.command == "jog":
                session.jog(int(a[0]), a[1])
            elif st.command == "direction":
                session.set_direction(int(a[0]), int(a[1]))
            elif st.command == "check-directions":
                session.check_directions(*(a or [0.4]))
            elif st.command == "tension":
                session.tension(*a)
            elif st.command == "bend":
                session.move(a[0], math.radians(a[1]))
                session.say(f"bend: kappa {a[0]:.3f} 1/m phi {a[1]:.1f} deg")
            elif st.command == "wait":
                session.keep(a[0])
            elif st.command == "persist":
                result = session.persist()
        except CalibrationError as exc:
            raise type(exc)(f"{source}:{st.line}: {st.command}: {exc}") from exc
    return result


def load(path: str | Path) -> list[Step]:
    p = Path(path)
    try:
        text = p.read_text()
    except OSError as exc:
        raise ScriptError(f"{p}: cannot read the script: {exc.strerror}") from None
    return parse(text, str(p))
