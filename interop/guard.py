"""The Foxglove server and its door: a read-only Foxglove WebSocket server
(:mod:`interop.foxglove_protocol`, served with ``websockets``) that checks every opening handshake
with the same rules as the daemon's API (one implementation: :mod:`host.api.guard` for Origin,
Host and path, :mod:`host.api.auth` for tokens, the failed-token back-off and the bind policy).
It is the only listener: no other server runs behind it, so nothing bypasses the checks.

- ``Origin``: refused (403) unless absent (scripts, ROS tools) or listed (``allowed_origins``,
  e.g. ``https://app.foxglove.dev``; ``file://`` for a desktop app whose page is a local file;
  ``null`` only with a token: the guard's rule, :mod:`host.api.guard`): a web page in a local
  browser cannot read the robot;
- ``Host``: an IP literal or a name of this server (refuses DNS-rebinding pages); path ``/``;
- TLS: ``tls_cert``/``tls_key`` (PEM; the key file private, mode 0600: the API's rule and code,
  :func:`host.api.auth.server_tls_context`) make it a ``wss://`` server;
- token: required for any non-loopback bind (which also needs TLS or ``insecure``), and when
  given, required on loopback too; at least 16 characters; presented as
  ``Authorization: Bearer <token>`` or, for viewers that cannot set headers, a ``?token=`` query
  parameter; compared in constant time; wrong tokens meet the API's back-off
  (:class:`host.api.auth.Backoff`, in the API's order): after a few failures a wrong token gets
  429 (``Retry-After``), while a valid one always gets in.

Limits: at most :data:`MAX_CONNECTIONS` accepted connections (503 beyond) and
:data:`MAX_PENDING` still in their opening handshake, from the TCP accept (with TLS, the TLS
handshake included) (a new one evicts the oldest that got least
far: ``host.api.admission.Admission``, the API's rule); :data:`MAX_PER_PEER` per non-loopback
address, pending and accepted, refused beyond that before any work; a client
frame above :data:`MAX_CLIENT_FRAME` closes the connection (1009) before it is read; per client
at most :data:`DATA_BACKLOG` messages / :data:`DATA_BACKLOG_BYTES` wait to be sent (the oldest
are dropped, counted), and a client that leaves :data:`CONTROL_BACKLOG` replies unread is closed.
Every client message is answered per the protocol: a malformed or unsupported one with a
``status`` message (counted, logged once per connection), never an exception.

Channels: the publisher advertises every topic it will write before the first message
(:meth:`FoxgloveGuard.advertise`: the live feed the topics of :mod:`interop.topics`, a replay the
recording's channels), so a client (Foxglove subscribes after the advertisement) is subscribed
when a one-shot topic's only message comes. Latched topics (``latched``): the last message is
kept and sent to each new subscriber of the topic, on its subscription, and to it only.

A malformed handshake (no WebSocket upgrade, e.g. ``curl``; no or a foreign subprotocol; not HTTP)
is refused by ``websockets`` itself; it is logged as one line (``Foxglove: refused ADDR: why``)
like the guard's own refusals, not as a traceback.
"""

from __future__ import annotations

import asyncio
import logging
import math
import sys
import threading
import time
from collections import deque
from collections.abc import Iterable
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from host.api.admission import (
    AUTHORIZING,
    REFUSING,
    VERIFIED,
    Admission,
    admitted_connections,
    peer_ip,
)
from host.api.auth import (
    AuthConfigError,
    Backoff,
    Token,
    check_bind,
    check_token_text,
    find_token,
    server_tls_context,
)
from host.api.guard import NULL_NEEDS_TOKEN, GuardConfigError, WebGuard
from interop import foxglove_protocol as P
from interop import ros2

log = logging.getLogger(__name__)
SUBPROTOCOLS = P.SUBPROTOCOLS

MAX_CONNECTIONS = 32  # accepted WebSocket connections (a few viewers is the use)
#: TCP connections still in their opening handshake; when full, a new one evicts the oldest that
#: got least far (host.api.admission.Admission, as the API): idle sockets cannot keep a viewer out
MAX_PENDING = 16
MAX_PER_PEER = 8  # per non-loopback address, pending and open (loopback: only the totals)
MAX_CLIENT_FRAME = 64 * 1024  # a client sends subscribe/unsubscribe: small JSON (the API's 64 KiB)
DATA_BACKLOG = 1024  # messages queued per client (foxglove-sdk's default); oldest dropped
DATA_BACKLOG_BYTES = 4 * 1024 * 1024  # bytes queued per client (the API's outbox)
CONTROL_BACKLOG = 256  # replies/advertisements queued per client; a client this far behind: closed
OPEN_TIMEOUT_S = 5.0  # opening handshake
AUTH_HOLD_S = 1.0  # during a token back-off, each attempt waits this before its check (the API's)
ENCODINGS = [ros2.MESSAGE_ENCODING]  # ROS 2 CDR; schemas are ros2msg text


