"""Requests a client sends on behalf of someone else (``ucr view`` for its pages): the
``on_behalf_of`` field the daemon writes into their audit lines (docs/api.md "Audit"), and the
sender the daemon then names for a command (a cFFC's ``input_from``, a goal's ``from``)."""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from typing import Any

#: Whom the requests sent in this context are for (see :func:`on_behalf_of`).
_ON_BEHALF_OF: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "ucr_client_on_behalf_of", default=None
)


@contextlib.contextmanager
def on_behalf_of(label: str | None) -> Iterator[None]:
    """Requests this thread sends inside the block carry ``on_behalf_of: label``, which the
    daemon writes into their audit lines (``for=…``): for a client that acts for others, as
    ``ucr view`` does for its pages. A declaration, like the User-Agent (docs/api.md "Audit")."""
    token = _ON_BEHALF_OF.set(label)
    try:
        yield
    finally:
        _ON_BEHALF_OF.reset(token)


def sender_words(sender: Any) -> str:
    """Who sent a command, as the daemon names it (``{"peer", "client", "for"}``), in words:
    ``API client 'gamepad' for 'stick js0' at 127.0.0.1:59320``; "" when it does not say. The
    client's own words are quoted as Python literals, so no control character reaches a
    terminal or a log."""
    if not isinstance(sender, dict):
        return ""
    client = sender.get("client")
    words = f"API client {client if isinstance(client, str) else '-'!r}"
    if isinstance(sender.get("for"), str):
        words += f" for {sender['for']!r}"
    peer = sender.get("peer")
    if isinstance(peer, str):
        words += f" at {peer if peer.isprintable() and ' ' not in peer else repr(peer)}"
    return words


__all__ = ["on_behalf_of", "sender_words"]
