"""Per-segment configuration (the flashed ``config.json``) derived from the robot's U(C)RDF.

The U(C)RDF is the single source of truth: geometry (backbone length and radius), tendon layout,
servo calibration and limits of one ``<bendable>`` become the JSON file a segment reads at boot
(keys and units: docs/architecture.md, "Segment configuration").
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from ucrdf import boards as board_plan
from ucrdf.checks import (
    DEFAULT_KAPPA_RATE_MAX,
    DEFAULT_WATCHDOG_MS,
    firmware_refusal,
    segment_config,
    segment_hardware_params,
)
from ucrdf.model import Actuation, Robot

__all__ = ["DEFAULT_KAPPA_RATE_MAX", "DEFAULT_WATCHDOG_MS", "SegmentConfigError", "config_for"]

CONFIG_KEYS = (
    "name",
    "length",
    "tendon_angles",
    "tendon_radius",
    "spool_radius",
    "kappa_max",
    "kappa_rate_max",
    "mass",
    "backbone_radius",
    "model",
    "servo_driver",
    "servos",
    "watchdog_ms",
    "board",
    "pins",
    "bus",
    "pwm",
)


class SegmentConfigError(ValueError):
    """The robot description cannot produce a segment configuration (message says why, as
    ``path:line: message`` when the robot was read from a file)."""

    def __init__(self, message: str, where: str = "") -> None:
        super().__init__(f"{where}: {message}" if where else message)


def _where(robot: Robot, line: int) -> str:
    return f"{robot.source}:{line}" if robot.source else ""


def validate(config: dict, where: str = "") -> dict:
    """``config`` if the segment firmware runs it exactly; SegmentConfigError with the firmware's
    reason otherwise (it would refuse to move). ``ucr flash`` calls this on what it writes."""
    reason = firmware_refusal(config)
    if reason is not None:
        raise SegmentConfigError(
            f"segment {config.get('name')!r}: the firmware would refuse this configuration "
            f"(and not move): {reason}",
            where,
        )
    return config


def config_for(robot: Robot, bendable_name: str, *, emulated: bool = False) -> dict:
    """The configuration dict (SI units, contract keys) of bendable ``bendable_name``.

    A bendable without ``<servo>`` elements is refused (``ucr flash``): its servo ids, zero
    offsets, directions and ranges are unknown, and inventing them would drive real servos by
    guesses. Only for an emulated chain (``emulated``, :func:`configs`), whose servos are
    emulated anyway, do stand-ins take their place (ids 0.., zero 0, direction 1)."""
    bendable = robot.bendables.get(bendable_name)
    if bendable is None:
        names = ", ".join(robot.bendables) or "none"
        raise SegmentConfigError(
            f"robot {robot.name!r} has no bendable {bendable_name!r} (bendables: {names})"
        )
    act = bendable.actuation
    if act is None or not act.angles:
        raise SegmentConfigError(
            f"bendable {bendable_name!r} has no tendon <actuation>: a segment needs tendon angles, "
            "tendon radius, spool radius and servos to be configured"
        )
    if act.type != "tendon":
        raise SegmentConfigError(
            f"bendable {bendable_name!r}: actuation type {act.type!r} is not supported by the "
            "segment firmware (only 'tendon')"
        )
    for what, v in (("tendon radius", act.radius), ("spool radius", act.spool_radius)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise SegmentConfigError(
                f"bendable {bendable_name!r}: {what} must be a finite number of m > 0, got {v!r}"
            )
    if not act.servos and not emulated:
        raise SegmentConfigError(
            f"bendable {bendable_name!r} declares no <servo>: its servo ids, zero offsets, "
            "directions and ranges are unknown and are not invented; add one <servo index= id= "
            "zero_offset= direction= min_angle= max_angle=/> per tendon to its <actuation> "
            "(docs/ucrdf.md, Servos)",
            _where(robot, bendable.line),
        )
    if act.servos and len(act.servos) != len(act.angles):
        raise SegmentConfigError(
            f"bendable {bendable_name!r}: {len(act.servos)} servos for {len(act.angles)} tendons"
        )
    # the safety keys only when the robot gives them: a config.json without them runs the
    # firmware's defaults (no hardware watchdog, hold in FAULT), as flashed before they existed
    try:
        params = segment_hardware_params(robot, bendable)
    except ValueError as exc:
        raise SegmentConfigError(str(exc)) from None
    config = segment_config(bendable, params.pop("watchdog_ms", DEFAULT_WATCHDOG_MS))
    config.update(params)
    config.update(_wiring(bendable_name, act))
    return validate(config, _where(robot, bendable.line))


def _wiring(name: str, act: Actuation) -> dict:
    """``board``, ``pins``, ``bus``, ``pwm`` (ucrdf/boards.py); an impossible plan is an error."""
    found = [msg for field, msg in board_plan.problems(act) if field != "servos"]
    if found:
        raise SegmentConfigError(
            f"bendable {name!r}: board {board_plan.board_of(act)!r}: {found[0]}"
        )
    return board_plan.plan(act)


def configs(robot: Robot) -> list[dict]:
    """Configuration of every bendable, in document order, for an emulated chain of the robot
    (a bendable without ``<servo>`` gets emulated stand-ins, see :func:`config_for`)."""
    return [config_for(robot, name, emulated=True) for name in robot.bendables]


def dumps_config(config: dict) -> str:
    """The file text: stable key order, one trailing newline."""
    return json.dumps(config, indent=1) + "\n"


def write_config(robot: Robot, name: str, path: str | os.PathLike) -> Path:
    """Write bendable ``name``'s configuration to ``path`` (a file or a directory)."""
    target = Path(path)
    if target.is_dir():
        target = target / "config.json"
    target.write_text(dumps_config(config_for(robot, name)))
    return target
