"""``ucr calibrate``: command line (script form) and the entry to the terminal UI.

Before its first frame it listens to the port as ``ucr doctor`` does (host/doctor.py ``listen``):
DISCOVER's bytes include Ctrl-C and Ctrl-D, which would stop or reset a segment's firmware on its
USB/REPL port, so a REPL or a silent port is refused with nothing sent. --baud and --robot are
checked by the same argparse types as doctor's (a bounded rate, a non-empty path).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from host.doctor import MAX_BAUD, PROTOCOL_FIX, baud_arg, listen, path_arg
from host.positions import label

#: exit code of a command stopped by Ctrl-C (128 + SIGINT), as every ucr command
INTERRUPTED = 130


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "calibrate",
        help="calibrate one segment: zero offsets, directions, tendon tension (moves it)",
        description="Calibrate the segment NAME over the chain (the daemon must be stopped: the "
        "port is opened exclusively). With --script FILE the steps run unattended; without it a "
        "terminal UI (the 'tui' extra) guides you. Ctrl-C or the hold key holds the segment at "
        "once. `persist` stores the calibration on the segment and, with --robot, in the U(C)RDF.",
    )
    p.add_argument(
        "--segment",
        required=True,
        help="segment name (descriptor), chain position (counted from 1) or uid",
    )
    p.add_argument("--port", default="/dev/ttyUSB0", help="chain port (path or pyserial URL)")
    p.add_argument(
        "--baud", type=baud_arg, default=921600, help=f"bit/s (default 921600, 1..{MAX_BAUD})"
    )
    p.add_argument(
        "--robot", type=path_arg, help="U(C)RDF to write the calibration into (on persist)"
    )
    p.add_argument("--script", type=path_arg, help="run these steps instead of the terminal UI")
    p.set_defaults(func=cmd_calibrate)


#: what --segment takes, said where it names nothing
SEGMENT_FORMS = "a segment name, a chain position counted from 1, or a uid"


def find_segment(descs: list[dict], which: str) -> dict:
    """The descriptor named ``which`` (name, then chain position counted from 1 as everywhere a
    user sees one, then uid); ValueError if none, or if a name is ambiguous (two segments flashed
    with the same configuration): the message lists the positions. An unknown one is refused as
    ``ucr move`` refuses it (``unknown segment 'X': ...``), naming the segments there are."""
    named = [d for d in descs if d.get("name") == which]
    if len(named) > 1:
        where = ", ".join(f"{label(d.get('position'))} ({d.get('uid')})" for d in named)
        raise ValueError(
            f"{len(named)} segments are named {which!r} ({where}): pick one with --segment "
            "POSITION or UID, and reflash the wrong one with its own configuration (`ucr flash`)"
        )
    if named:
        return named[0]
    number = which.isascii() and which.isdigit()  # not '²' (a digit to str.isdigit, not to int)
    if number:
        for d in descs:
            if isinstance(d.get("position"), int) and d["position"] + 1 == int(which):
                return d
    for d in descs:
        if str(d.get("uid", "")).lower() == which.lower():
            return d
    names = ", ".join(
        f"{label(d.get('position'))}: {d.get('name')} ({d.get('uid')})" for d in descs
    )
    hint = " (positions count from 1)" if number and int(which) == 0 else ""
    there = f"the chain's segments are {names}" if names else "no segment answers"
    raise ValueError(f"unknown segment {which!r}{hint}: {there}; --segment takes {SEGMENT_FORMS}")


def open_session(args: argparse.Namespace, say=print) -> tuple[Any, Any]:
    """(link, session) for the segment of ``args``; LinkError/ValueError say why not.

    The port is listened to first, as doctor does: a segment's REPL port (or a silent one, as a
    running firmware's REPL is) gets no frame, since DISCOVER's bytes would stop that segment. A
    DISCOVER that fails is reported as what it is: a segment in another protocol version (with
    doctor's fix) or an incomplete chain, not as "no segment answers"."""
    from host.calibrate import Session  # noqa: PLC0415
    from host.link import ChainLink, LinkError  # noqa: PLC0415
    from host.link_frames import ProtocolVersionError  # noqa: PLC0415

    heard = listen(args.port, args.baud, who="calibrate")
    if heard is not None:
        raise ValueError(f"{heard.message}: {heard.fix}")
    link = ChainLink(args.port, args.baud)
    try:
        descs: list[dict] = []
        failed: LinkError | None = None
        for _ in range(3):
            try:
                descs, failed = link.discover(timeout=1.0), None
            except ProtocolVersionError as exc:  # it answered: retrying would not change it
                raise ValueError(f"{exc}; fix: {PROTOCOL_FIX}") from None
            except LinkError as exc:
                descs, failed = [], exc
            if descs:
                break
        if not descs and failed is not None:
            raise ValueError(
                f"no complete answer to DISCOVER in 3 tries ({failed}): check the cable after "
                f"the last answering segment; `ucr doctor --port {args.port}` finds it"
            )
        d = find_segment(descs, args.segment)
        if d.get("config_error"):
            raise ValueError(
                f"segment {args.segment} refused its configuration ({d['config_error']}): "
                "fix it first (`ucr doctor`)"
            )
        return link, Session(link, d["position"], len(descs), d, say)
    except BaseException:
        link.close()
        raise


def check_robot(args: argparse.Namespace, session: Any) -> None:
    """With --robot: the file must take this segment's calibration (its bendable, one <servo>
    per servo, and `ucr check` passing afterwards), checked before anything moves or is stored
    on the segment; RobotFileError says why not."""
    if not args.robot:
        return
    from host.calibrate_robot import check  # noqa: PLC0415

    name = session.desc.get("name") or args.segment
    check(args.robot, name, list(session.zeros), list(session.dirs))


def persist_robot(args: argparse.Namespace, session: Any, result: Any, say=print) -> None:
    """Write the persisted calibration into the U(C)RDF given with --robot (if any), right
    after the segment stored it (the script's and the terminal UI's `persist` step alike).
    RobotFileError (one line) if the file cannot take it: the segment has it stored already, so
    the message says the file lacks it and how to write it there once the file is fixed."""
    if not args.robot or result is None:
        return
    from host.calibrate_robot import RobotFileError, write  # noqa: PLC0415

    name = session.desc.get("name") or args.segment
    try:
        write(args.robot, name, result.zero_offsets, result.directions)
    except (RobotFileError, OSError) as exc:
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise RobotFileError(
            f"{why}; the calibration is stored on the segment but not in {args.robot}: once "
            f"the file is fixed, a script of just `persist` with --robot writes it there"
        ) from None
    say(f"persist: written to {args.robot} (bendable {name}); `ucr check {args.robot}` passes")


def cmd_calibrate(args: argparse.Namespace) -> int:
    if args.script is None:
        return run_tui(args)
    try:
        return run_script(args)
    except KeyboardInterrupt:  # before any motion (a running script holds the segment itself)
        print("ucr calibrate: stopped (Ctrl-C) before anything moved", file=sys.stderr)
        return 130


def _script_problems(args: argparse.Namespace) -> tuple[list[Any], list[str]]:
    """(steps, problems) of --script: every problem of the file at once, each FILE:LINE."""
    from host.calibrate_script import ScriptError, load  # noqa: PLC0415

    try:
        return load(args.script), []
    except ScriptError as exc:
        return exc.steps, exc.problems


def run_script(args: argparse.Namespace) -> int:
    """``ucr calibrate --script FILE``: the whole file checked (alone, then against the segment
    and the robot file) before anything moves; every problem of the script reported at once."""
    from host.calibrate import CalibrationError  # noqa: PLC0415
    from host.calibrate_robot import RobotFileError  # noqa: PLC0415
    from host.calibrate_script import run, segment_problems  # noqa: PLC0415
    from host.link import LinkError  # noqa: PLC0415

    steps, problems = _script_problems(args)
    if problems and not steps:  # unreadable, or nothing well formed to check on the segment
        print("\n".join(f"ucr calibrate: {p}" for p in problems), file=sys.stderr)
        return 1
    try:
        link, session = open_session(args)
    except (ValueError, LinkError) as exc:
        for p in problems:
            print(f"ucr calibrate: {p}", file=sys.stderr)
        print(f"ucr calibrate: {exc}", file=sys.stderr)
        return 1
    try:
        # the script and the robot file against the segment found, still before any motion
        problems += segment_problems(steps, session.desc, args.script)
        if problems:
            problems.sort(key=_line_of)
            for p in problems:
                print(f"ucr calibrate: {p}", file=sys.stderr)
            print(
                f"ucr calibrate: {len(problems)} problem(s) in {args.script} (nothing moved)",
                file=sys.stderr,
            )
            return 1
        try:
            check_robot(args, session)
        except RobotFileError as exc:
            print(f"ucr calibrate: {exc} (nothing moved)", file=sys.stderr)
            return 1
        try:
            # the robot file is written at the persist step, as the terminal UI does: a step
            # failing after it must not leave the segment calibrated and the file not
            run(session, steps, args.script, on_persist=lambda r: persist_robot(args, session, r))
            return 0
        except KeyboardInterrupt:
            try:
                session.stop()
                said = "the segment holds"
            except LinkError as exc:
                said = f"HOLD not sent ({exc}); its watchdog holds it"
            print(f"ucr calibrate: stopped (Ctrl-C): {said}", file=sys.stderr)
            return 130
        except (CalibrationError, RobotFileError, LinkError, OSError) as exc:
            try:
                session.stop()
            except LinkError:
                pass
            print(f"ucr calibrate: {exc} (the segment holds)", file=sys.stderr)
            return 1
    finally:
        link.close()


def _line_of(problem: str) -> int:
    """The line number of a ``FILE:LINE: message`` problem (0 for one about the whole file)."""
    head = problem.split(": ", 1)[0]
    number = head.rsplit(":", 1)[-1]
    return int(number) if number.isascii() and number.isdigit() else 0


def run_tui(args: argparse.Namespace) -> int:
    """``ucr calibrate --segment NAME`` without --script: the terminal UI (the 'tui' extra)."""
    from host.calibrate_robot import RobotFileError  # noqa: PLC0415
    from host.calibrate_tui import CalibrateApp  # noqa: PLC0415 - textual only here
    from host.link import LinkError  # noqa: PLC0415

    try:
        link, session = open_session(args, say=print)
    except (ValueError, LinkError) as exc:
        print(f"ucr calibrate: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("ucr calibrate: stopped (Ctrl-C) before anything moved", file=sys.stderr)
        return INTERRUPTED
    try:
        check_robot(args, session)
    except RobotFileError as exc:
        link.close()
        print(f"ucr calibrate: {exc} (nothing moved)", file=sys.stderr)
        return 1
    try:
        app = CalibrateApp(
            session, on_persist=lambda r: persist_robot(args, session, r, session.say)
        )
        app.run()
        # what the UI's log said goes with it when it closes: a failed persist (on the segment
        # or into --robot) is said again here, and a crash is not a success
        if app.persist_error is not None:
            print(f"ucr calibrate: persist failed: {app.persist_error}", file=sys.stderr)
        if app.return_code == INTERRUPTED:  # Ctrl-C, a key in the UI: it held the segment
            print("ucr calibrate: stopped (Ctrl-C): the segment holds", file=sys.stderr)
            return INTERRUPTED
        if app.return_code:  # textual's code for an unhandled exception, or a failed HOLD
            said = app.error or f"the terminal UI stopped on an error (code {app.return_code})"
            print(f"ucr calibrate: {said}", file=sys.stderr)
            return 1
        return 1 if app.persist_error is not None else 0
    except KeyboardInterrupt:  # SIGINT outside the UI's raw terminal (e.g. while it starts)
        print("ucr calibrate: stopped (Ctrl-C): the segment holds", file=sys.stderr)
        return INTERRUPTED
    finally:
        try:
            session.stop()
        except LinkError:
            pass
        link.close()


__all__ = ["cmd_calibrate", "find_segment", "open_session", "register", "run_script"]
