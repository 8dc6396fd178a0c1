"""Requests a client sends on behalf of someone else (``ucr view`` for its pages): the
``on_behalf_of`` field the daemon writes into their audit lines (docs/api.md "Audit")."""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator

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


__all__ = ["on_behalf_of"]
