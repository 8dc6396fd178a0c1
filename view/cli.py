"""``ucr view [FILE]``: serve the 3D view of the robot (live from the daemon, or offline on FILE).

Heavy imports (viser, the app) stay inside the command so ``ucr --help`` stays fast on a Pi.
"""

# ruff: noqa: PLC0415

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path
from typing import Any

from host.api import ENV_TOKEN_FILE
from host.client_common import number_arg, port_arg
from host.extras import install_command
from host.stopsignals import StopSignals

INSTALL_HINT = f"ucr view needs the `view` extra (viser): {install_command('view')}"
VIEW_NICE = 5  # as the API process (host.api.process.API_NICE): the control loop comes first


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "view",
        help="the robot in a browser: live 3D with true arcs, sliders, tip gizmo",
        description=(
            "Without FILE: connect to the daemon (--url) and show the live robot with controls. "
            "With FILE and --offline (or no daemon reachable): show the U(C)RDF file, sliders "
            "drive FK only, the file reloads on save and its check errors show on the page."
        ),
    )
    p.add_argument("file", nargs="?", help="U(C)RDF file (offline mode, or the daemon's robot)")
    p.add_argument("--offline", action="store_true", help="never contact the daemon")
    p.add_argument("--url", default=None, help="daemon API (default $UCR_URL or loopback)")
    p.add_argument(
        "--token-file",
        default=os.environ.get(ENV_TOKEN_FILE),
        help="file (mode 0600) holding the daemon API token (default $UCR_TOKEN_FILE; or set "
        "$UCR_TOKEN)",
    )
    p.add_argument(
        "--timeout",
        type=number_arg(float, 0.0, False, " s"),
        default=5.0,
        help="seconds to wait for the daemon's replies (default 5)",
    )
    p.add_argument("--host", default="127.0.0.1", help="address to serve the page on (loopback)")
    p.add_argument(
        "--port", type=port_arg, default=8080, help="port of the page (8080; 0: any free)"
    )
    p.add_argument(
        "--allow-host",
        action="append",
        default=[],
        help="extra host name the page may be reached under (Host/Origin check; repeatable)",
    )
    p.add_argument(
        "--rate", type=float, default=40.0, help="scene updates per second (40; at most 1000)"
    )
    p.add_argument(
        "--nice",
        type=_nice_arg,
        default=VIEW_NICE,
        help=f"lower the view's scheduling priority by this much (default {VIEW_NICE}: a daemon "
        "on the same machine keeps the CPU first; 0: unchanged)",
    )
    p.add_argument("--exit-with-parent", action="store_true", help=argparse.SUPPRESS)
    p.set_defaults(func=cmd_view)


