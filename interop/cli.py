"""``ucr record``, ``ucr replay``, ``ucr foxglove``: the robot's data in ROS 2 / Foxglove tools.

Heavy imports (mcap, mcap-ros2-support) happen inside the commands; without the optional ``record``
dependencies each command says so in one line (no traceback).
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import signal
import sys
from typing import Any

from host.client_common import number_arg, port_arg
from host.extras import install_command
from host.stopsignals import stop_while_starting

_NEEDS = {
    "record": ("mcap", "mcap_ros2", "zstandard"),
    "replay": ("mcap", "mcap_ros2", "zstandard"),
    "foxglove": ("mcap_ros2",),
}


def missing_dependency(command: str) -> str | None:
    """The first module ``command`` needs that is not installed, else None."""
    for mod in _NEEDS[command]:
        try:
            importlib.import_module(mod)
        except ImportError:
            return mod
    return None


def _guard(command: str, fn: Any, parser: argparse.ArgumentParser | None = None) -> Any:
    def run(args: argparse.Namespace) -> int:
        if getattr(args, "execute", False):  # a one-shot: SIGTERM's default action, also when
            signal.signal(signal.SIGTERM, signal.SIG_DFL)  # ucr took it for `--exec` (abbreviated)
        else:
            stop_while_starting()  # (tools/cli.py did already for `ucr`; here for direct callers)
        usage = _usage_error(command, args)
        if usage and parser is not None:
            parser.error(usage)  # exit 2, as argparse's own checks
        mod = missing_dependency(command)
        if mod:
            print(f"ucr: `ucr {command}` needs the optional recording dependencies (module "
                  f"{mod!r} is missing): {install_command('record')}", file=sys.stderr)  # fmt: skip
            return 1
        _lower_priority(getattr(args, "nice", 0))
        return int(fn(args) or 0)

    return run


def _usage_error(command: str, args: argparse.Namespace) -> str | None:
    """An option combination argparse cannot express, else None."""
    if command == "replay" and not args.execute:
        given = [o for o, on in (("--go", args.go), ("--measured", args.measured)) if on]
        if given:
            return f"{' and '.join(given)} only with --execute (re-running the recorded motion)"
    if command == "record" and args.foxglove_port is None and args.foxglove_host is None:
        serve = [o for o, on in (("--serve-token-file", args.serve_token_file),
                                 ("--tls-cert", args.tls_cert), ("--tls-key", args.tls_key),
                                 ("--insecure", args.insecure),
                                 ("--allow-origin", args.allow_origin)) if on]  # fmt: skip
        if serve:
            return (f"{', '.join(serve)} only with a Foxglove server (--foxglove-port P or "
                    "--foxglove-host H)")  # fmt: skip
    return None


#: Default nice increment of these clients (as the API process and ``ucr view``): on the daemon's
#: machine the control loop keeps the CPU first.
CLIENT_NICE = 5


def _lower_priority(nice: int) -> None:
    if nice > 0 and hasattr(os, "nice"):  # >= 0: nice_arg
        try:
            os.nice(nice)
        except OSError as exc:  # not fatal: recording works at any priority
            print(f"ucr: priority unchanged ({exc.strerror})", file=sys.stderr)


POSITIVE_S = number_arg(float, 0.0, False, " s")
POSITIVE_HZ = number_arg(float, 0.0, False, " Hz")
NON_NEGATIVE_S = number_arg(float, 0.0, True, " s")
#: ``ucrdf.export``'s bound: pseudo-rigid links per bendable in /robot_description and /tf
SUBDIVISIONS = number_arg(int, 1, True, high=1000)


def nice_arg(text: str) -> int:
    """An argparse ``type``: a nice increment >= 0. Only lowering the priority is offered
    (raising it needs privileges and would compete with the daemon's control loop)."""
    v = number_arg(int, -math.inf, False)(text)
    if v < 0:
        raise argparse.ArgumentTypeError(
            f"must be >= 0, got {text}: only lowering this process's priority is offered "
            "(the daemon's control loop keeps the CPU first)"
        )
    return v


def _common(p: argparse.ArgumentParser) -> None:
    from host.client_common import add_connection_args  # noqa: PLC0415 - fast `ucr --help`

    add_connection_args(p)  # --url, --token-file, --ca, --timeout: as every API client
    p.add_argument(
        "--robot", default=None, help="U(C)RDF file (default: the file the daemon reports)"
    )
    p.add_argument(
        "--nice",
        type=nice_arg,
        default=CLIENT_NICE,
        help=f"lower this process's scheduling priority by this much, >= 0 (default "
        f"{CLIENT_NICE}: a daemon on the same machine keeps the CPU first; 0: unchanged)",
    )


OFF_LOOPBACK = (
    "loopback; any other address needs --serve-token-file and --tls-cert/--tls-key (or --insecure)"
)


def _serve(p: argparse.ArgumentParser) -> None:
    """Options of the Foxglove server's door (interop/guard.py)."""
    p.add_argument("--serve-token-file", default=None, metavar="FILE",
                   help="file (mode 0600) holding the token Foxglove clients must present "
                   "(default $UCR_FOXGLOVE_TOKEN); needed for a non-loopback address")  # fmt: skip
    # A token on a command line is visible to every user (/proc/PID/cmdline): refused with advice.
    p.add_argument("--serve-token", default=None, help=argparse.SUPPRESS)
    p.add_argument("--tls-cert", default=None, metavar="FILE",
                   help="PEM certificate (chain): serve wss:// (with --tls-key)")  # fmt: skip
    p.add_argument("--tls-key", default=None, metavar="FILE",
                   help="PEM private key of --tls-cert; mode 0600 (not group/world "
                   "readable)")  # fmt: skip
    p.add_argument("--insecure", action="store_true",
                   help="allow a non-loopback address without TLS (the token crosses the "
                   "network in clear: trusted networks only)")  # fmt: skip
    p.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN",
                   help="browser origin allowed to connect, e.g. https://app.foxglove.dev; "
                   "file:// or null (with a token only) for Lichtblick / Foxglove desktop "
                   "(repeatable; default none: only clients that send no Origin)")  # fmt: skip


