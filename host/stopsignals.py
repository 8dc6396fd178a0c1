"""How a long-running ``ucr`` command is stopped, one rule for all of them.

SIGTERM (a service manager, a script: a requested stop) and Ctrl-C (SIGINT) both set one event
the command waits on, so it closes what it opened either way; the exit code tells them apart:
0 after SIGTERM, 130 after Ctrl-C (128 + SIGINT, what a shell reports for a command it
interrupted). docs/daemon.md "Stopping" states the rule.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

#: the exit code after Ctrl-C
INTERRUPTED = 130

#: the long-running commands (docs/daemon.md "Stopping"); ``replay --execute`` is a one-shot
LONG_RUNNING = frozenset(
    {"daemon", "view", "record", "replay", "foxglove", "zenoh", "zenoh-router", "emulate"}
)


def stop_while_starting() -> None:
    """SIGTERM while a long-running command starts (the ``ucr`` dispatcher's parser, the
    command's heavy imports: mcap, zenoh, viser; before it takes SIGTERM and Ctrl-C itself with
    :class:`StopSignals`) ends it at once with exit 0, as a stop once it runs, not killed (143):
    what is open by then closes in its ``finally``. Ctrl-C stays ``KeyboardInterrupt`` (130)."""
    signal.signal(signal.SIGTERM, _stopped_while_starting)


def _stopped_while_starting(signum: int, frame: Any) -> None:
    raise SystemExit(0)


def starts_long_running(argv: list[str]) -> bool:
    """Whether command line ``argv`` (without the program) starts a long-running command."""
    words = [a for a in argv if not a.startswith("-")]
    if not words or words[0] not in LONG_RUNNING:
        return False
    # `--execute` as argparse takes it: any prefix of it (replay has no other --e option)
    one_shot = any(len(a) > 3 and "--execute".startswith(a.split("=")[0]) for a in argv)
    return not (words[0] == "replay" and one_shot)


class StopSignals:
    """``stop`` is set by SIGTERM or SIGINT; ``interrupted`` by SIGINT only."""

    def __init__(self) -> None:
        self.stop = threading.Event()
        self.interrupted = threading.Event()

    def install(self) -> StopSignals:
        """Take SIGTERM and SIGINT (from the main thread, as Python's ``signal`` requires)."""
        signal.signal(signal.SIGTERM, self._on_signal)
        signal.signal(signal.SIGINT, self._on_signal)
        return self

    def _on_signal(self, signum: int, frame: Any) -> None:
        if signum == signal.SIGINT:
            self.interrupted.set()
        self.stop.set()

    def exit_code(self, result: int = 0) -> int:
        """The command's ``result``; a success after Ctrl-C is 130 (a failure stays one)."""
        return INTERRUPTED if result == 0 and self.interrupted.is_set() else result
