"""Audit trail: who moved the robot or changed its controllers, on the ``ucr.audit`` logger.

One line per op that can cause motion or changes controllers (trajectory send/cancel, cFFC input
when the set of deflected sticks changes, manual takeover, controller switch and hand-back, the
zero command sent for a client that vanished): peer, token label, scope, op, goal id, summary.
The logger has its own handler on stderr (journald under systemd) and does not propagate, so it
stays on when the rest of the logging is turned down (``--log-level warning``).
"""

from __future__ import annotations

import logging
import sys
from typing import Any

AUDIT_LOGGER = "ucr.audit"
_audit = logging.getLogger(AUDIT_LOGGER)


class _StderrHandler(logging.StreamHandler):
    """Writes each record to ``sys.stderr`` as it is when the record comes (not the stream of
    the moment the logger was set up, which a test harness or a redirection may have closed)."""

    @property  # type: ignore[override]
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        pass


def audit_logger() -> logging.Logger:
    """The audit logger, set up once: INFO, own stderr handler, not propagated."""
    if not getattr(_audit, "_ucr_ready", False):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s AUDIT %(message)s"))
        _audit.addHandler(handler)
        _audit.setLevel(logging.INFO)
        _audit.propagate = False
        _audit._ucr_ready = True  # type: ignore[attr-defined]
    return _audit


def audit_log(peer: str, who: str, scope: str, op: str, goal: Any, summary: str) -> None:
    """One audit record (fields as ``key=value``, the summary last)."""
    audit_logger().info(
        "peer=%s token=%s scope=%s op=%s goal=%s %s", peer, who, scope, op, goal, summary[:500]
    )
