"""The daemon's network API: JSON over WebSocket (``websockets`` asyncio server).

The server never touches the daemon directly: it talks to it through the bridge
(``host.api.bridge``), so the same code runs in the daemon's process (:class:`ApiServer`, a thread;
tests and embedding) or in a process of its own (:mod:`host.api.process`, what ``ucr daemon``
does, so that client load never competes with the control loop for the interpreter lock).

Bounded by design: connections still in their opening handshake (pending, from the TCP accept:
with TLS, their TLS handshake included) and accepted ones are capped apart
(``host.api.admission.Admission``): a full pending cap evicts the oldest pending connection that got
least far, so idle sockets cannot keep a client out, and only accepted
(authenticated) connections count against the total and the slots kept for control tokens;
what all connections hold of their clients' requests (frames read ahead, a frame being read, the
request being answered) is counted and capped in total (``inbound_bytes``: above it the connection
holding the most is closed), and frames are not compressed (permessage-deflate off: a 1 KiB
compressed frame used to become 1 MiB in the server); subscriptions per connection are capped;
each published message arrives encoded once and is fanned out by kind to the subscribers'
outboxes, bounded in messages and bytes (per client and in total); a client that stops reading is
closed; requests are paced by a budget weighted by their bytes and the work they cause, shared
fairly between tokens (``host.api.connection``). ``status`` is answered from the latest snapshot
the daemon sent (at most ``status_period`` old, refreshed after every state-changing op), without
a round trip.

Security: every handshake passes the browser guard (``host.api.guard``: Origin, Host, path), then
the bearer token check (``host.api.auth``): a valid token always gets in; wrong ones meet a
back-off per source and for all sources together. Tokens carry a scope (read or control); ops
that move the robot or switch controllers need control and are written to the ``ucr.audit``
logger. Off loopback, TLS (``wss``) and a token are required.

One piece: besides the lifecycle, the server owns the TCP caps, the cap on the request bytes
connections hold and the handshake; the first two live in one connection class, all three keep
their counts in the server, so they stay together here.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import socket
import ssl
import sys
import threading
import time
from dataclasses import dataclass, field
from http import HTTPStatus
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

from host.api import DEFAULT_HOST, DEFAULT_PORT
from host.api import schema as S
from host.api.admission import (
    AUTHORIZING,
    REFUSING,
    VERIFIED,
    Admission,
    admitted_connections,
    peer_ip,
)
from host.api.auth import (
    CONTROL,
    AuthConfigError,
    Backoff,
    Token,
    check_token_text,
    find_token,
    server_tls_context,
)
from host.api.auth import check_bind as _check_bind_policy
from host.api.bridge import DaemonBridge, DaemonLink
from host.api.connection import Connections, Outboxes
from host.api.dispatch import Dispatcher, goal_done
from host.api.guard import GuardConfigError, WebGuard, is_loopback
from host.api.session import _peer

__all__ = [
    "ApiServer",
    "ApiServerError",
    "ServerOptions",
    "check_bind",
    "goal_done",
    "is_loopback",
    "start_server",
]

log = logging.getLogger("ucr.api")


class _HandshakeLog(logging.LoggerAdapter):
    """The ``websockets`` server's logger: a failed opening handshake (a client that reset or
    sent no valid request) is counted (``failed_handshakes``) and summed up in one warning line
    at most every :data:`HANDSHAKE_LOG_S` seconds, never a traceback each: a client aborting
    handshakes in a loop cannot fill the journal. Everything else goes to
    ``websockets.server`` unchanged."""

    def __init__(self, server: ApiServer) -> None:
        super().__init__(logging.getLogger("websockets.server"), {})
        self.server = server
        self._said_at = -math.inf
        self._unsaid = 0

    def log(self, level: int, msg: object, *args: object, **kwargs: Any) -> None:
        if msg == "opening handshake failed":
            self.server.counters["failed_handshakes"] += 1
            self._unsaid += 1
            now = time.monotonic()
            if now - self._said_at >= HANDSHAKE_LOG_S:
                exc = sys.exc_info()[1]
                log.warning("API: %d opening handshake(s) failed (the last: %s: %s)",
                            self._unsaid, type(exc).__name__ if exc else "?", exc)  # fmt: skip
                self._said_at, self._unsaid = now, 0
            return
        super().log(level, msg, *args, **kwargs)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # keep the connection's own ``extra``


HANDSHAKE_LOG_S = 10.0


class ApiServerError(RuntimeError):
    """The API server cannot start (bad bind address, missing token, port in use)."""


def check_bind(
    host: str | None,
    token: str | None = None,
    *,
    tls: bool = False,
    insecure: bool = False,
    tokens: list[Token] | tuple[Token, ...] = (),
) -> tuple[Token, ...]:
    """Validate the token(s) and the bind policy; returns the accepted tokens.

    Off loopback a token and TLS are required (``insecure`` waives TLS only). A token needs at
    least 16 printable characters without spaces. Raises :class:`ApiServerError`.
    """
    out = list(tokens)
    try:
        if token is not None:
            out.append(Token(check_token_text(token, "api.token"), CONTROL, "api.token"))
        _check_bind_policy(host, out, tls=tls, insecure=insecure)
    except AuthConfigError as exc:
        raise ApiServerError(str(exc)) from None
    return tuple(out)


@dataclass
class ServerOptions:
    """Limits and policies of one API server (defaults documented in docs/api.md)."""

    max_request_bytes: int = S.MAX_REQUEST_BYTES
    hard_frame_bytes: int = 1024 * 1024  # a frame above this closes the connection (1009)
    outbox_size: int = 256  # stream messages queued per client
    outbox_bytes: int = 4 * 1024 * 1024  # bytes queued per client
    global_outbox_bytes: int = 64 * 1024 * 1024  # bytes queued for all clients together
    max_connections: int = 256  # connections whose handshake was accepted (authenticated)
    #: the last of those slots admit only control tokens (with tokens configured): viewers
    #: with a read token cannot take every slot and keep the operator out
    control_reserve: int = 16
    #: TCP connections still in their opening handshake; when full, a new one evicts the
    #: oldest that got least far (host.api.admission.Admission)
    max_pending: int = 64
    max_per_peer: int = 32  # per remote address (loopback peers count only in the totals)
    max_subscriptions: int = 16  # per connection
    max_queue: int = 2  # frames read ahead per connection
    inbound_bytes: int = 16 * 1024 * 1024  # request bytes all connections may hold (see _Capped)
    max_request_rate: float = 500.0  # budget units/s per connection (1 per request + 1 per KiB)
    global_request_rate: float = 4000.0  # budget units/s for all, shared fairly between tokens
    slow_close_s: float = 5.0  # a client whose outbox did not move for this long is closed
    open_timeout_s: float = 5.0  # the TLS handshake, then the opening handshake: each at most
    auth_hold_s: float = 1.0  # during an auth back-off, each attempt waits this before its check
    status_period: float = 0.05  # s between status snapshots from the daemon
    goal_poll_s: float = 0.05  # s between goal status polls for trajectory pushes
    upload_points_total: int = 4 * S.MAX_POINTS  # pending chunked-upload points, all clients
    #: resident-size growth (bytes) after which a quiet second returns memory to the OS (0: off;
    #: the API's own process sets host.api.memory.RELEASE_AFTER_GROWTH: in the daemon's process
    #: the release's full collection would hold up the control loop)
    release_after_growth: int = 0
    origins: tuple[str, ...] = ()
    names: tuple[str, ...] = ()
    path: str = "/"
    tls_cert: str | None = None
    tls_key: str | None = None
    insecure: bool = False
    tokens: tuple[Token, ...] = field(default_factory=tuple)


class ApiServer:
    """WebSocket API in front of a ``Daemon`` facade; ``start()`` runs it in a background thread.

    Composes three parts (each gets what it needs at construction): ``outboxes`` (fan-out,
    :class:`host.api.connection.Outboxes`), ``requests`` (:class:`host.api.dispatch.Dispatcher`)
    and ``connections`` (:class:`host.api.connection.Connections`); the server itself owns the
    lifecycle, the TCP caps, the handshake and the link to the daemon.

    ``daemon`` is the facade (the server reaches it through an in-process bridge) or, in the
    API's own process, a connected :class:`host.api.bridge.DaemonLink`. ``port=0`` picks a free
    port (see :attr:`port`). Keyword options: the fields of :class:`ServerOptions`.
    """

    def __init__(
        self,
        daemon: Any,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        token: str | None = None,
        **options: Any,
    ) -> None:
        opts = ServerOptions(**options)
        tls = bool(opts.tls_cert or opts.tls_key)
        if tls and not (opts.tls_cert and opts.tls_key):
            raise ApiServerError("TLS needs both api.tls.cert and api.tls.key")
        opts.tokens = check_bind(
            host, token, tls=tls, insecure=opts.insecure, tokens=tuple(opts.tokens)
        )
        self.opts = opts
        try:
            self.guard = WebGuard.build(
                bind=host, origins=opts.origins, names=opts.names, path=opts.path
            )
        except GuardConfigError as exc:
            raise ApiServerError(str(exc)) from None
        self._ssl = self._ssl_context() if tls else None
        self.daemon = daemon
        self.host = host
        self.requested_port = port
        self.port: int | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._admission = Admission(
            opts.max_connections, opts.max_pending, opts.max_per_peer, opts.control_reserve
        )
        self._tcp = self._admission.tcp
        self._conns: set[Any] = set()  # open TCP connections (the _Capped class below)
        self.inbound = 0  # request bytes the connections hold (frames read, being read, answered)
        self.inbound_peak = 0
        self._backoff = Backoff()
        self._link: DaemonLink | None = None
        self._bridge: DaemonBridge | None = None
        self.counters = {
            "connections": 0,
            "requests": 0,
            "errors": 0,
            "auth_failures": 0,
            "refused_connections": 0,
            "evicted_pending": 0,
            "failed_handshakes": 0,
            "refused_handshakes": 0,
            "dropped": 0,
            "slow_closed": 0,
            "forbidden": 0,
            "throttled": 0,
            "rate_limited": 0,
            "auth_backoff": 0,
            "inbound_closed": 0,
            "memory_releases": 0,
        }
        self.outboxes = Outboxes(opts, self.counters, self._want_stream)
        self.requests = Dispatcher(
            opts,
            self.counters,
            self.outboxes,
            self._call,
            self._status_text,
            lambda: self.connections.sessions,
        )
        self.connections = Connections(
            opts, self.counters, self.outboxes, self.requests, self._call, lambda: self._tcp.total
        )

    def _ssl_context(self) -> ssl.SSLContext:
        try:
            return server_tls_context(str(self.opts.tls_cert), str(self.opts.tls_key))
        except AuthConfigError as exc:
            raise ApiServerError(str(exc)) from None

    # ------------------------------------------------------------------ lifecycle
    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        if host in ("", "0.0.0.0"):  # noqa: S104 - only naming the URL
            host = "127.0.0.1"
        scheme = "wss" if self._ssl is not None else "ws"
        return f"{scheme}://{host}:{self.port}"

    def start(self, timeout: float = 5.0) -> ApiServer:
        """Bind and serve in a background thread; :class:`ApiServerError` if binding fails."""
        if self._thread is not None:
            raise ApiServerError("API server already started")
        if isinstance(self.daemon, DaemonLink):
            self._link = self.daemon
        else:  # in-process: the same bridge as a separate process, over a socket pair
            a, b = socket.socketpair()
            self._bridge = DaemonBridge(
                self.daemon, a, status_period=self.opts.status_period
            ).start()
            self._link = DaemonLink(b)
        self._thread = threading.Thread(target=self._run, name="ucr-api", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise ApiServerError("API server did not start in time")
        if self._start_error is not None:
            self._thread.join(1.0)
            self._close_bridge()
            err = self._start_error
            raise ApiServerError(f"cannot listen on {self.host}:{self.requested_port}: {err}")
        log.info("API listening on %s%s", self.url, " (token required)" if self.opts.tokens else "")
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Close all connections (their streams end, subscriptions are released) and the thread."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(timeout)
        self._close_bridge()

    def _close_bridge(self) -> None:
        if self._bridge is not None:
            self._link.close()
            self._bridge.stop()
            self._bridge = None

    def call_in_loop(self, fn: Any, *args: Any) -> None:
        """Run ``fn(*args)`` in the server's event loop (from any thread)."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(fn, *args)

    def __enter__(self) -> ApiServer:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> dict:
        """Counters for diagnostics: connections, requests, errors, clients, drops, throttling."""
        sessions = list(self.connections.sessions)
        return {
            **self.counters,
            "clients": len(sessions),
            "tcp_connections": self._tcp.total,
            "pending_connections": self._admission.pending,
            "subscriptions": sum(len(s.subs) for s in sessions),
            "queued_bytes": self.outboxes.queued_bytes,
            "inbound_bytes": self.inbound,
            "inbound_peak": self.inbound_peak,
            "upload_points": self.requests.upload_points,
        }

    # ------------------------------------------------------------------ the daemon side
    async def _call(self, name: str, *args: Any) -> Any:
        """Call ``name`` on the daemon (through the bridge)."""
        return await self._link.call(name, *args)

    def _status_text(self) -> str | None:
        """The latest status snapshot the daemon sent (JSON text), None before the first, with
        ``status_age_s``: how long ago it came (the daemon sends one every 50 ms; a daemon
        whose process is frozen or whose lock is held sends none, and its last one ages)."""
        text = self._link.status_text
        if text is None or not text.startswith("{") or text.startswith('{"__error__"'):
            return text
        age = max(time.monotonic() - self._link.status_t, 0.0)
        return f'{{"status_age_s":{age:.3f}' + ("," + text[1:] if text != "{}" else "}")

    def _want_stream(self, kinds: dict[str, tuple[float, ...] | None]) -> None:
        self._link.want_stream(kinds)

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported through start()
            if not self._ready.is_set():
                self._start_error = exc
                self._ready.set()
            else:
                log.exception("API server stopped with an error")

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        server: Server
        conn_class = self._connection_class()
        async with serve(
            self.connections.handle,
            self.host,
            self.requested_port,
            process_request=self._authorize,
            create_connection=conn_class,
            max_size=self.opts.hard_frame_bytes,
            max_queue=self.opts.max_queue,
            # No permessage-deflate: inbound, a 1 KiB frame inflated to 1 MiB in the server
            # (every frame of a read inflated at once, before any cap could look); outbound, it
            # cost each subscriber a compression of every message (docs/api.md, "Limits").
            compression=None,
            open_timeout=self.opts.open_timeout_s,
            ping_interval=20,
            ping_timeout=20,
            server_header="ucr-api",
            logger=_HandshakeLog(self),
            # TLS is not given here: the connection class upgrades each connection after its
            # TCP accept has been admitted (host.api.admission.admitted_connections)
        ) as server:
            # once bound: a failed start leaves the link alone
            await self._link.start(self.outboxes.publish)
            sock = next(iter(server.sockets))
            self.port = sock.getsockname()[1]
            self.guard = self.guard.with_port(self.port)
            self._ready.set()
            tasks = [
                asyncio.create_task(self.requests.goal_pump()),
                asyncio.create_task(self.connections.janitor()),
            ]
            stop_wait = asyncio.create_task(self._stop.wait())
            await asyncio.wait(
                [stop_wait, asyncio.create_task(self._link_gone())],
                return_when=asyncio.FIRST_COMPLETED,
            )
            for t in tasks:
                t.cancel()
            conn_class.ucr_abort_tls()
            server.close(close_connections=True)
            await server.wait_closed()

    async def _link_gone(self) -> None:
        """In the API's own process: when the daemon side closes, the server ends too."""
        while not self._link.closed:
            await asyncio.sleep(0.2)
        if self._bridge is None:
            # the daemon's ordered stop closes the bridge first (its own log says why it
            # stopped, also when it died): not a warning of the API's
            log.info("API: the daemon closed the bridge; stopping")
        else:
            await self._stop.wait()

    # ------------------------------------------------------------------ connection caps
    def _connection_class(self) -> type[ServerConnection]:
        """ServerConnection that is admitted (:class:`host.api.admission.Admission`: per-peer cap,
        pending cap with eviction) at its TCP accept, before any work (with TLS: before its TLS
        handshake), and counts the request bytes it holds into :attr:`inbound` (see
        :meth:`_account`)."""
        srv = self

        def refused(_ip: str) -> None:
            srv.counters["refused_connections"] += 1

        def evicted() -> None:
            srv.counters["evicted_pending"] += 1

        admitted = admitted_connections(
            ServerConnection, srv._admission, refused, evicted,
            tls=srv._ssl, tls_timeout=srv.opts.open_timeout_s,
        )  # fmt: skip

        class _Capped(admitted):  # type: ignore[misc, valid-type]
            ucr_held = 0  # request bytes this connection holds, as counted in srv.inbound
            ucr_handling = 0  # length of the request its handler is answering
            ucr_shed = False  # closed for holding the most when all held too much

            def ucr_admitted(self) -> None:
                srv._conns.add(self)

            def ucr_gone(self) -> None:
                srv._conns.discard(self)
                srv.inbound -= self.ucr_held
                self.ucr_held = 0

            def data_received(self, data: bytes) -> None:
                super().data_received(data)
                srv._account(self)

            def ucr_account(self) -> None:
                """Count again what this connection holds (its handler took or answered one)."""
                srv._account(self)

            def ucr_holds(self) -> int:
                """Request bytes held now: the bytes read and not yet parsed into frames (a
                frame being read), the frames read ahead, the fragments of a message being
                assembled and the request the handler is answering."""
                if self.ucr_ip is None:
                    return 0
                protocol = self.protocol
                held = len(protocol.reader.buffer) + (protocol.current_size or 0)
                held += sum(len(f.data) for f in self.recv_messages.frames.queue)
                return held + self.ucr_handling

            def ucr_close_for_input(self) -> None:
                """Close this connection now (1013) and drop what it holds."""
                srv.counters["inbound_closed"] += 1
                self.ucr_shed = True
                log.warning(
                    "API: closing %s: it holds %d request bytes and all connections together "
                    "hold more than %d",
                    _peer(self),
                    self.ucr_held,
                    srv.opts.inbound_bytes,
                )
                with contextlib.suppress(Exception):
                    self.protocol.fail(CloseCode.TRY_AGAIN_LATER, "server busy: too much input")
                    self.send_data()
                self.transport.abort()
                # Free what it holds now: the bytes read, and the frames read ahead but the one
                # a pending read was already promised (its handler stops at it: ucr_shed).
                self.protocol.reader.buffer.clear()
                frames = self.recv_messages.frames
                keep = 1 if frames.get_waiter is not None and frames.get_waiter.done() else 0
                while len(frames.queue) > keep:
                    frames.queue.pop()
                srv.inbound -= self.ucr_held
                self.ucr_held = 0

        return _Capped

    def _account(self, conn: Any) -> None:
        """Update :attr:`inbound` with what ``conn`` holds now; above ``inbound_bytes`` close
        the connections holding the most until the total is back under it. A client sending
        requests of at most 64 KiB one at a time holds at most one: 256 of them together stay
        under the default cap (16 MiB), so only clients sending more than that are closed."""
        held = conn.ucr_holds() if conn in self._conns else 0
        self.inbound += held - conn.ucr_held
        conn.ucr_held = held
        if self.inbound > self.inbound_peak:
            self.inbound_peak = self.inbound
        while self.inbound > self.opts.inbound_bytes:
            victim = max(self._conns, key=lambda c: c.ucr_held, default=None)
            if victim is None or victim.ucr_held <= 0:
                break
            self._conns.discard(victim)
            victim.ucr_close_for_input()

    # ------------------------------------------------------------------ handshake
    async def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        """Guard (Origin, Host, path), then the token. A valid token always gets in; the
        back-off (per source and for all sources together, :class:`host.api.auth.Backoff`)
        meets only wrong ones. While it is on, every attempt it concerns first waits
        ``auth_hold_s`` (the valid ones too, so an early answer does not tell a guesser it was
        wrong): guessing runs at most one guess per connection and hold. An accepted handshake
        is counted open (:meth:`_open`), which may still refuse it for lack of room."""
        self._admission.advance(conn, AUTHORIZING)
        refusal = self.guard.check(request.path, request.headers)
        if refusal is not None:
            self.counters["refused_handshakes"] += 1
            log.warning("API: refused %s: %s", _peer(conn), refusal.reason)
            return conn.respond(HTTPStatus(refusal.status), refusal.reason + "\n")
        if not self.opts.tokens:
            conn.ucr_token = None
            return self._open(conn, None)
        ip = peer_ip(conn.remote_address)
        token = find_token(self.opts.tokens, request.headers.get("Authorization", ""))
        # while it waits out the hold: a valid one is evicted last, a wrong one first
        self._admission.advance(conn, REFUSING if token is None else VERIFIED)
        if self._backoff.blocked_for(ip) > 0 and self.opts.auth_hold_s > 0:
            self.counters["auth_backoff"] += 1
            await asyncio.sleep(self.opts.auth_hold_s)
        if token is not None:
            conn.ucr_token = token
            return self._open(conn, token)
        self.counters["auth_failures"] += 1
        wait = self._backoff.blocked_for(ip)
        if wait > 0:  # refused without counting again: the back-off grows once it has passed
            response = conn.respond(
                HTTPStatus.TOO_MANY_REQUESTS,
                f"missing or wrong API token; too many failed attempts: retry in {wait:.0f} s\n",
            )
            response.headers["Retry-After"] = str(math.ceil(wait))
            return response
        backoff = self._backoff.failed(ip)
        log.warning(
            "API: refused %s: missing or wrong token%s",
            _peer(conn),
            f" (back-off {backoff:.0f} s)" if backoff else "",
        )
        return conn.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong API token\n")

    def _open(self, conn: ServerConnection, token: Token | None) -> Response | None:
        """Count an accepted handshake open (None), or the 503 to answer when there is no room:
        all ``max_connections`` taken, or for a read token the first ``max_connections -
        control_reserve`` (without tokens every client has control: no reserve)."""
        control = token is None or token.scope == CONTROL
        if self._admission.promote(conn, control):
            return None
        if not self._admission.is_pending(conn):  # evicted while its check waited: gone
            return conn.respond(HTTPStatus.SERVICE_UNAVAILABLE, "evicted\n")
        self.counters["refused_connections"] += 1
        if control:
            reason = "too many connections"
        else:
            reason = "too many connections: the remaining ones are kept for control tokens"
        log.warning(
            "API: refused %s%s: %s", _peer(conn), f" ({token.label})" if token else "", reason
        )
        response = conn.respond(HTTPStatus.SERVICE_UNAVAILABLE, reason + "\n")
        response.headers["Retry-After"] = "5"
        return response


def start_server(
    daemon: Any,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    token: str | None = None,
    **kwargs: Any,
) -> ApiServer:
    """Create and start an in-process :class:`ApiServer` (tests, embedding)."""
    return ApiServer(daemon, host, port, token, **kwargs).start()
