"""The ``ucr`` command: one dispatcher, each area registers its own subcommands.

Each module in ``_AREAS`` exposes ``register(subparsers)``; it adds its subcommands and sets
``func`` on each parser (a callable taking the parsed args and returning an exit code). Areas keep
heavy imports inside their command functions so ``ucr --help`` stays fast on a Raspberry Pi.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from host.extras import MissingPart
from host.stopsignals import starts_long_running, stop_while_starting

_AREAS = (
    "ucrdf.cli",
    "tools.tools_cli",
    "host.cli",
    "host.doctor",
    "host.calibrate_cli",
    "tools.demo",
    "host.client_cli",
    "interop.cli",
    "interop.zenoh.cli",
    "view.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ucr", description="Modular soft continuum robots: U(C)RDF, segments, host daemon."
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    parser.commands = sub  # type: ignore[attr-defined] - main() finds a command's own parser
    for name in _AREAS:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:
                raise
            continue  # area not installed in this build
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    if starts_long_running(sys.argv[1:] if argv is None else argv):
        stop_while_starting()  # SIGTERM while its parser is built and it starts: exit 0, not 143
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # the command's own usage, not the dispatcher's (`ucr status --bogus`)
        command = parser.commands.choices.get(args.command, parser)
        command.error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130
    except MissingPart as exc:
        # an optional part (extra) this command needs is not installed: say what to install
        print(f"ucr: error: {exc}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # the reader went away (`ucr watch | head`): stop quietly, as Unix tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a tool killed by the pipe


if __name__ == "__main__":
    sys.exit(main())