class GuardError(ValueError):
    """A refused configuration (non-loopback without token or TLS, bad token, bad origin)."""


class _Client:
    """One accepted connection: its subscriptions and what waits to be sent to it (guarded by
    the server's lock; the writer task drains it)."""

    def __init__(self, ws: ServerConnection, loop: asyncio.AbstractEventLoop) -> None:
        self.ws = ws
        self.loop = loop
        self.subs: dict[int, int] = {}  # subscription id -> channel id
        self.by_channel: dict[int, int] = {}  # channel id -> subscription id
        self.control: deque[str] = deque()
        self.data: deque[tuple[int, int, bytes]] = deque()  # (subscription id, log time, CDR)
        self.data_bytes = 0
        self.dropped = 0
        self.invalid = 0
        self.overflow = False
        self.wake = asyncio.Event()
        self._wake_pending = False

    def _notify(self) -> None:
        if not self._wake_pending:
            self._wake_pending = True
            try:
                self.loop.call_soon_threadsafe(self.wake.set)
            except RuntimeError:  # the loop is closed: the server stopped
                pass

    def push_control(self, text: str) -> None:
        if len(self.control) >= CONTROL_BACKLOG:
            self.overflow = True
        else:
            self.control.append(text)
        self._notify()

    def push_data(self, sub_id: int, t_ns: int, data: bytes) -> int:
        """Queue a message; returns how many old ones were dropped to make room."""
        self.data.append((sub_id, t_ns, data))
        self.data_bytes += len(data)
        dropped = 0
        while len(self.data) > 1 and (
            len(self.data) > DATA_BACKLOG or self.data_bytes > DATA_BACKLOG_BYTES
        ):
            self.data_bytes -= len(self.data.popleft()[2])
            dropped += 1
        self.dropped += dropped
        self._notify()
        return dropped

    def pop(self) -> str | bytes | bool | None:
        """The next frame to send, True to close (too far behind), None when idle."""
        if self.overflow:
            return True
        if self.control:
            return self.control.popleft()
        if self.data:
            sub_id, t_ns, data = self.data.popleft()
            self.data_bytes -= len(data)
            return P.message_data(sub_id, t_ns, data)
        self._wake_pending = False
        return None


