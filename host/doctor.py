"""``ucr doctor``: find what is wrong with a segment chain, in order, each finding with its fix.

Read-only by construction: it first listens (and sends one carriage return): a MicroPython REPL
(a segment's USB port) or a silent port gets no frame, as its bytes (Ctrl-C, Ctrl-D) would stop or
reset a running firmware; then it sends only DISCOVER, PARAM_GET, HEARTBEAT and CALIBRATE with the
read action (never SYNC, PARAM_SET, CLEAR_FAULT, HOLD or a calibration change), so nothing moves and
no setting changes. It lives in host/ because it runs on
the Raspberry Pi next to the daemon (host/ is what a Pi install has; host/ never imports tools/).
Checks, in order (docs/commissioning.md): port present and permitted (host/serialport.py), the
chain answers at the baud rate (else which rate it answers at), per segment firmware and protocol
version, configuration, servos found, faults and error counters, the watchdog; with a U(C)RDF the
chain against it, the configuration hash and the board (host/doctor_config.py); then loop timing
over a few seconds. The checks themselves: host/doctor_checks.py. Each finding is printed as it is
made (progress on stderr before a slow step); Ctrl-C keeps what was found and exits 130.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from host.client_common import number_arg
from host.doctor_checks import (  # noqa: F401 - re-exported: the names tests and docs use
    EXPECTED_FW_VERSION,
    EXPECTED_PROTOCOL_VERSION,
    P_SERVO_TELEMETRY,
    Finding,
    check_segment,
    check_timing,
)
from host.doctor_config import check_board, check_config_hash, check_robot
from host.positions import label
from host.serialport import access_problem

#: the highest --baud taken (doctor, calibrate): above it no UART adapter runs, and pyserial
#: overflows on 2**31 (a traceback) where a usage error should say so
MAX_BAUD = 10_000_000
_baud_at_least_1 = number_arg(int, 1, True)


def baud_arg(text: str) -> int:
    """An argparse ``type`` for --baud: a whole number 1..MAX_BAUD bit/s. 0 would be termios B0
    (hang up the line) and 2**31 overflowed in pyserial: both are usage errors (exit 2)."""
    value = _baud_at_least_1(text)
    if value > MAX_BAUD:
        raise argparse.ArgumentTypeError(f"must be <= {MAX_BAUD} bit/s, got {text}")
    return value


baud_arg.__name__ = "int"  # argparse names the type in its own messages


def path_arg(text: str) -> str:
    """An argparse ``type`` for a file option: an empty path (``--robot "$ROBOT"`` with the
    variable unset) is a usage error naming it, not an option silently left out."""
    if not text:
        raise argparse.ArgumentTypeError("empty path '' (an unset shell variable?): give a file")
    return text


#: the fix of a segment answering DISCOVER in another protocol version (doctor's `protocol`
#: finding; ``ucr calibrate`` says the same)
PROTOCOL_FIX = (
    "reflash it: `ucr flash --port <its USB port> --robot <robot> --segment <name>` (the "
    "segments before it answered in this host's version)"
)

#: bit/s tried, in order, when the chain is silent at the configured rate
BAUD_RATES = (921600, 460800, 230400, 115200, 1000000, 500000, 250000, 57600)


def check_port(path: str, *, uid: int | None = None, groups: set[int] | None = None) -> Finding:
    """Is ``path`` present and readable/writable by this user (host/serialport.py decides)?"""
    if "://" in path:
        return Finding("port", "ok", f"{path} is a pyserial URL (not a device file)")
    found = access_problem(path, uid=uid, groups=groups)
    if found is None:
        return Finding("port", "ok", f"{path} present and permitted")
    return Finding("port", "error", found[0], found[1])


def scan_baud(port: str, configured: int) -> Finding:
    """The chain is silent at ``configured`` bit/s: which other rate does it answer at?"""
    from host.link import ChainLink, LinkError  # noqa: PLC0415

    for baud in BAUD_RATES:
        if baud == configured:
            continue
        try:
            with ChainLink(port, baud) as link:
                link.send_raw(b"\x00")  # a delimiter: ends whatever garbage came before
                descs = link.discover(timeout=0.5)
        except LinkError:
            continue
        if descs:
            return Finding(
                "baud",
                "error",
                f"no answer at {configured} bit/s, but {len(descs)} segment(s) answer at "
                f"{baud} bit/s",
                f"run with --baud {baud}, or set the chain's baud rate (the U(C)RDF's upstream "
                f"uart baud) to {configured} and reflash",
            )
    return Finding(
        "baud",
        "error",
        f"no answer at any of {', '.join(map(str, BAUD_RATES))} bit/s",
        "check power of the first segment and the TX/RX wiring (crossed)",
    )


#: What a MicroPython REPL prints (banner, prompts, the firmware's own lines, a traceback).
REPL_MARKERS = (b">>> ", b"MicroPython v", b"raw REPL; CTRL-B", b"[main] ", b"Traceback (most")
#: Seconds doctor listens before it sends a frame (a powered chain sends ALIVE every 50 ms).
LISTEN_S = 0.3


def listen(
    port: str, baud: int, seconds: float = LISTEN_S, *, who: str = "doctor"
) -> Finding | None:
    """Before any frame is sent: what does the port say unasked? A segment's USB/REPL port
    (MicroPython prompt, banner, the firmware's lines) is a finding: frames would stop or reset
    its firmware (Ctrl-C, Ctrl-D bytes). A silent port is one too: a powered first segment sends
    ALIVE unasked, so nothing answers there, and a running firmware's REPL is silent as well. Only
    a carriage return is sent (a REPL shows its prompt; the chain protocol drops it). ``who``
    names the command in the fix: ``ucr calibrate`` listens the same way before its DISCOVER,
    whose bytes would stop a segment's firmware just as doctor's would."""
    import serial  # noqa: PLC0415

    try:
        kwargs = {} if "://" in port else {"exclusive": True}
        ser = serial.serial_for_url(port, baudrate=baud, timeout=0.05, **kwargs)
    except (serial.SerialException, OSError, ValueError):
        return None  # the link open that follows says why
    seen = b""
    try:
        for probe in (b"", b"\r"):
            if probe:
                ser.write(probe)
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                seen += ser.read(256)
            if any(m in seen for m in REPL_MARKERS):
                return Finding(
                    "port",
                    "error",
                    f"{port} is a segment's REPL port (MicroPython answers there), not the chain "
                    "port",
                    "give the chain port (the first segment's upstream UART adapter) with --port; "
                    f"{who} sends nothing more here: frames would stop or reset that segment",
                )
            if seen:
                return None
    except (serial.SerialException, OSError):
        return None
    finally:
        ser.close()
    return Finding(
        "chain",
        "error",
        f"no segment answers at {baud} bit/s: the port is silent (a powered first segment sends "
        "ALIVE unasked every 50 ms)",
        "check power of the first segment and the TX/RX wiring (crossed); a wrong baud rate "
        f"(--baud) would still show garbled bytes. {who.capitalize()} sends no frame to a "
        "silent port: a "
        "segment's USB/REPL port running its firmware is silent too, and frames would reset it",
    )


def run(
    port: str,
    baud: int,
    robot: str | None,
    seconds: float,
    link: Any = None,
    *,
    report: Callable[[Finding], None] | None = None,
    progress: Callable[[str], None] | None = None,
) -> list[Finding]:
    """All checks in order; stops early where later checks cannot run (no port, no answer).
    ``report`` gets each finding as it is made and ``progress`` a line before each slow step, so
    a caller can show them at once (and keep them when Ctrl-C ends the run)."""
    from host.link import ChainLink, LinkError  # noqa: PLC0415
    from host.link_frames import ProtocolVersionError  # noqa: PLC0415

    findings: list[Finding] = []

    def add(*found: Finding) -> None:
        for f in found:
            findings.append(f)
            if report is not None:
                report(f)

    def say(text: str) -> None:
        if progress is not None:
            progress(text)

    add(check_port(port))
    if findings[-1].level == "error":
        return findings
    own = link is None
    if own:
        heard = listen(port, baud)
        if heard is not None:
            add(heard)
            return findings
    try:
        if own:
            link = ChainLink(port, baud)
    except LinkError as exc:
        add(
            Finding(
                "open",
                "error",
                str(exc),
                "is the daemon running on this port? stop it (`systemctl stop ucr-daemon`) "
                "while running doctor",
            )
        )
        return findings
    try:
        descs: list[dict] = []
        for _ in range(3):
            try:
                descs = link.discover(timeout=1.0)
            except ProtocolVersionError as exc:  # a segment answers, in another version
                add(
                    Finding(
                        "protocol",
                        "error",
                        str(exc),
                        PROTOCOL_FIX,
                        exc.position,
                    )
                )
                return findings
            except LinkError:
                descs = []
            if descs:
                break
        if not descs:
            add(
                Finding(
                    "chain",
                    "error",
                    f"no segment answers DISCOVER at {baud} bit/s",
                    "check power of the first segment, the TX/RX wiring (crossed), and that the "
                    "baud rate (--baud) matches the segments' config.json",
                )
            )
            if own:
                link.close()
                say(f"baud: trying {len(BAUD_RATES) - 1} other rates (about 0.5 s each) ...")
                add(scan_baud(port, baud))
            return findings
        add(Finding("chain", "ok", f"{len(descs)} segment(s) answer at {baud} bit/s"))
        try:  # each segment's measured bend: the load check compares with it (read-only)
            states = link.heartbeat(timeout=0.5, expected=len(descs))
        except LinkError:
            states = []
        for d in descs:
            pos = d["position"]
            state = states[pos] if isinstance(pos, int) and 0 <= pos < len(states) else None
            add(*check_segment(link, pos, d, state))
        if robot:
            add(*check_robot(robot, descs))
            add(*check_config_hash(robot, descs))
            add(*check_board(link, robot, descs))
        if seconds > 0:
            say(f"timing: HEARTBEAT round trips for {seconds:g} s ...")
            add(check_timing(link, len(descs), seconds))
        else:
            add(Finding("timing", "ok", "not checked (--seconds 0)"))
        return findings
    finally:
        if own:
            link.close()


_MARK = {"ok": "ok  ", "warning": "WARN", "error": "FAIL"}


def format_finding(f: Finding) -> str:
    """One finding as the text report shows it: its line, and its fix unless it is ok."""
    where = f"{label(f.position)} " if f.position is not None else ""
    line = f"[{_MARK[f.level]}] {where}{f.check}: {f.message}"
    if f.fix and f.level != "ok":
        line += f"\n       fix: {f.fix}"
    return line


def format_summary(findings: list[Finding]) -> str:
    bad = sum(f.level == "error" for f in findings)
    warn = sum(f.level == "warning" for f in findings)
    return f"{bad} error(s), {warn} warning(s)"


def format_text(findings: list[Finding]) -> str:
    return "\n".join([*map(format_finding, findings), format_summary(findings)])


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "doctor",
        help="find what is wrong with a segment chain (read-only: moves nothing)",
        description="Check the port, the chain and every segment, in order, each finding with "
        "its fix. Read-only: sends DISCOVER, PARAM_GET, HEARTBEAT and CALIBRATE read only. Exit "
        "1 if anything is wrong, 130 after Ctrl-C (the findings so far are kept).",
    )
    p.add_argument("--port", default="/dev/ttyUSB0", help="chain port (path or pyserial URL)")
    p.add_argument(
        "--baud", type=baud_arg, default=921600, help=f"bit/s (default 921600, 1..{MAX_BAUD})"
    )
    p.add_argument("--robot", type=path_arg, help="U(C)RDF to compare the chain with")
    p.add_argument(
        "--seconds",
        type=number_arg(float, 0.0, True, " s"),
        default=3.0,
        help="loop timing check duration (s, default 3; 0 skips the check)",
    )
    p.add_argument("--json", action="store_true", help="findings as JSON")
    p.set_defaults(func=cmd_doctor)


def _as_json(findings: list[Finding]) -> str:
    # positions counted from 1, as in the text report and everywhere else a user sees them
    out = [asdict(f) for f in findings]
    for f in out:
        if f["position"] is not None:
            f["position"] += 1
    return json.dumps(out, indent=1)


def cmd_doctor(args: argparse.Namespace) -> int:
    """Text: each finding printed as it is made, progress on stderr before each slow step. On
    Ctrl-C the findings so far stay (JSON: printed then), a one-line note says so, exit 130."""
    found: list[Finding] = []
    if args.robot:  # a file that cannot be read is a usage error, whatever the chain says
        from ucrdf.errors import UcrdfError  # noqa: PLC0415
        from ucrdf.parser import load  # noqa: PLC0415

        try:
            load(args.robot)
        except UcrdfError as exc:
            print(f"ucr: --robot: {exc}", file=sys.stderr)
            return 2

    def show(f: Finding) -> None:
        found.append(f)
        if not args.json:
            print(format_finding(f), flush=True)

    def progress(text: str) -> None:
        if not args.json:
            print(f"  ... {text}", file=sys.stderr, flush=True)

    try:
        findings = run(
            args.port, args.baud, args.robot, args.seconds, report=show, progress=progress
        )
    except KeyboardInterrupt:
        if args.json:
            print(_as_json(found), flush=True)
        print(
            f"ucr doctor: interrupted (Ctrl-C) after {len(found)} finding(s): "
            f"{format_summary(found)} so far; the checks after them did not run",
            file=sys.stderr,
        )
        return 130
    if args.json:
        print(_as_json(findings))
    else:
        for f in findings[len(found) :]:  # any not reported as made
            print(format_finding(f))
        print(format_summary(findings))
    return 1 if any(f.level == "error" for f in findings) else 0
