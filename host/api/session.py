"""Per-connection state of the API server: the client session, its subscriptions, a chunked upload
(kept by the request side, :mod:`host.api.dispatch`, with the session that owns it), a parsed
request.

Plain data holders used by :mod:`host.api.connection` (outbox, fan-out) and
:mod:`host.api.dispatch` (requests); no I/O here.
"""

from __future__ import annotations

import asyncio
import collections
import contextvars
import ipaddress
import time
from typing import Any, NamedTuple

from websockets.asyncio.server import ServerConnection

from host.api import schema as S
from host.api.auth import (
    Token,
)
from host.api.feed import admits

#: The ``on_behalf_of`` of the request being served (a context variable: each request's task
#: sees its own; None outside a request): its audit line's ``for=`` and its command's sender.
ON_BEHALF_OF: contextvars.ContextVar[str | None] = contextvars.ContextVar(
    "ucr_on_behalf_of", default=None
)


class _Request(NamedTuple):
    """A request that parsed and passed the scope check: id, op and validated parameters."""

    rid: Any
    op: str
    params: dict
    on_behalf_of: str | None = None  # who the client says it acts for (the audit line's for=)


class _Subscription:
    """One API subscription: kinds, per-kind rate limiting and counters."""

    def __init__(self, sid: int, kinds: list[str], max_rate: float | None) -> None:
        self.sid = sid
        self.kinds = kinds
        self.min_period = 1.0 / max_rate if max_rate else 0.0
        self.last_sent: dict[str, float] = {}
        self.dropped = 0  # lost because the client read too slowly
        self.thinned = 0  # skipped on purpose because of max_rate
        self.sent = 0

    def admit(self, kind: str, t: float) -> bool:
        """Whether a message of ``kind`` stamped ``t`` (s) goes to this subscription: the rule
        the daemon side thins by too (host/api/feed.py ``admits``, with its slack)."""
        if self.min_period <= 0.0 or kind not in S.RATE_LIMITED_KINDS:
            return True
        if not admits(t, self.last_sent.get(kind), self.min_period):
            self.thinned += 1
            return False
        self.last_sent[kind] = t
        return True


class _Upload:
    """A trajectory being uploaded in chunks (``trajectory.upload``)."""

    def __init__(self, uid: int, owner: Any) -> None:
        self.uid = uid
        self.owner = owner  # the _Session that uploads it
        self.points: list[dict] = []
        self.last_t = 0.0
        self.t_touched = time.monotonic()


class _Session:
    """State of one connected client."""

    def __init__(self, ws: ServerConnection, token: Token | None, anonymous_scope: str) -> None:
        self.ws = ws
        self.peer = _peer(ws)
        self.agent = _agent(ws)  # the program it says it is (User-Agent): for the audit log
        self.scope = token.scope if token is not None else anonymous_scope
        self.who = token.label if token is not None else "anonymous"
        self.authenticated = token is not None  # a token let it in (else: no tokens configured)
        self.subs: dict[int, _Subscription] = {}
        self.goals: dict[Any, Any] = {}  # goal id -> last pushed status
        self.ffc_active: set[str] = set()  # bendables this client last drove with non-zero input
        self.ffc_audited: set[str] | None = None  # deflected set last written to the audit log
        self.stream: collections.deque[tuple[_Subscription, str]] = collections.deque()
        self.priority: collections.deque[str] = collections.deque()
        self.queued_bytes = 0
        self.wakeup = asyncio.Event()
        self.closed = False
        self.tokens = 0.0  # request budget (token bucket)
        self.t_refill = time.monotonic()
        self.throttled = 0  # requests read later: this connection's own budget was used up
        self.share: Any = None  # its token's share of the global budget (host.api.connection)
        self.rate_limited = 0  # requests refused: its token's share was used up
        self.t_progress = time.monotonic()  # last time the sender got a message out


def command_source(session: _Session) -> dict[str, str]:
    """Who sends a command (its connection's address and program, and the ``on_behalf_of`` of
    the request being served): the daemon keeps it as the cFFC's ``input_from`` and a goal's
    ``from``, which any client may read, so never its token's label (the audit line has it)."""
    source = {"peer": session.peer, "client": session.agent}
    if (behalf := ON_BEHALF_OF.get()) is not None:
        source["for"] = behalf
    return source


def _peer(ws: Any) -> str:
    try:
        addr = ws.remote_address
        return f"{addr[0]}:{addr[1]}"
    except Exception:  # noqa: BLE001 - purely cosmetic
        return "?"


def _agent(ws: Any) -> str:
    """The connection's User-Agent (``ucr view``, ``ucr zenoh``, a browser's), at most 64
    characters; ``-`` when it sent none."""
    try:
        agent = ws.request.headers.get("User-Agent") or "-"
    except Exception:  # noqa: BLE001 - purely informative
        return "-"
    return str(agent)[:64]


def _is_loopback_ip(ip: str) -> bool:
    try:
        return ipaddress.ip_address(ip).is_loopback
    except ValueError:
        return False
