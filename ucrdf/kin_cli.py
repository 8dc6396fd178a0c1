"""``ucr fk``, ``ucr ik`` and ``ucr export-urdf``: the kinematics commands.

Registered by :mod:`ucrdf.cli`. Every failure is one or more plain lines on stderr and exit code
1 (file problems as ``path:line: message``), never a traceback. Heavy imports stay inside the
command functions so ``ucr --help`` is fast.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from ucrdf.cli import print_out
from ucrdf.numtext import number, shown, whole
from ucrdf.units import phi_beyond_a_turn


class _CliError(Exception):
    """A failure the user can act on (a file that cannot be written, a configuration the robot
    cannot take): printed as one line, exit 1."""


class _UsageError(_CliError):
    """An option value that cannot work (not JSON, not three numbers, out of its range):
    printed as one line, exit 2, as argparse's own usage errors."""


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``fk``, ``ik`` and ``export-urdf`` to the ``ucr`` dispatcher."""
    p = subparsers.add_parser(
        "fk",
        help="forward kinematics: transform of every link frame as JSON",
        description="Print a JSON object {link: 4x4 homogeneous transform in the root frame, "
        "one row per line; rotation unitless, translation (last column) in m} for a "
        'configuration. --config maps each bendable to {"kappa": 1/m, "phi": rad} (its model\'s '
        "variables) and each movable joint to a number (rad or m); anything not named takes its "
        "ros2_control initial_value, else 0.",
    )
    p.add_argument("file", metavar="FILE", help="U(C)RDF file")
    p.add_argument(
        "--config",
        default="{}",
        help='configuration as a JSON string, or @path to a JSON file: {"BENDABLE": {"kappa": '
        '1/m, "phi": rad}, "JOINT": rad or m}',
    )
    p.set_defaults(func=_guard(run_fk))

    p = subparsers.add_parser(
        "ik",
        help="inverse kinematics: configuration that puts a link at a target position",
        description="Solve for the configuration placing the tip link at x,y,z (m, root frame) "
        "by damped least squares in (kx, ky). Prints JSON {success, residual, iterations, "
        "message, tip, config}; exit 0 on success, 1 when no solution within tolerance.",
    )
    p.add_argument("file", metavar="FILE", help="U(C)RDF file")
    p.add_argument("--target", required=True, help="target position x,y,z in m (root frame)")
    p.add_argument("--tip", help="link to place (default: the robot's one end link)")
    p.add_argument("--initial", help="start configuration (JSON or @file), like fk --config")
    p.add_argument("--tol", default="1e-4", help="position tolerance in m (1e-4)")
    p.set_defaults(func=_guard(run_ik))

    p = subparsers.add_parser(
        "export-urdf",
        help="export plain URDF: each bendable as a chain of rigid subdivisions",
        description="Write a plain URDF in which every bendable is a pseudo-rigid-body chain of "
        "N subdivisions (universal joints). With --config the pose (bendables and rigid joints) is "
        "baked into fixed joints.",
    )
    p.add_argument("file", metavar="FILE", help="U(C)RDF file")
    p.add_argument("--subdivisions", "-n", default="10", help="per bendable (10; at most 1000)")
    p.add_argument("-o", "--output", required=True, help="output URDF path ('-' for stdout)")
    p.add_argument("--config", help="bake this configuration (JSON or @file) as fixed joints")
    p.set_defaults(func=_guard(run_export))


def _guard(func):
    """Turn expected errors into stderr lines and exit code 1 (2 for a usage error)."""

    def run(args: argparse.Namespace) -> int:
        from ucrdf.errors import UcrdfError  # noqa: PLC0415
        from ucrdf.models.base import ModelError  # noqa: PLC0415

        try:
            return func(args)
        except UcrdfError as exc:
            for diagnostic in exc.diagnostics:
                print(diagnostic, file=sys.stderr)
            return 1
        except (_CliError, ModelError) as exc:
            print(f"ucr {args.command}: error: {exc}", file=sys.stderr)
            return 2 if isinstance(exc, _UsageError) else 1

    return run


def _json_arg(text: str, option: str) -> Any:
    """Parse a JSON option value; ``@path`` reads the file (UTF-8). A key given twice in one
    object is refused (json would keep the last one silently)."""
    source = option
    if text.startswith("@"):
        path = Path(text[1:])
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise _UsageError(f"cannot read {option} file {str(path)!r}: {exc.strerror}") from None
        except UnicodeDecodeError as exc:
            raise _UsageError(
                f"cannot read {option} file {str(path)!r}: not UTF-8 text (byte {exc.start})"
            ) from None
        source = f"{option} file {str(path)!r}"

    def unique(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
        obj: dict[str, Any] = {}
        for key, value in pairs:
            if key in obj:
                raise _UsageError(f"{source}: key {shown(key)} is given twice")
            obj[key] = value
        return obj

    try:
        value = json.loads(text, object_pairs_hook=unique)
    except json.JSONDecodeError as exc:
        raise _UsageError(
            f"{source} is not valid JSON: {exc.msg} (line {exc.lineno}, column {exc.colno})"
        ) from None
    except (ValueError, RecursionError) as exc:  # e.g. an integer of 5000 digits, deep nesting
        reason = str(exc).split(";")[0] if isinstance(exc, ValueError) else "nested too deeply"
        raise _UsageError(f"{source} is not usable JSON: {reason}") from None
    if not isinstance(value, dict):
        raise _UsageError(f"{source} must be a JSON object mapping names to values")
    for name, variables in value.items():  # a unit mistake, not an angle to wrap
        phi = variables.get("phi") if isinstance(variables, dict) else None
        why = None
        if isinstance(phi, (int, float)) and not isinstance(phi, bool):
            why = phi_beyond_a_turn(phi)
        if why is not None:
            raise _UsageError(f"{source}: {name}: phi = {why}")
    return value


def _load(path: str):
    from ucrdf.parser import load  # noqa: PLC0415

    return load(path)


def _print(text: str, end: str = "\n") -> None:
    """``text`` on stdout; a stdout that cannot take it (``> /dev/full``) is one error line."""
    try:
        print_out(text, end)
    except BrokenPipeError:
        raise  # the reader left: the dispatcher stops quietly
    except OSError as exc:
        raise _CliError(f"cannot write the output: {exc.strerror or exc}") from None


def run_fk(args: argparse.Namespace) -> int:
    import numpy as np  # noqa: PLC0415

    from ucrdf.fk import RobotKinematics  # noqa: PLC0415

    config = _json_arg(args.config, "--config")
    robot = _load(args.file)
    with np.errstate(all="ignore"):  # an overflow is reported below, once
        frames = RobotKinematics(robot).fk(config)
    out = {name: [[float(x) for x in row] for row in t.tolist()] for name, t in frames.items()}
    for name, rows in out.items():  # JSON has no NaN or Infinity: an error, not invalid output
        if not all(math.isfinite(x) for row in rows for x in row):
            raise _CliError(f"the transform of link {name!r} is not finite (numbers overflow)")
    _print(matrices_json(out))
    return 0


def matrices_json(frames: dict[str, list[list[float]]]) -> str:
    """JSON of ``{link: 4x4 matrix}`` with each matrix row on one line (a reader sees the
    rotation and, in the last column, the position in m; ``json.loads`` reads it as usual)."""
    items = []
    for name, rows in frames.items():
        body = ",\n".join("  " + json.dumps(row) for row in rows)
        items.append(f" {json.dumps(name)}: [\n{body}\n ]")
    return "{\n" + ",\n".join(items) + "\n}" if items else "{}"


def _target(text: str) -> tuple[float, float, float]:
    values = [number(p) for p in text.split(",")]
    if len(values) != 3 or not all(v is not None and math.isfinite(v) for v in values):
        raise _UsageError(f"--target must be three numbers x,y,z in m, got {shown(text, 60)}")
    return tuple(values)  # type: ignore[return-value]


def run_ik(args: argparse.Namespace) -> int:
    import numpy as np  # noqa: PLC0415

    from ucrdf.fk import ConfigError  # noqa: PLC0415
    from ucrdf.ik import solve_ik  # noqa: PLC0415

    target = _target(args.target)
    initial = _json_arg(args.initial, "--initial") if args.initial else None
    tol = number(args.tol)
    if tol is None or not (tol > 0.0 and math.isfinite(tol)):
        raise _UsageError(f"--tol must be a positive number of metres, got {shown(args.tol)}")
    robot = _load(args.file)
    if initial is not None:  # a start outside the limits is refused as by fk --config
        from ucrdf.fk import RobotKinematics  # noqa: PLC0415

        try:
            RobotKinematics(robot).resolve(initial)
        except ConfigError as exc:
            raise _CliError(f"--initial: {exc}") from None
    with np.errstate(all="ignore"):  # an overflow is reported below, once
        result = solve_ik(robot, target, tip=args.tip, initial=initial, tol=tol)
    out = {
        "success": result.success,
        "residual": result.residual,
        "iterations": result.iterations,
        "message": result.message,
        "tip": result.tip,
        "target": list(target),
        "config": result.config,
    }
    try:  # JSON has no NaN or Infinity: an error, not invalid output
        text = json.dumps(out, indent=1, allow_nan=False)
    except ValueError:
        raise _CliError(
            f"the solution is not finite (residual {result.residual}): numbers overflow"
        ) from None
    _print(text)
    if not result.success:
        print(f"ucr ik: {result.message}", file=sys.stderr)
    return 0 if result.success else 1


def run_export(args: argparse.Namespace) -> int:
    from ucrdf.export import MAX_SUBDIVISIONS, export_urdf  # noqa: PLC0415

    n = whole(args.subdivisions)
    if n is None or not 1 <= n <= MAX_SUBDIVISIONS:
        raise _UsageError(
            f"--subdivisions must be in 1..{MAX_SUBDIVISIONS}, got {shown(args.subdivisions)}"
        )
    config = _json_arg(args.config, "--config") if args.config else None
    robot = _load(args.file)
    text = export_urdf(robot, n, config)
    if args.output == "-":
        _print(text, end="")
        return 0
    try:
        Path(args.output).write_text(text, encoding="utf-8")
    except OSError as exc:
        raise _CliError(f"cannot write {args.output!r}: {exc.strerror}") from None
    print(f"wrote {args.output} ({len(robot.bendables)} bendable(s) x {n} "
          "subdivisions)", file=sys.stderr)  # fmt: skip
    return 0