def _nice_arg(text: str) -> int:
    """An argparse ``type``: how much to lower the view's priority (0 or more: raising it is
    not offered, the daemon on the same machine comes first)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(
            f"must be >= 0, got {text}: the view only lowers its priority (0: unchanged)"
        )
    return v


def _token(args: argparse.Namespace) -> str | None:
    """The daemon API token as every client reads it (host.api.auth.read_token_file: a file
    of mode 0600 owned by us, a token of 16+ printable characters; else $UCR_TOKEN)."""
    from host.api.client import ApiAuthError, read_token

    try:
        return read_token(args.token_file)
    except ApiAuthError as exc:
        raise SystemExit(f"ucr: {exc.message}") from None


def _not_a_file(path: str) -> str | None:
    """Why the offline view cannot show ``path`` at all, else None."""
    p = Path(path)
    if not p.exists():
        return f"{p}: no such file"
    if not p.is_file():
        return f"{p}: not a file" + (" (a directory)" if p.is_dir() else "")
    return None


def _print_check(path: str) -> Any:
    """The offline source's ``on_errors``: the file's check errors on the terminal as on the
    page (``path:line: ...``), again after each save that changes them."""
    state = {"bad": False}

    def show(errors: list[str]) -> None:
        if errors:
            for e in errors:
                print(e, file=sys.stderr)
            print(f"ucr view: {len(errors)} check error(s) in {path} (shown on the page too; "
                  "it reloads on save)", file=sys.stderr, flush=True)  # fmt: skip
        elif state["bad"]:
            print(f"ucr view: {path} loads again", file=sys.stderr, flush=True)
        state["bad"] = bool(errors)

    return show


def cmd_view(args: argparse.Namespace) -> int:
    try:
        import viser  # noqa: F401
    except ModuleNotFoundError:
        print(f"ucr: {INSTALL_HINT}", file=sys.stderr)
        return 1
    logging.basicConfig(level=logging.WARNING, format="ucr view: %(message)s")
    if args.nice > 0 and hasattr(os, "nice"):
        try:
            os.nice(args.nice)
        except OSError as exc:  # not fatal: the view works at any priority
            print(f"ucr view: priority unchanged ({exc.strerror})", file=sys.stderr)
    from host.api.client import ApiError
    from host.listen import check_listen
    from view.app import ViewApp
    from view.guard import GuardError, is_loopback
    from view.source import LiveSource, OfflineSource, RobotFileError

    if not 0 < args.rate <= 1000:
        print(f"ucr: --rate must be in (0, 1000] updates per second, got {args.rate:g}",
              file=sys.stderr)  # fmt: skip
        return 2
    try:  # before anything starts: else viser waits forever on an address it cannot bind
        check_listen(args.host, args.port)
    except OSError as exc:
        print(f"ucr: cannot serve the view: {exc}", file=sys.stderr)
        return 1
    control = True
    if not is_loopback(args.host):
        # the page can move hardware and has no login of its own: off loopback it only shows
        control = False
        print(
            f"ucr view: serving on {args.host} (not loopback): view only, no controls. "
            "To control remotely use an SSH tunnel to the loopback page.",
            file=sys.stderr,
        )
    source: Any
    if args.offline:
        if not args.file:
            print("ucr: --offline needs a U(C)RDF FILE", file=sys.stderr)
            return 2
        why = _not_a_file(args.file)
        if why:
            print(f"ucr: {why}", file=sys.stderr)
            return 1
        source = OfflineSource(args.file, on_errors=_print_check(args.file)).start()
    else:
        token = _token(args)
        try:
            source = LiveSource(args.url, token, args.file, timeout=args.timeout).start()
        except RobotFileError as exc:
            # the daemon answered: the file is what is wrong, not the daemon (never "no daemon")
            for e in exc.errors:
                print(e, file=sys.stderr)
            print(f"ucr: the daemon answers, but {exc.path} does not load ({len(exc.errors)} "
                  "check error(s) above): fix it, or run `ucr view` without FILE to view the "
                  "daemon's own robot", file=sys.stderr)  # fmt: skip
            return 1
        except PermissionError as exc:  # the daemon refused the token (ApiAuthError)
            print(f"ucr: the daemon refused this view's token: {exc}", file=sys.stderr)
            return 1
        except (ConnectionError, RuntimeError, TimeoutError, ApiError) as exc:
            # (a daemon too slow to answer: ApiTimeoutError, a TimeoutError and an ApiError)
            if not args.file:
                print(f"ucr: {exc}", file=sys.stderr)
                return 1
            why = _not_a_file(args.file)
            if why:
                print(f"ucr: {exc}; and offline: {why}", file=sys.stderr)
                return 1
            if isinstance(exc, ConnectionError):
                said = f"no daemon ({exc})"
            elif isinstance(exc, TimeoutError):
                said = f"the daemon does not answer ({exc})"
            else:
                said = f"the daemon answers but cannot serve the view ({exc})"
            print(f"ucr view: {said}; offline on {args.file}", file=sys.stderr)
            source = OfflineSource(args.file, on_errors=_print_check(args.file)).start()
        if getattr(source, "scope", "control") == "read":
            print("ucr view: view only: read token (the daemon API token has the read scope; "
                  "no page gets controls)", file=sys.stderr)  # fmt: skip
    try:
        app = ViewApp(
            source, args.host, args.port, tuple(args.allow_host), control, args.rate
        ).start()
    except (OSError, GuardError) as exc:
        source.stop()
        print(f"ucr: cannot serve the view: {exc}", file=sys.stderr)
        return 1
    # Ctrl-C (exit 130) or SIGTERM (0) closes the view: taken before the URL is printed, so a
    # signal sent once the URL is out (the demo's SIGTERM) finds the handler in place
    signals = StopSignals().install()
    # the URL that works: with the page token when the page can move the robot (view/guard.py)
    print(f"ucr view: {app.url}  ({source.mode}; Ctrl-C to stop)", flush=True)
    parent = os.getppid()
    try:
        while not (args.exit_with_parent and os.getppid() != parent):  # started by the demo
            if signals.stop.wait(1.0):
                break
        return signals.exit_code()
    finally:
        app.stop()