class FoxgloveGuard:
    """A read-only Foxglove WebSocket server on ``host:port`` that checks every handshake; runs
    its own event loop in a thread. :meth:`write` (any thread) publishes a message."""

    def __init__(
        self,
        host: str,
        port: int,
        token: str | None = None,
        allowed_origins: tuple[str, ...] | list[str] = (),
        insecure: bool = False,
        *,
        name: str = "ucr",
        latched: Iterable[str] = (),
        backoff: Backoff | None = None,
        auth_hold_s: float = AUTH_HOLD_S,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ) -> None:
        try:
            tokens = (
                (Token(check_token_text(token, "the Foxglove token"), "read", "foxglove"),)
                if token is not None
                else ()
            )
            self.web = WebGuard.build(bind=host, port=port, origins=allowed_origins, path="/",
                                      token_required=bool(tokens))  # fmt: skip
            if bool(tls_cert) != bool(tls_key):
                raise AuthConfigError("TLS needs both --tls-cert and --tls-key")
            self._ssl = server_tls_context(tls_cert, tls_key) if tls_cert and tls_key else None
        except (AuthConfigError, GuardConfigError) as exc:
            hint = " (--serve-token-file FILE)" if NULL_NEEDS_TOKEN in str(exc) else ""
            raise GuardError(f"Foxglove server: {exc}{hint}") from None
        try:
            check_bind(host, tokens, tls=self._ssl is not None, insecure=insecure)  # the API's
        except AuthConfigError:  # its advice names the API's settings: ours are options
            raise GuardError(_bind_refusal(host, bool(tokens))) from None
        self.name = name
        self.latched_topics = frozenset(latched)
        self.host = host
        self.requested_port = port
        self.tokens = tokens
        self.port: int | None = None
        self.refused = 0  # handshakes refused (guard rules, token, back-off, malformed)
        self.refused_connections = 0  # TCP connections over the caps
        self.evicted_pending = 0  # connections closed in their handshake to make room
        self.connections = 0  # accepted WebSocket connections, ever
        self.invalid_messages = 0  # client messages answered with a status; frames too big
        self.dropped = 0  # data messages dropped for slow clients
        self.backoff = backoff if backoff is not None else Backoff()
        self.auth_hold_s = auth_hold_s
        self._admission = Admission(MAX_CONNECTIONS, MAX_PENDING, MAX_PER_PEER)
        self._at_cap = False
        self._session = str(time.time_ns())
        self._lock = threading.Lock()  # channels, kept messages, clients and their queues
        self._channels: dict[str, P.ChannelInfo] = {}
        self._channel_ids: dict[int, P.ChannelInfo] = {}
        self._kept: dict[str, tuple[bytes, int]] = {}
        self._clients: set[_Client] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="foxglove-guard", daemon=True)

    def start(self) -> FoxgloveGuard:
        self._thread.start()
        self._ready.wait(10)
        if self._error is not None:
            raise self._error
        if self.port is None:
            raise GuardError("the Foxglove guard did not start")
        return self

    def stop(self) -> None:
        """Stop serving (again: nothing)."""
        loop = self._loop
        if loop is not None and self._stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:  # closed meanwhile: stopped already
                pass
        if self._thread.is_alive():
            self._thread.join(5)

    # -- data (any thread) ---------------------------------------------------------------------
    def advertise(self, channels: Iterable[tuple[str, str, str]]) -> None:
        """Advertise topics before any message of theirs: ``(topic, typename, schema)`` each
        (topics already advertised are left as they are). A client subscribes to a channel
        only after it is advertised (as Foxglove does), so a topic first advertised by the
        :meth:`write` of its first message would lose that message to every client: whoever
        publishes advertises the topics it will write first."""
        with self._lock:
            new = [self._channel(*c) for c in channels if c[0] not in self._channels]
            if new:
                text = P.advertise(new)
                for c in self._clients:
                    c.push_control(text)

    def _channel(self, topic: str, typename: str, schema: str) -> P.ChannelInfo:
        """A new channel for ``topic`` (under the lock; advertising it is the caller's)."""
        ch = P.ChannelInfo(len(self._channels) + 1, topic, ros2.MESSAGE_ENCODING, typename,
                           ros2.SCHEMA_ENCODING, schema)  # fmt: skip
        self._channels[topic] = ch
        self._channel_ids[ch.id] = ch
        return ch

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        """Publish one encoded message: keep it if latched, queue it for every client subscribed
        to the topic. A topic not advertised before (:meth:`advertise`) is advertised now, and
        this message goes to no client (none can have subscribed to it yet) unless latched."""
        t_ns = min(max(int(t_ns), 0), P.U64_MAX)
        with self._lock:
            ch = self._channels.get(topic)
            if ch is None:
                ch = self._channel(topic, typename, schema)
                text = P.advertise([ch])
                for c in self._clients:
                    c.push_control(text)
            if topic in self.latched_topics:
                self._kept[topic] = (data, t_ns)
            for c in self._clients:
                sub_id = c.by_channel.get(ch.id)
                if sub_id is not None:
                    self.dropped += c.push_data(sub_id, t_ns, data)

    def latched(self, topic: str) -> tuple[bytes, int] | None:
        """The last message (CDR bytes, log time ns) of a latched topic, else None."""
        with self._lock:
            return self._kept.get(topic)

    # -- server --------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        conn_class = self._connection_class()  # (it does the TLS: admitted first, as the API)
        async with serve(
            self._handle, self.host, self.requested_port, subprotocols=SUBPROTOCOLS,
            process_request=self._authorize, create_connection=conn_class,
            max_size=MAX_CLIENT_FRAME, max_queue=4, compression=None,
            open_timeout=OPEN_TIMEOUT_S, ping_interval=20, ping_timeout=20,
            server_header="ucr-foxglove", logger=_HandshakeLog(self),
        ) as server:  # fmt: skip
            self.port = next(iter(server.sockets)).getsockname()[1]
            self.web = self.web.with_port(self.port)
            self._ready.set()
            await self._stop.wait()
            conn_class.ucr_abort_tls()
            server.close(close_connections=True)
            await server.wait_closed()

    def _connection_class(self) -> type[ServerConnection]:
        """ServerConnection admitted before any work (at its TCP accept, before any TLS
        handshake) as the API's server admits them (:class:`host.api.admission.Admission`: per-peer
        cap; pending cap with eviction of the oldest pending connection that got least far; only
        accepted ones count in the total)."""
        guard = self

        def refused(ip: str) -> None:
            guard.refused_connections += 1
            if not guard._at_cap:  # one line per episode, not one per connection
                guard._at_cap = True
                log.warning("Foxglove: refusing connections from %s: at most %d per address",
                            ip, MAX_PER_PEER)  # fmt: skip

        def evicted() -> None:
            guard.evicted_pending += 1

        admitted = admitted_connections(ServerConnection, guard._admission, refused, evicted,
                                        tls=guard._ssl, tls_timeout=OPEN_TIMEOUT_S)  # fmt: skip

        class _Capped(admitted):  # type: ignore[misc, valid-type]
            def ucr_gone(self) -> None:
                guard._at_cap = False

        return _Capped

    def _refuse(self, conn: ServerConnection, status: HTTPStatus, why: str) -> Response:
        self.refused += 1
        log.warning("Foxglove: refused %s: %s", conn.remote_address, why)
        return conn.respond(status, why + "\n")

    async def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        """Guard (Origin, Host, path), then the token, in the API's order
        (``host.api.server.ApiServer._authorize``) with its back-off (:class:`Backoff`): a valid
        token always gets in; while the back-off is on for this address, every attempt first
        waits ``auth_hold_s`` (valid ones too: an early answer would tell a guesser it was
        wrong), and a wrong token gets 429 without being counted again."""
        self._admission.advance(conn, AUTHORIZING)
        parts = urlsplit(request.path)
        refusal = self.web.check(parts.path, request.headers)
        if refusal is not None:
            return self._refuse(conn, HTTPStatus(refusal.status), refusal.reason)
        if not self.tokens:
            return self._open(conn)
        ip = peer_ip(conn.remote_address)
        header = request.headers.get("Authorization", "")
        if not header.lower().startswith("bearer "):
            given = (parse_qs(parts.query).get("token") or [""])[0]
            header = f"Bearer {given}"
        valid = find_token(self.tokens, header) is not None
        # while it waits out the hold: a valid one is evicted last, a wrong one first
        self._admission.advance(conn, VERIFIED if valid else REFUSING)
        if self.backoff.blocked_for(ip) > 0 and self.auth_hold_s > 0:
            await asyncio.sleep(self.auth_hold_s)
        if valid:
            return self._open(conn)
        wait = self.backoff.blocked_for(ip)
        if wait > 0:  # counted, not logged (as the API)
            self.refused += 1
            why = f"missing or wrong token; too many failed attempts: retry in {wait:.0f} s\n"
            response = conn.respond(HTTPStatus.TOO_MANY_REQUESTS, why)
            response.headers["Retry-After"] = str(math.ceil(wait))
            return response
        backoff = self.backoff.failed(ip)
        return self._refuse(conn, HTTPStatus.UNAUTHORIZED, "missing or wrong token"
                            + (f" (back-off {backoff:.0f} s)" if backoff else ""))  # fmt: skip

    def _open(self, conn: ServerConnection) -> Response | None:
        """Count an accepted handshake open (None), or the 503 when all are taken."""
        if self._admission.promote(conn, control=True):
            return None
        if not self._admission.is_pending(conn):  # evicted while its check waited: gone
            return conn.respond(HTTPStatus.SERVICE_UNAVAILABLE, "evicted\n")
        self.refused_connections += 1
        response = self._refuse(conn, HTTPStatus.SERVICE_UNAVAILABLE,
                                f"too many connections (at most {MAX_CONNECTIONS})")  # fmt: skip
        response.headers["Retry-After"] = "5"
        return response

    async def _handle(self, ws: ServerConnection) -> None:
        self.connections += 1
        client = _Client(ws, asyncio.get_running_loop())
        with self._lock:
            client.push_control(P.server_info(self.name, self._session, ENCODINGS))
            if self._channels:
                client.push_control(P.advertise(list(self._channels.values())))
            self._clients.add(client)
        writer = asyncio.create_task(self._writer(client))
        try:
            async for msg in ws:
                self._on_message(client, msg)
        except ConnectionClosed as exc:
            if exc.sent is not None and exc.sent.code == 1009:  # websockets: frame too big
                self.invalid_messages += 1
                log.warning("Foxglove: closed %s: a frame above %d bytes", ws.remote_address,
                            MAX_CLIENT_FRAME)  # fmt: skip
        finally:
            with self._lock:
                self._clients.discard(client)
            writer.cancel()
            try:
                await writer
            except (asyncio.CancelledError, ConnectionClosed):
                pass
            if client.invalid > 1:
                log.info("Foxglove: %s sent %d invalid messages", ws.remote_address,
                         client.invalid)  # fmt: skip
            if client.dropped:
                log.info("Foxglove: %d messages dropped for slow client %s", client.dropped,
                         ws.remote_address)  # fmt: skip

    async def _writer(self, client: _Client) -> None:
        """Send what is queued for this client, in order (control messages first)."""
        while True:
            client.wake.clear()
            with self._lock:
                item = client.pop()
            if item is None:
                await client.wake.wait()
            elif item is True:
                log.warning("Foxglove: closing %s: %d replies unread", client.ws.remote_address,
                            CONTROL_BACKLOG)  # fmt: skip
                await client.ws.close(1008, "too many unread messages")
                return
            else:
                await client.ws.send(item)

    def _on_message(self, client: _Client, msg: str | bytes) -> None:
        """Act on one client message; anything else is answered with a status message."""
        req = P.parse_client(msg)
        with self._lock:
            if isinstance(req, P.Subscribe):
                problems = self._subscribe(client, req.subscriptions)
            elif isinstance(req, P.Unsubscribe):
                problems = self._unsubscribe(client, req.ids)
            else:
                problems = [req]
            if problems:
                first = problems[0]
                more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
                client.push_control(P.status(first.level, first.message + more))
        if problems:
            client.invalid += 1
            self.invalid_messages += 1
            if client.invalid == 1:  # one line per connection; the count when it ends
                log.warning("Foxglove: %s: %s", client.ws.remote_address, problems[0].message)

    def _subscribe(self, client: _Client, subs: tuple[tuple[int, int], ...]) -> list[P.Invalid]:
        problems = []
        for sub_id, channel_id in subs:
            ch = self._channel_ids.get(channel_id)
            if ch is None:
                problems.append(P.Invalid(P.ERROR, f"Unknown channel ID: {channel_id}"))
            elif sub_id in client.subs:
                problems.append(P.Invalid(P.ERROR, f"Subscription ID {sub_id} is in use"))
            elif channel_id in client.by_channel:
                problems.append(P.Invalid(P.WARNING, f"Client is already subscribed to channel: "
                                          f"{channel_id}; ignoring subscription"))  # fmt: skip
            else:
                client.subs[sub_id] = channel_id
                client.by_channel[channel_id] = sub_id
                kept = self._kept.get(ch.topic)
                if kept is not None:  # latched: to this new subscriber only
                    self.dropped += client.push_data(sub_id, kept[1], kept[0])
        return problems

    def _unsubscribe(self, client: _Client, ids: tuple[int, ...]) -> list[P.Invalid]:
        problems = []
        for sub_id in ids:
            channel_id = client.subs.pop(sub_id, None)
            if channel_id is None:
                problems.append(P.Invalid(P.WARNING, f"Unknown subscription ID: {sub_id}"))
            else:
                client.by_channel.pop(channel_id, None)
        return problems


