"""Audit trail: who moved the robot or changed its controllers, on the ``ucr.audit`` logger.

One line per op that can cause motion or changes controllers (trajectory send/cancel, cFFC input
when the set of deflected sticks changes, manual takeover, controller switch and hand-back, the
zero command sent for a client that vanished): peer, token label, scope, the client program
(as the connection declares it), op, goal id, summary.
The logger has its own handler on stderr (journald under systemd) and does not propagate, so it
stays on when the rest of the logging is turned down (``--log-level warning``).

One record is one line, whatever a client sends: a field is written as it is only when it is a
plain word (letters, digits, ``._:@/+-``), else as a Python literal (``'x\\n…'``); callers
write the values a client chose into the summary with ``!r``, and any character that is not
printable left in the summary (a line break in a daemon message quoting a request) is escaped.
"""

from __future__ import annotations

import logging
import re
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


_PLAIN = re.compile(r"[A-Za-z0-9_.:@/+\-]{1,128}")


def audit_field(value: Any) -> str:
    """A field's value as written: a plain word as it is, anything else as a Python literal."""
    if value is None or isinstance(value, bool | int):
        return str(value)
    text = str(value)
    return text if _PLAIN.fullmatch(text) else repr(text)


def _one_line(text: str) -> str:
    """``text`` with every character that is not printable escaped (``\\n``, ``\\u2028``)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def audit_log(
    peer: str,
    who: str,
    scope: str,
    op: str,
    goal: Any,
    summary: str,
    client: str = "-",
    on_behalf_of: str | None = None,
) -> None:
    """One audit record, one line (fields as ``key=value``, the summary last). ``client``: the
    program the connection said it is (its WebSocket User-Agent, e.g. ``ucr view``): what it
    declares, not what the token proves. ``on_behalf_of``: whom the request said it was for (a
    ``for=`` field after ``client=``, only when given), declared as well."""
    behalf = "" if on_behalf_of is None else f" for={audit_field(on_behalf_of)}"
    audit_logger().info(
        "peer=%s token=%s scope=%s client=%s%s op=%s goal=%s %s",
        *(audit_field(v) for v in (peer, who, scope, client)),
        behalf,
        *(audit_field(v) for v in (op, goal)),
        _one_line(summary)[:500],
    )
