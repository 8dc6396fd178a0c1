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

The whole file is checked before anything moves, and every error is reported at once, one
``FILE:LINE: message`` each. :func:`parse` checks what needs no segment (names, counts, numbers,
jog <= 0.5 rad, LOAD in (0, 0.8), STEP in (0, 0.1] rad, wait 0..60 s, KAPPA >= 0);
:func:`check_segment` then, with the segment found, refuses a KAPPA beyond its kappa_max (the
segment would clamp it and report a bend it never made) and a servo index it does not have.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from host.calibrate import CalibrationError, Result, Session
from host.errors import not_utf8

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


#: commands whose first argument is a curvature (1/m, 0..kappa_max)
_KAPPA_ARG = ("identify", "check-directions", "bend")
#: ``tension LOAD`` is a fraction of max torque below this (host/calibrate.py refuses more)
TENSION_MAX = 0.8
#: largest ``tension … STEP`` (rad): each step changes the zero offset by this much at once
TENSION_STEP_MAX = 0.1


class ScriptError(ValueError):
    """What is wrong with a script: every problem found, each ``FILE:LINE: message`` on a line
    of its own (``problems``); ``steps`` holds the lines that were well formed, so the checks
    against the segment can still add theirs."""

    def __init__(self, problems: str | list[str], steps: list[Step] | None = None) -> None:
        self.problems = [problems] if isinstance(problems, str) else list(problems)
        self.steps = steps or []
        super().__init__("\n".join(self.problems))


@dataclass
class Step:
    line: int
    command: str
    args: list[float]


def _line_problems(cmd: str, rest: list[str]) -> tuple[list[str], list[float]]:
    """Every problem of one line (names, argument count, numbers, ranges) and its numbers."""
    if cmd not in _ARITY:
        return [f"unknown command {cmd!r} (one of {', '.join(_ARITY)})"], []
    out = []
    lo, hi = _ARITY[cmd]
    if not lo <= len(rest) <= hi:
        want = str(lo) if lo == hi else f"{lo}..{hi}"
        out.append(f"{cmd} takes {want} argument(s), got {len(rest)}")
    try:
        args = [float(w) for w in rest]
    except ValueError:
        return [*out, f"{cmd}: arguments must be numbers: {rest}"], []
    if any(not math.isfinite(a) for a in args):
        return [*out, f"{cmd}: arguments must be finite"], []
    if out:  # a wrong count: which argument is which is unknown
        return out, args
    if cmd in ("jog", "direction") and args[0] != int(args[0]):
        out.append(f"{cmd}: the servo index must be an integer")
    if cmd == "direction" and args[1] not in (1.0, -1.0):
        out.append("direction must be 1 or -1")
    if cmd == "jog" and abs(args[1]) > 0.5:
        out.append("jog at most 0.5 rad at a time")
    if cmd == "wait" and not 0 <= args[0] <= 60:
        out.append("wait 0..60 s")
    if cmd in _KAPPA_ARG and args and args[0] < 0:
        out.append(
            f"{cmd}: kappa {args[0]:g} 1/m is negative: kappa is a magnitude >= 0 "
            "(bend the other way with phi + 180 deg)"
        )
    if cmd == "tension" and not 0 < args[0] < TENSION_MAX:
        out.append(f"tension LOAD {args[0]:g} must be in (0, {TENSION_MAX:g}) of max torque")
    if cmd == "tension" and len(args) > 1 and not 0 < args[1] <= TENSION_STEP_MAX:
        out.append(
            f"tension STEP {args[1]:g} rad must be in (0, {TENSION_STEP_MAX:g}] rad (default 0.01)"
        )
    return out, args


def parse(text: str, source: str = "<script>") -> list[Step]:
    """Every step of a script, checked (names, argument counts, numbers, ranges); ScriptError
    lists every problem of the file at once, each ``FILE:LINE: message``."""
    steps = []
    problems = []
    for no, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        words = line.split()
        cmd = words[0].lower()
        found, args = _line_problems(cmd, words[1:])
        problems += [f"{source}:{no}: {p}" for p in found]
        if not found:
            steps.append(Step(no, cmd, args))
    if problems:
        raise ScriptError(problems, steps)
    if not steps:
        raise ScriptError(f"{source}: the script has no step")
    return steps


def segment_problems(steps: list[Step], descriptor: dict, source: str = "<script>") -> list[str]:
    """The steps against the segment found (its descriptor): every curvature within
    [0, kappa_max], every servo index one of its servos; each ``FILE:LINE: message``."""
    out = []
    kappa_max = descriptor.get("kappa_max")
    if not isinstance(kappa_max, (int, float)) or not kappa_max > 0:
        out.append(f"{source}: the segment reports no kappa_max to check the script against")
        kappa_max = None
    tendons = descriptor.get("tendon_angles")
    n = len(tendons) if isinstance(tendons, list) else None
    for st in steps:
        if (
            kappa_max is not None
            and st.command in _KAPPA_ARG
            and st.args
            and st.args[0] > kappa_max + 1e-9
        ):
            out.append(
                f"{source}:{st.line}: {st.command}: kappa {st.args[0]:g} 1/m is beyond the "
                f"segment's kappa_max {kappa_max:g} 1/m (it would stop at the limit)"
            )
        if st.command in ("jog", "direction") and n is not None and not 0 <= st.args[0] < n:
            out.append(
                f"{source}:{st.line}: {st.command}: servo {st.args[0]:g}: the segment has "
                f"servos 0..{n - 1}"
            )
    return out


def check_segment(steps: list[Step], descriptor: dict, source: str = "<script>") -> None:
    """:func:`segment_problems` as a ScriptError listing them all (called before anything
    moves)."""
    problems = segment_problems(steps, descriptor, source)
    if problems:
        raise ScriptError(problems, steps)


def run(
    session: Session,
    steps: list[Step],
    source: str = "<script>",
    on_persist: Callable[[Result], None] | None = None,
) -> Result | None:
    """Run the steps in order; a failing step raises CalibrationError naming its line.
    ``on_persist`` gets the result of each `persist` step at once (``ucr calibrate --robot``
    writes the robot file there, as the terminal UI does): were the file written only when the
    script ends, a step failing after `persist` would leave the segment calibrated and the file
    not."""
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
                st_ = session.move(a[0], math.radians(a[1]))
                session.say(
                    f"bend: kappa {st_['kappa']:.3f} 1/m phi {math.degrees(st_['phi']):.1f} deg "
                    f"measured (asked {a[0]:.3f} 1/m, {a[1]:.1f} deg)"
                )
            elif st.command == "wait":
                session.keep(a[0])
            elif st.command == "persist":
                result = session.persist()
                if on_persist is not None:
                    on_persist(result)
        except CalibrationError as exc:
            raise type(exc)(f"{source}:{st.line}: {st.command}: {exc}") from exc
    return result


def load(path: str | Path) -> list[Step]:
    """The steps of the script file at ``path``, checked (:func:`parse`); a file that cannot be
    read or is not UTF-8 text is a ScriptError of one line (not a UnicodeDecodeError traceback),
    exit 1 as every other problem of the script."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise ScriptError(f"{p}: cannot read the script: {not_utf8(exc)}") from None
    except OSError as exc:
        raise ScriptError(f"{p}: cannot read the script: {exc.strerror or exc}") from None
    return parse(text, str(p))