def _record(args: argparse.Namespace) -> int:
    from interop.record import run  # noqa: PLC0415 - after the dependency check

    return run(args)


def _replay(args: argparse.Namespace) -> int:
    from interop.replay import run  # noqa: PLC0415

    return run(args)


def _foxglove(args: argparse.Namespace) -> int:
    from interop.foxglove import run  # noqa: PLC0415

    return run(args)


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "record", help="record the live robot into an MCAP file (ROS 2 messages)",
        description="Record the daemon's live data as ROS 2 messages (CDR) into MCAP: "
        "/joint_states, /tf, /tf_static, /robot_description, /ucr/arcs, status, events, goals, "
        "loop statistics (docs/recording.md). Ctrl-C or SIGTERM stops and closes the file.",
    )  # fmt: skip
    p.add_argument("-o", "--output", required=True, help="MCAP file to write (e.g. run.mcap)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the output file if it exists (default: refuse)")  # fmt: skip
    p.add_argument("--duration", type=POSITIVE_S, default=None, help="stop after this many s")
    p.add_argument(
        "--subdivisions",
        type=SUBDIVISIONS,
        default=10,
        help="pseudo-rigid links per bendable in /robot_description and /tf, 1..1000 (10)",
    )
    p.add_argument(
        "--viz-rate", type=POSITIVE_HZ, default=20.0, help="max rate of /tf and /ucr/arcs, Hz (20)"
    )
    p.add_argument(
        "--compression",
        choices=("zstd", "lz4", "none"),
        default="zstd",
        help="chunk compression (default zstd: smallest files; lz4: less CPU on the Pi, larger "
        "files; none: largest; every MCAP reader opens all three)",
    )
    p.add_argument(
        "--flush-interval",
        type=POSITIVE_S,
        default=1.0,
        help="close a chunk at least this often, s: at most this much is lost if the "
        "recorder is killed (1)",
    )
    p.add_argument(
        "--foxglove-port",
        type=port_arg,
        default=None,
        help="also serve the same data live to Foxglove on this port",
    )
    p.add_argument("--foxglove-host", default=None, help="address of that server "
                   f"({OFF_LOOPBACK}); alone it serves on port 8766")  # fmt: skip
    _serve(p)
    _common(p)
    p.set_defaults(func=_guard("record", _record, p))

    p = subparsers.add_parser(
        "replay", help="play an MCAP recording into Foxglove, or re-run its motion (--execute)",
        description="Play a recording back on a Foxglove WebSocket server at --rate x speed. "
        "With --execute: re-run the recorded motion on the robot (dry run unless --go).",
    )  # fmt: skip
    p.add_argument("file", help="MCAP file written by `ucr record`")
    p.add_argument("--rate", type=number_arg(float, 0.0, True), default=1.0,
                   help="playback speed, x recorded (1; 0: as fast as possible)")  # fmt: skip
    p.add_argument("--host", default="127.0.0.1", help=f"server address ({OFF_LOOPBACK})")
    p.add_argument("--port", type=port_arg, default=8766, help="Foxglove server port (8766)")
    p.add_argument("--no-foxglove", action="store_true", help="no Foxglove server (with --view)")
    p.add_argument("--view", action="store_true", help="play into the 3D view (`ucr view`) as well")
    p.add_argument("--view-host", default="127.0.0.1", help="view address (loopback)")
    p.add_argument("--view-port", type=port_arg, default=8080, help="view port (8080; 0: any free)")
    p.add_argument(
        "--wait-client",
        type=NON_NEGATIVE_S,
        default=0.0,
        help="wait this many s before playing, for a viewer to connect (0)",
    )
    p.add_argument(
        "--execute",
        action="store_true",
        help="re-run the recorded motion on the robot: prints what would move, the lead-in "
        "from the robot's pose now included (dry run)",
    )
    p.add_argument("--go", action="store_true", help="with --execute: really move the robot")
    p.add_argument(
        "--measured",
        action="store_true",
        help="with --execute: re-run the measured motion (/joint_states), not the commanded goals",
    )
    p.add_argument(
        "--sample-period",
        type=POSITIVE_S,
        default=0.1,
        help="with --execute: waypoint spacing, s (0.1)",
    )
    p.add_argument(
        "--lead-in",
        type=POSITIVE_S,
        default=2.0,
        help="with --execute: time to reach the first recorded pose, s (2)",
    )
    _serve(p)
    _common(p)
    p.set_defaults(func=_guard("replay", _replay, p))

    p = subparsers.add_parser(
        "foxglove", help="serve the live robot to Foxglove / Lichtblick (WebSocket protocol)",
        description="Serve the same topics as `ucr record` live on the Foxglove WebSocket "
        "protocol (its read-only part, served by ucr itself: docs/recording.md). Loopback by "
        "default; any other address needs --serve-token-file and --tls-cert/--tls-key "
        "(or --insecure) (docs/recording.md, security).",
    )  # fmt: skip
    p.add_argument("--host", default="127.0.0.1",
                   help=f"address to listen on ({OFF_LOOPBACK})")  # fmt: skip
    p.add_argument("--port", type=port_arg, default=8766, help="port (8766; 0: any free port)")
    p.add_argument("--duration", type=POSITIVE_S, default=None, help="stop after this many s")
    p.add_argument(
        "--subdivisions",
        type=SUBDIVISIONS,
        default=10,
        help="pseudo-rigid links per bendable, 1..1000 (10)",
    )
    p.add_argument(
        "--viz-rate", type=POSITIVE_HZ, default=20.0, help="max rate of /tf and /ucr/arcs, Hz (20)"
    )
    _serve(p)
    _common(p)
    p.set_defaults(func=_guard("foxglove", _foxglove))
