"""``ucr check FILE``: validate a U(C)RDF file and print its structure, or its errors.

On success the summary tree goes to stdout and the exit code is 0. On any problem (missing file,
XML syntax, schema, semantics) each problem is one ``path:line: message`` line on stderr and the
exit code is 1 — never a traceback. The kinematics commands (``fk``, ``ik``, ``export-urdf``)
live in :mod:`ucrdf.kin_cli` and are registered from here when that module is installed.
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the model imports numpy; keep `ucr --help` light
    from ucrdf.model import Actuation, Bendable, Interface, Joint, Robot


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``check`` (and, when available, the kinematics commands) to the ``ucr`` dispatcher."""
    parser = subparsers.add_parser(
        "check",
        help="validate a U(C)RDF file and print its links, joints, bendables and interfaces",
        description="Validate a U(C)RDF file (XML syntax, schema, semantic checks). Prints a "
        "summary tree on success; prints path:line: message lines on stderr and exits 1 on error.",
    )
    parser.add_argument("file", metavar="FILE", help="U(C)RDF file (.ucrdf / .urdf)")
    parser.add_argument(
        "-q", "--quiet", action="store_true", help="print nothing on success (exit code only)"
    )
    parser.set_defaults(func=run_check)
    try:
        kin_cli = importlib.import_module("ucrdf.kin_cli")
    except ModuleNotFoundError as exc:
        if exc.name != "ucrdf.kin_cli":
            raise
        return
    kin_cli.register(subparsers)


def run_check(args: argparse.Namespace) -> int:
    """Entry point of ``ucr check``: 0 when the file is valid, 1 otherwise."""
    from ucrdf.errors import UcrdfError  # noqa: PLC0415 - lazy: lxml/numpy only when run
    from ucrdf.parser import load  # noqa: PLC0415

    try:
        robot = load(args.file)
    except UcrdfError as exc:
        for diagnostic in exc.diagnostics:
            print(diagnostic, file=sys.stderr)
        count, path = len(exc.diagnostics), args.file or "''"
        print(f"{path}: {count} error{'s' if count != 1 else ''}", file=sys.stderr)
        return 1
    _print_warnings(args.file, robot)
    if not args.quiet:
        try:
            print_out(summary(robot))
        except BrokenPipeError:  # e.g. `ucr check FILE | head`: the reader left, not an error
            pass
        except OSError as exc:  # e.g. `> /dev/full`
            reason = exc.strerror or str(exc)
            print(f"ucr check: error: cannot write the summary: {reason}", file=sys.stderr)
            return 1
    return 0


def print_out(text: str, end: str = "\n") -> None:
    """``print(text, end=end)``, flushed. When stdout cannot take it the OSError propagates
    (BrokenPipeError: the reader left; another: e.g. a full disk), and stdout then points to
    /dev/null, so the interpreter's final flush of what is left does not fail again."""
    try:
        print(text, end=end, flush=True)
    except OSError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        raise


def _print_warnings(path: str, robot: Robot) -> None:
    """``path:line: warning: …`` on stderr for what a usable file still lacks (exit code 0)."""
    from ucrdf.checks import warnings  # noqa: PLC0415
    from ucrdf.parser import parse_with_lines, read_file  # noqa: PLC0415

    try:
        _, lines = parse_with_lines(read_file(path), path)
    except Exception:  # noqa: BLE001 - it loaded a moment ago; lines are a nicety
        lines = {}
    for diagnostic in warnings(robot, lines):
        print(diagnostic, file=sys.stderr)


# -- summary -------------------------------------------------------------------------------------
def _num(value: float, digits: int = 4) -> str:
    return f"{value:.{digits}g}"


def _deg(angle_rad: float) -> str:
    return f"{math.degrees(angle_rad):.1f}°"


def _interface(iface: Interface, unit: str | None) -> str:
    """``kappa [0, 3.314] 1/m, init 0 1/m``: the interface's bounds and initial value."""
    per = f" {unit}" if unit else ""
    details = []
    lo, hi = iface.params.get("min"), iface.params.get("max")
    if lo is not None or hi is not None:
        lo_text = _num(lo) if isinstance(lo, float) else "-"
        hi_text = _num(hi) if isinstance(hi, float) else "-"
        details.append(f"[{lo_text}, {hi_text}]{per}")
    init = iface.params.get("initial_value")
    if isinstance(init, float):
        details.append(f"init {_num(init)}{per}")
    return f"{iface.name} {', '.join(details)}" if details else iface.name


#: Units of a rigid joint's interfaces: (revolute or continuous, prismatic)
_JOINT_UNITS = {
    "position": ("rad", "m"),
    "velocity": ("rad/s", "m/s"),
    "acceleration": ("rad/s^2", "m/s^2"),
    "effort": ("N m", "N"),
}


def _interface_units(robot: Robot, name: str) -> dict[str, str]:
    """The unit of each interface of the bendable or joint ``name`` (those known)."""
    if name in robot.bendables:
        from ucrdf.checks import model_registry  # noqa: PLC0415

        try:
            model = model_registry()[0](robot.bendables[name].model.type)
            return {v.name: v.unit for v in model.variables()}
        except Exception:  # noqa: BLE001 - a summary of a checked robot; units are a nicety
            return {}
    joint = robot.joints.get(name)
    if joint is None or joint.type not in ("revolute", "continuous", "prismatic"):
        return {}
    return {k: units[joint.type == "prismatic"] for k, units in _JOINT_UNITS.items()}