def _bind_refusal(host: str, has_token: bool) -> str:
    """Why a non-loopback address is refused, with the options that change it."""
    where = f"Foxglove server: refusing to listen on {host or 'all interfaces'}"
    if not has_token:
        return (f"{where} without a token: other machines could read the robot. Give "
                "--serve-token-file FILE (`ucr token FILE`, mode 0600) or $UCR_FOXGLOVE_TOKEN, "
                "or bind 127.0.0.1.")  # fmt: skip
    return (f"{where} without TLS: the token would cross the network in clear. Give "
            "--tls-cert FILE --tls-key FILE (key mode 0600), add --insecure on a trusted "
            "network, or bind 127.0.0.1 and use an SSH tunnel.")  # fmt: skip


def _why(exc: BaseException | None) -> str:
    """An exception and its causes on one line."""
    parts = []
    while exc is not None and len(parts) < 4:
        text = str(exc).strip().splitlines()
        parts.append(text[0] if text else type(exc).__name__)
        exc = exc.__cause__
    return "; ".join(parts) or "invalid handshake"


class _HandshakeLog(logging.LoggerAdapter):
    """The ``websockets`` server's logger: a handshake it refuses itself (no upgrade, no common
    subprotocol, not HTTP) is logged as one line, as the guard's own refusals, not with a
    traceback; everything else goes to ``websockets.server`` unchanged."""

    def __init__(self, guard: FoxgloveGuard) -> None:
        super().__init__(logging.getLogger("websockets.server"), {})
        self.guard = guard

    def log(self, level: int, msg: object, *args: object, **kwargs: Any) -> None:
        if msg == "opening handshake failed" and kwargs.get("exc_info"):
            conn = (kwargs.get("extra") or {}).get("websocket")
            self.guard.refused += 1
            log.warning("Foxglove: refused %s: %s", getattr(conn, "remote_address", "?"),
                        _why(sys.exc_info()[1]))  # fmt: skip
            return
        super().log(level, msg, *args, **kwargs)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # keep the connection's own ``extra``
