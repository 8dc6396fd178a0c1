"""Errors shared across the host (no host imports: any module may raise or catch them)."""

from __future__ import annotations

from typing import Any


def not_utf8(exc: UnicodeDecodeError) -> str:
    """Why bytes are not text, where: ``not UTF-8 text (byte 0xff at offset 0)``."""
    bad = exc.object[exc.start : exc.start + 1].hex()
    return f"not UTF-8 text (byte 0x{bad} at offset {exc.start})"


class ConfigError(ValueError):
    """A configuration file or value is wrong; ``str()`` is one line: ``file: key: problem``."""

    def __init__(self, source: str, key: str, problem: str):
        self.source = source
        self.key = key
        self.problem = problem
        super().__init__(f"{source}: {key}: {problem}" if key else f"{source}: {problem}")


class DaemonError(RuntimeError):
    """The daemon cannot start or go on (message says why, one line)."""


class TopologyError(DaemonError):
    """The discovered chain does not match the description (and ``--adopt`` was not given)."""

    def __init__(self, comparison: Any, message: str):
        self.comparison = comparison  # a host.topology.Comparison
        super().__init__(message)


class GoalNotFound(LookupError):
    """No goal with this id."""