def _joint_line(joint: Joint) -> str:
    text = f"joint {joint.name} ({joint.type}"
    if joint.movable:
        text += f", axis {' '.join(_num(a, 3) for a in joint.axis)}"
        if joint.limit is not None and joint.type != "continuous":
            lo, hi = joint.limit.lower, joint.limit.upper
            if joint.type == "revolute":
                text += f", [{_num(lo)}, {_num(hi)}] rad = [{_deg(lo)}, {_deg(hi)}]"
            else:
                text += f", [{_num(lo)}, {_num(hi)}] m"
    return text + ")"


def _bendable_lines(b: Bendable) -> list[str]:
    """Heading plus detail lines (limits, actuation) of one bendable."""
    lim = b.model.limits
    bend = lim.kappa_max * b.length
    head = f"bendable {b.name} (model {b.model.type}, length {_num(b.length)} m)"
    limits = f"kappa_max {_num(lim.kappa_max)} 1/m ({math.degrees(bend):.1f}° bend)"
    if lim.kappa_rate_max is not None:
        limits += f", kappa_rate_max {_num(lim.kappa_rate_max)} 1/m/s"
    limits += f", phi [{_num(lim.phi_min)}, {_num(lim.phi_max)}] rad"
    out = [head, limits]
    if b.inertial is not None:
        out.append(f"mass {_num(b.inertial.mass)} kg")
    act = b.actuation
    if act is not None:
        angles = ", ".join(_deg(a) for a in act.angles)
        text = (
            f"{act.count} tendons at {angles}, radius {_num(act.radius)} m, "
            f"spool {_num(act.spool_radius)} m, driver {act.driver}"
        )
        if act.servos:
            text += f", servo ids {', '.join(str(s.id) for s in act.servos)}"
        else:
            text += ", no servos declared"
        out.append(text)
        out.append(_board_line(act))
    return out


def _board_line(act: Actuation) -> str:
    """The segment's board and wiring as config.json gets it (ucrdf/boards.py): chain UARTs,
    servo bus UART or PWM pins and pulse range."""
    from ucrdf.boards import board_of, plan, problems  # noqa: PLC0415

    if problems(act):
        return f"board {board_of(act)} (wiring not possible: see the errors)"
    p = plan(act)
    pins = p["pins"]
    parts = [
        f"board {p['board']}",
        f"upstream UART{pins['up_uart']} tx {pins['up_tx']} rx {pins['up_rx']}",
        f"downstream UART{pins['down_uart']} tx {pins['down_tx']} rx {pins['down_rx']}",
        f"{pins.get('baud', 921600)} baud",
    ]
    if p["bus"]:
        bus = p["bus"]
        text = f"servo bus UART{bus['uart']} tx {bus['tx']} rx {bus['rx']}"
        if "baud" in bus:
            text += f" {bus['baud']} baud"
        parts.append(text)
    if p["pwm"]:
        pw = p["pwm"]
        parts.append(
            f"PWM pins {', '.join(str(g) for g in pw['pins'])}, pulse "
            f"{_num(pw['min_us'])}..{_num(pw['max_us'])} us = {_num(pw['range'])} rad"
        )
    return ", ".join(parts)


#: Tree levels the summary indents; deeper levels print at this indentation.
_MAX_INDENT = 32


def summary(robot: Robot) -> str:
    """The robot as an indented tree from its root link, then its ros2_control blocks."""
    lines = [
        (
            f"robot {robot.name}: {len(robot.links)} links, {len(robot.joints)} joints, "
            f"{len(robot.bendables)} bendables"
        )
    ]
    children: dict[str, list[tuple[list[str], str]]] = {}
    for j in robot.joints.values():
        children.setdefault(j.parent, []).append(([_joint_line(j)], j.child))
    for b in robot.bendables.values():
        children.setdefault(b.parent, []).append((_bendable_lines(b), b.child))

    # depth-first with an explicit stack (a chain of thousands of links must not hit Python's
    # recursion limit); the indentation stops growing after _MAX_INDENT levels, so the summary of
    # a deep chain stays linear in size
    root = robot.root_link()
    lines.append(f"link {root}")
    stack: list[tuple[list[tuple[list[str], str]], int, str]] = [(children.get(root, []), 0, "")]
    while stack:
        items, i, prefix = stack.pop()
        if i >= len(items):
            continue
        stack.append((items, i + 1, prefix))  # the next sibling, after this child's subtree
        label, child = items[i]
        last = i == len(items) - 1
        inner = prefix + ("   " if last else "│  ")
        lines.append(f"{prefix}{'└─' if last else '├─'} {label[0]}")
        lines.extend(f"{inner}│    {detail}" for detail in label[1:])
        lines.append(f"{inner}└─ link {child}")
        deeper = inner + "   " if len(inner) < 6 * _MAX_INDENT else prefix
        stack.append((children.get(child, []), 0, deeper))
    for control in robot.ros2_control:
        lines.append(f"ros2_control {control.name} ({control.type}), plugin {control.plugin}")
        if control.hardware_params:
            params = ", ".join(f"{k}={v}" for k, v in control.hardware_params.items())
            lines.append(f"  hardware: {params}")
        for cj in control.joints:
            kind = "bendable" if cj.name in robot.bendables else "joint"
            lines.append(f"  {kind} {cj.name}")
            units = _interface_units(robot, cj.name)
            if cj.command_interfaces:
                commands = "; ".join(
                    _interface(i, units.get(i.name)) for i in cj.command_interfaces
                )
                lines.append(f"    command: {commands}")
            if cj.state_interfaces:
                states = "; ".join(_interface(i, units.get(i.name)) for i in cj.state_interfaces)
                lines.append(f"    state: {states}")
    return "\n".join(lines)
