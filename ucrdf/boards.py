"""Board and wiring plan of each bendable, checked against the board profiles.

A bendable's ``<actuation board=…>`` names the board its segment runs on; ``<uart role=…>`` and
``<pwm index=… pin=…/>`` override the board's default pins. The profiles and the rules are
``protocol/boards.py`` (the one source the firmware and the emulator read too), so whatever
``ucr check`` accepts here the firmware accepts at boot, and the reverse.
"""

from __future__ import annotations

from typing import Any

from protocol import boards
from ucrdf.errors import Diagnostic
from ucrdf.model import Actuation, Robot

#: U(C)RDF ``<uart role>`` -> the plan's side in config.json ``pins``
_ROLE_SIDE = {"upstream": "up", "downstream": "down"}
#: problem field (protocol/boards.py) -> U(C)RDF element it comes from
_FIELD_ROLE = {"up": "upstream", "down": "downstream", "bus": "servo_bus"}


def board_of(act: Actuation) -> str:
    """The board a bendable runs on: ``board`` if given, else the default for its driver.

    Default: ``esp32``; a serial-bus driver defaults to ``esp32s3-usbrepl``, because a stock
    ESP32 has no UART left for a servo bus (UART0 is the REPL's, UART1/2 the chain's).
    """
    return act.board or boards.default_board(act.driver)


def plan(act: Actuation) -> dict[str, Any]:
    """The config.json wiring keys of a bendable: ``board``, ``pins``, ``bus``, ``pwm``
    (the board's defaults with the description's overrides; ``bus``/``pwm`` None when unused)."""
    name = board_of(act)
    pins: dict[str, Any] = {}
    for role, side in _ROLE_SIDE.items():
        u = act.uarts.get(role)
        if u:
            pins.update({f"{side}_uart": u["id"], f"{side}_tx": u["tx"], f"{side}_rx": u["rx"]})
            if "baud" in u:
                pins["baud"] = u["baud"]
    bus = None
    if "servo_bus" in act.uarts:
        u = act.uarts["servo_bus"]
        bus = {"uart": u["id"], "tx": u["tx"], "rx": u["rx"]}
        if "baud" in u:
            bus["baud"] = u["baud"]
    pwm = None
    if act.pwm_pins:
        default = list(boards.BOARDS[name]["pwm"]) if name in boards.BOARDS else []
        pins_list = [
            act.pwm_pins.get(i, default[i] if i < len(default) else -1) for i in range(act.count)
        ]
        pwm = {"pins": pins_list}
    try:
        chain, bus_full, pwm_pins = boards.resolve(name, pins, bus, pwm)
    except ValueError:
        chain, bus_full, pwm_pins = pins, bus, (pwm or {}).get("pins")
    return {
        "board": name,
        "pins": chain,
        "bus": bus_full if act.driver in boards.BUS_DRIVERS else None,
        "pwm": _pwm(act, pwm_pins) if act.driver == "pwm" and pwm_pins else None,
    }


def _pwm(act: Actuation, pins: list[int]) -> dict[str, Any]:
    """config.json ``pwm`` of a PWM segment: its pins and the pulse calibration it runs
    (``<pwm_pulse>``, else the firmware's defaults, written out so the file says them)."""
    p = act.pulse()
    return {"pins": pins[: act.count], "min_us": p.min_us, "max_us": p.max_us, "range": p.range}


def problems(act: Actuation) -> list[tuple[str, str]]:
    """(field, message) of every reason the bendable's wiring cannot work on its board."""
    p = plan(act)
    return boards.problems(
        p["board"],
        p["pins"],
        p["bus"],
        p["pwm"],
        driver=act.driver,
        servo_ids=[s.id for s in act.servos],
        n=act.count,
    )


def check(robot: Robot, lines: dict) -> list[Diagnostic]:
    """``path:line: message`` for every impossible wiring plan of the robot's bendables."""
    out = []
    source = robot.source or "<robot>"
    for b in robot.bendables.values():
        act = b.actuation
        if act is None or not act.angles:
            continue
        key = ("bendable", b.name)
        aline = lines.get((*key, "actuation"), b.line)
        for field, message in problems(act):
            if field == "servos":
                continue  # duplicate servo ids: reported by ucrdf.checks for every driver
            line = aline
            if field in _FIELD_ROLE:
                line = lines.get((*key, "uart", _FIELD_ROLE[field]), aline)
            elif field == "pwm" and act.pwm_pins:
                line = lines.get((*key, "pwm", min(act.pwm_pins)), aline)
            out.append(
                Diagnostic(source, line, f"bendable {b.name!r}: board {board_of(act)!r}: {message}")
            )
    return out
