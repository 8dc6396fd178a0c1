"""The daemon's network API: JSON over WebSocket (``websockets`` asyncio server).

The server never touches the daemon directly: it talks to it through the bridge
(``host.api.bridge``), so the same code runs in the daemon's process (:class:`ApiServer`, a thread;
tests and embedding) or in a process of its own (:mod:`host.api.process`, what ``ucr daemon``
does, so that client load never competes with the control loop for the interpreter lock).

Bounded by design: connections are capped (total and per peer) before any handshake work;
subscriptions per connection are capped; each published message arrives encoded once and is fanned
out by kind to the subscribers' outboxes, bounded in messages and bytes (per client and in total);
a client that stops reading is closed; requests are paced by a budget weighted by their bytes and
the work they cause. ``status`` is answered from the latest snapshot the daemon sent (at most
``status_period`` old, refreshed after every state-changing op), without a round trip.

Security: every handshake passes the browser guard (``host.api.guard``: Origin, Host, path), then
the bearer token check with per-peer back-off (``host.api.auth``). Tokens carry a scope (read or
control); ops that move the robot or switch controllers need control and are written to the
``ucr.audit`` logger. Off loopback, TLS (``wss``) and a token are required.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import gc
import ipaddress
import json
import logging
import math
import socket
import ssl
import threading
import time
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from host.api import DEFAULT_HOST, DEFAULT_PORT
from host.api import schema as S
from host.api.audit import audit_log
from host.api.auth import (
    CONTROL,
    READ_OPS,
    AuthConfigError,
    Backoff,
    Token,
    check_private,
    check_token_text,
    find_token,
)
from host.api.auth import check_bind as _check_bind_policy
from host.api.bridge import BridgeClosed, DaemonBridge, DaemonLink, RemoteError
from host.api.guard import GuardConfigError, WebGuard, is_loopback

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

_TERMINAL_STATES = frozenset(
    {
        "succeeded",
        "success",
        "aborted",
        "canceled",
        "cancelled",
        "failed",
        "rejected",
        "done",
        "preempted",
        "replaced",
    }
)
# Extra budget units per op, on top of 1 per request and 1 per KiB: what it costs the daemon.
_OP_WORK = {
    "topology": 4,
    "loop_stats": 4,
    "controllers.list": 4,
    "trajectory.status": 2,
    "trajectory.cancel": 4,
    "controllers.switch": 20,
    "controllers.hand_back": 20,
    "trajectory.send": 20,
    "ffc.input": 1,
}
_CONTROL_OPS_AUDITED = (
    "controllers.switch",
    "controllers.hand_back",
    "trajectory.send",
    "trajectory.cancel",
)


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


def goal_done(status: Any) -> bool:
    """Whether a ``trajectory_status`` result describes a finished goal."""
    if not isinstance(status, dict):
        return False
    if status.get("done") is True or status.get("finished") is True:
        return True
    for key in ("state", "status", "result"):
        value = status.get(key)
        if isinstance(value, str) and value.lower() in _TERMINAL_STATES:
            return True
    return False


@dataclass
class ServerOptions:
    """Limits and policies of one API server (defaults documented in docs/api.md)."""

    max_request_bytes: int = S.MAX_REQUEST_BYTES
    hard_frame_bytes: int = 1024 * 1024  # a frame above this closes the connection (1009)
    outbox_size: int = 256  # stream messages queued per client
    outbox_bytes: int = 4 * 1024 * 1024  # bytes queued per client
    global_outbox_bytes: int = 64 * 1024 * 1024  # bytes queued for all clients together
    max_connections: int = 256  # TCP connections, handshaking or open
    max_per_peer: int = 32  # per remote address (loopback peers count only in the total)
    max_subscriptions: int = 16  # per connection
    max_request_rate: float = 500.0  # budget units/s per connection (1 per request + 1 per KiB)
    global_request_rate: float = 4000.0  # budget units/s for all connections together
    slow_close_s: float = 5.0  # a client whose outbox did not move for this long is closed
    open_timeout_s: float = 5.0  # opening handshake (TLS included)
    status_period: float = 0.05  # s between status snapshots from the daemon
    goal_poll_s: float = 0.05  # s between goal status polls for trajectory pushes
    upload_points_total: int = 4 * S.MAX_POINTS  # pending chunked-upload points, all clients
    origins: tuple[str, ...] = ()
    names: tuple[str, ...] = ()
    path: str = "/"
    tls_cert: str | None = None
    tls_key: str | None = None
    insecure: bool = False
    tokens: tuple[Token, ...] = field(default_factory=tuple)


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

    def admit(self, kind: str, now: float) -> bool:
        if self.min_period <= 0.0 or kind not in S.RATE_LIMITED_KINDS:
            return True
        last = self.last_sent.get(kind)
        # A little slack so a 100 Hz source thinned to 50 Hz does not alias down to 33 Hz.
        if last is not None and now - last < self.min_period * 0.9:
            self.thinned += 1
            return False
        self.last_sent[kind] = now
        return True


class _Upload:
    """A trajectory being uploaded in chunks (``trajectory.upload``)."""

    def __init__(self, uid: int) -> None:
        self.uid = uid
        self.points: list[dict] = []
        self.last_t = 0.0
        self.t_touched = time.monotonic()


class _Session:
    """State of one connected client."""

    def __init__(self, ws: ServerConnection, token: Token | None, anonymous_scope: str) -> None:
        self.ws = ws
        self.peer = _peer(ws)
        self.scope = token.scope if token is not None else anonymous_scope
        self.who = token.label if token is not None else "anonymous"
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
        self.throttled = 0
        self.t_progress = time.monotonic()  # last time the sender got a message out
        self.upload: _Upload | None = None


def _peer(ws: Any) -> str:
    try:
        addr = ws.remote_address
        return f"{addr[0]}:{addr[1]}"
    except Exception:  # noqa: BLE001 - purely cosmetic
        return "?"


def _peer_ip(addr: Any) -> str:
    try:
        return str(addr[0])
    except Exception:  # noqa: BLE001 - unknown transports share one bucket
        return "?"


def _is_loopback_ip(ip: str) -> bool:
    try:
        return ipaddress.ip_address(ip).is_loopback
    except ValueError:
        return False


class ApiServer:
    """WebSocket API in front of a ``Daemon`` facade; ``start()`` runs it in a background thread.

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
        self.max_request_bytes = opts.max_request_bytes
        self.max_request_rate = opts.max_request_rate
        self.request_burst = max(1.0, opts.max_request_rate / 5)
        self._global_tokens = opts.global_request_rate / 5
        self._global_refill = time.monotonic()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._sessions: set[_Session] = set()
        self._by_kind: dict[str, dict[_Subscription, _Session]] = {k: {} for k in S.KINDS}
        self._next_sub = 1
        self._next_upload = 1
        self._upload_points = 0
        self._tcp_total = 0
        self._tcp_by_ip: dict[str, int] = {}
        self._queued_bytes = 0
        self._backoff = Backoff()
        self._link: DaemonLink | None = None
        self._bridge: DaemonBridge | None = None
        self.counters = {
            "connections": 0,
            "requests": 0,
            "errors": 0,
            "auth_failures": 0,
            "refused_connections": 0,
            "refused_handshakes": 0,
            "dropped": 0,
            "slow_closed": 0,
            "forbidden": 0,
            "throttled": 0,
        }

    def _ssl_context(self) -> ssl.SSLContext:
        cert, key = Path(str(self.opts.tls_cert)), Path(str(self.opts.tls_key))
        try:
            check_private(key, "the TLS key")
            ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            ctx.minimum_version = ssl.TLSVersion.TLSv1_2
            ctx.load_cert_chain(cert, key)
        except AuthConfigError as exc:
            raise ApiServerError(str(exc)) from None
        except (OSError, ssl.SSLError) as exc:
            raise ApiServerError(f"TLS: cannot load {cert} / {key}: {exc}") from None
        return ctx

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
        sessions = list(self._sessions)
        return {
            **self.counters,
            "clients": len(sessions),
            "tcp_connections": self._tcp_total,
            "subscriptions": sum(len(s.subs) for s in sessions),
            "queued_bytes": self._queued_bytes,
            "upload_points": self._upload_points,
        }

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
        async with serve(
            self._handle,
            self.host,
            self.requested_port,
            process_request=self._authorize,
            create_connection=self._connection_class(),
            max_size=self.opts.hard_frame_bytes,
            max_queue=2,
            open_timeout=self.opts.open_timeout_s,
            ping_interval=20,
            ping_timeout=20,
            server_header="ucr-api",
            ssl=self._ssl,
        ) as server:
            await self._link.start(self._publish)  # once bound: a failed start leaves it alone
            sock = next(iter(server.sockets))
            self.port = sock.getsockname()[1]
            self.guard = self.guard.with_port(self.port)
            self._ready.set()
            tasks = [asyncio.create_task(self._goal_pump()), asyncio.create_task(self._janitor())]
            stop_wait = asyncio.create_task(self._stop.wait())
            await asyncio.wait(
                [stop_wait, asyncio.create_task(self._link_gone())],
                return_when=asyncio.FIRST_COMPLETED,
            )
            for t in tasks:
                t.cancel()
            server.close(close_connections=True)
            await server.wait_closed()

    async def _link_gone(self) -> None:
        """In the API's own process: when the daemon side closes, the server ends too."""
        while not self._link.closed:
            await asyncio.sleep(0.2)
        if self._bridge is None:
            log.warning("API: the daemon side closed; stopping")
        else:
            await self._stop.wait()

    # ------------------------------------------------------------------ connection caps
    def _connection_class(self) -> type[ServerConnection]:
        """ServerConnection that refuses TCP connections above the caps before any work."""
        srv = self

        class _Capped(ServerConnection):
            _ucr_ip: str | None = None

            def connection_made(self, transport: asyncio.BaseTransport) -> None:
                ip = _peer_ip(transport.get_extra_info("peername"))
                per_peer = srv._tcp_by_ip.get(ip, 0)
                over_peer = per_peer >= srv.opts.max_per_peer and not _is_loopback_ip(ip)
                if srv._tcp_total >= srv.opts.max_connections or over_peer:
                    srv.counters["refused_connections"] += 1
                    transport.abort()
                    return
                self._ucr_ip = ip
                srv._tcp_total += 1
                srv._tcp_by_ip[ip] = per_peer + 1
                super().connection_made(transport)

            def connection_lost(self, exc: Exception | None) -> None:
                ip = self._ucr_ip
                if ip is None:
                    return  # refused in connection_made: nothing was set up
                self._ucr_ip = None
                srv._tcp_total -= 1
                left = srv._tcp_by_ip.get(ip, 1) - 1
                if left > 0:
                    srv._tcp_by_ip[ip] = left
                else:
                    srv._tcp_by_ip.pop(ip, None)
                super().connection_lost(exc)

        return _Capped

    # ------------------------------------------------------------------ handshake
    def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        refusal = self.guard.check(request.path, request.headers)
        if refusal is not None:
            self.counters["refused_handshakes"] += 1
            log.warning("API: refused %s: %s", _peer(conn), refusal.reason)
            return conn.respond(HTTPStatus(refusal.status), refusal.reason + "\n")
        if not self.opts.tokens:
            conn.ucr_token = None
            return None
        ip = _peer_ip(conn.remote_address)
        wait = self._backoff.blocked_for(ip)
        if wait > 0:
            self.counters["auth_failures"] += 1
            response = conn.respond(
                HTTPStatus.TOO_MANY_REQUESTS, f"too many failed attempts: retry in {wait:.0f} s\n"
            )
            response.headers["Retry-After"] = str(math.ceil(wait))
            return response
        token = find_token(self.opts.tokens, request.headers.get("Authorization", ""))
        if token is None:
            self.counters["auth_failures"] += 1
            backoff = self._backoff.failed(ip)
            log.warning(
                "API: refused %s: missing or wrong token%s",
                _peer(conn),
                f" (back-off {backoff:.0f} s)" if backoff else "",
            )
            return conn.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong API token\n")
        self._backoff.succeeded(ip)
        conn.ucr_token = token
        return None

    # ------------------------------------------------------------------ connection
    async def _handle(self, ws: ServerConnection) -> None:
        token = getattr(ws, "ucr_token", None)
        session = _Session(ws, token, CONTROL)
        session.tokens = self.request_burst
        self._sessions.add(session)
        self.counters["connections"] += 1
        log.info("API: client %s connected (%s, %s)", session.peer, session.who, session.scope)
        sender = asyncio.create_task(self._sender(session))
        try:
            async for frame in ws:
                await self._throttle(session, frame)
                reply = await self._serve_frame(session, frame)
                text = reply if isinstance(reply, str) else self._encode_reply(reply)
                await ws.send(text)
        except ConnectionClosed:
            pass
        finally:
            session.closed = True
            session.wakeup.set()
            sender.cancel()
            self._sessions.discard(session)
            self._drop_outbox(session)
            await self._cleanup(session)
            log.info("API: client %s gone", session.peer)

    @staticmethod
    def _encode_reply(reply: dict) -> str:
        try:
            return S.encode(reply)
        except (TypeError, ValueError) as exc:  # a result JSON cannot carry
            log.error("API: cannot encode the reply to %s: %s", reply.get("id"), exc)
            return S.encode(
                S.error_reply(
                    reply.get("id"), S.INTERNAL, f"internal error: result not encodable ({exc})"
                )
            )

    async def _throttle(self, session: _Session, frame: str | bytes) -> None:
        """Pace a client by a budget weighted by bytes and by work: reading its next request
        later (TCP back-pressure) instead of refusing it, so one client cannot load the daemon.
        A second, global budget bounds all clients together."""
        cost = 1.0 + len(frame) / 1024.0
        if isinstance(frame, str) and len(frame) < 4096:
            op_at = frame.find('"op"')
            if op_at >= 0:
                for op, work in _OP_WORK.items():
                    if f'"{op}"' in frame[op_at : op_at + 40]:
                        cost += work
                        break
        now = time.monotonic()
        rate = self.max_request_rate
        session.tokens = min(self.request_burst, session.tokens + (now - session.t_refill) * rate)
        session.t_refill = now
        grate = self.opts.global_request_rate
        self._global_tokens = min(
            grate / 5, self._global_tokens + (now - self._global_refill) * grate
        )
        self._global_refill = now
        wait = max(
            (cost - session.tokens) / rate if session.tokens < cost else 0.0,
            (cost - self._global_tokens) / grate if self._global_tokens < cost else 0.0,
        )
        if wait > 0:
            session.throttled += 1
            self.counters["throttled"] += 1
            await asyncio.sleep(min(wait, 10.0))
            now = time.monotonic()
            session.tokens = min(
                self.request_burst, session.tokens + (now - session.t_refill) * rate
            )
            session.t_refill = now
        session.tokens -= cost
        self._global_tokens -= cost

    async def _sender(self, session: _Session) -> None:
        """Send pushes in order: trajectory progress first, then stream messages."""
        ws = session.ws
        try:
            while not session.closed:
                await session.wakeup.wait()
                session.wakeup.clear()
                while session.priority or session.stream:
                    if session.priority:
                        text = session.priority.popleft()
                    else:
                        _, text = session.stream.popleft()
                    session.queued_bytes -= len(text)
                    self._queued_bytes -= len(text)
                    await ws.send(text)
                    session.t_progress = time.monotonic()
        except ConnectionClosed:
            pass

    def _drop_outbox(self, session: _Session) -> None:
        self._queued_bytes -= session.queued_bytes
        session.queued_bytes = 0
        session.stream.clear()
        session.priority.clear()
        for sub in session.subs.values():
            for kind in sub.kinds:
                self._by_kind[kind].pop(sub, None)
        self._update_stream_wanted()

    async def _cleanup(self, session: _Session) -> None:
        """Release what a departed client held: uploads, subscriptions and its cFFC stream."""
        self._end_upload(session)
        session.subs.clear()
        if session.ffc_active:
            # Stop its cFFC input at once rather than waiting for the daemon's deadman.
            zeros = {name: (0.0, 0.0) for name in session.ffc_active}
            audit_log(
                session.peer, session.who, session.scope, "ffc.input", None, "zeroed on disconnect"
            )
            try:
                await self._link.call("ffc_input", zeros)
            except Exception:  # noqa: BLE001 - e.g. a segment gone meanwhile: try one by one
                for name in sorted(session.ffc_active):
                    with contextlib.suppress(Exception):
                        await self._link.call("ffc_input", {name: (0.0, 0.0)})

    async def _janitor(self) -> None:
        """Once a second: close clients that stopped reading; forget stale uploads; give memory
        back to the OS once a crowd of connections has gone."""
        peak = 0
        while True:
            await asyncio.sleep(min(1.0, self.opts.slow_close_s / 2))
            now = time.monotonic()
            peak = max(peak, self._tcp_total)
            if peak >= 32 and self._tcp_total <= peak // 8:
                peak = self._tcp_total
                _release_memory()
            for session in list(self._sessions):
                stuck = session.stream or session.priority
                if stuck and now - session.t_progress > self.opts.slow_close_s:
                    self.counters["slow_closed"] += 1
                    log.warning("API: closing %s: it stopped reading", session.peer)
                    self._drop_outbox(session)
                    session.closed = True
                    session.ws.transport.abort()
                up = session.upload
                if up is not None and now - up.t_touched > 60.0:
                    self._end_upload(session)

    # ------------------------------------------------------------------ fan-out
    def _publish(self, kind: str, text: str) -> None:
        """One published message (JSON text, encoded once) to every subscriber of its kind."""
        subs = self._by_kind.get(kind)
        if not subs:
            return
        now = time.monotonic()
        for sub, session in list(subs.items()):
            if session.closed or not sub.admit(kind, now):
                continue
            push = f'{{"push":"stream","sub":{sub.sid},"dropped":{sub.dropped},"msg":{text}}}'
            self._push_stream(session, sub, push)

    def _push_stream(self, session: _Session, sub: _Subscription, push: str) -> None:
        size = len(push)
        opts = self.opts
        while session.stream and (
            len(session.stream) >= opts.outbox_size
            or session.queued_bytes + size > opts.outbox_bytes
            or self._queued_bytes + size > opts.global_outbox_bytes
        ):
            victim, old = session.stream.popleft()
            session.queued_bytes -= len(old)
            self._queued_bytes -= len(old)
            victim.dropped += 1
            self.counters["dropped"] += 1
        if self._queued_bytes + size > opts.global_outbox_bytes:
            sub.dropped += 1
            self.counters["dropped"] += 1
            return
        if not session.stream and not session.priority:
            session.t_progress = time.monotonic()  # idle until now: not a slow reader
        session.stream.append((sub, push))
        session.queued_bytes += size
        self._queued_bytes += size
        sub.sent += 1
        session.wakeup.set()

    def _push_priority(self, session: _Session, text: str) -> None:
        if not session.stream and not session.priority:
            session.t_progress = time.monotonic()
        session.priority.append(text)
        session.queued_bytes += len(text)
        self._queued_bytes += len(text)
        session.wakeup.set()

    def _update_stream_wanted(self) -> None:
        self._link.want_stream({kind for kind, subs in self._by_kind.items() if subs})

    # ------------------------------------------------------------------ requests
    async def _serve_frame(self, session: _Session, frame: str | bytes) -> dict | str:
        self.counters["requests"] += 1
        try:
            rid, op, params = S.parse_request(frame, self.max_request_bytes)
        except S.RequestError as exc:
            self.counters["errors"] += 1
            return S.error_reply(exc.request_id, exc.code, exc.message)
        if op not in READ_OPS and session.scope != CONTROL:
            self.counters["errors"] += 1
            self.counters["forbidden"] += 1
            return S.error_reply(
                rid, S.FORBIDDEN, f"{op!r} needs a token with the control scope (this one: read)"
            )
        try:
            result = await self._dispatch(session, op, params)
        except S.RequestError as exc:
            self.counters["errors"] += 1
            return S.error_reply(rid, exc.code, exc.message)
        except RemoteError as exc:
            self.counters["errors"] += 1
            return S.error_reply(rid, exc.code, str(exc))
        except Exception as exc:  # noqa: BLE001 - becomes an error reply, never kills the server
            self.counters["errors"] += 1
            log.exception("API: op %s failed", op)
            return S.error_reply(rid, S.INTERNAL, f"internal error ({type(exc).__name__}): {exc}")
        if isinstance(result, _Raw):
            return f'{{"id":{json.dumps(rid)},"ok":true,"result":{result.text}}}'
        return S.ok_reply(rid, result)

    def _audit(self, session: _Session, op: str, goal: Any, summary: str) -> None:
        audit_log(session.peer, session.who, session.scope, op, goal, summary)

    async def _dispatch(self, session: _Session, op: str, p: dict) -> Any:
        call = self._link.call
        if op == "ping":
            return {"pong": True, "t": time.time()}
        if op == "status":
            return self._status()
        if op == "topology":
            return await call("topology")
        if op == "loop_stats":
            return await call("loop_stats")
        if op == "controllers.list":
            return await call("controllers")
        if op == "controllers.switch":
            self._audit(session, op, None, f"start {p['start']} stop {p['stop']}")
            return await call("switch_controllers", p["start"], p["stop"])
        if op == "controllers.hand_back":
            self._audit(session, op, None, f"manual {p['manual']}")
            return await call("hand_back", p["manual"])
        if op == "faults.clear":
            self._audit(session, op, None, f"clear fault on {p['segment'] or 'every segment'}")
            return await call("clear_fault", p["segment"])
        if op == "trajectory.upload":
            return self._upload(session, p)
        if op == "trajectory.send":
            return await self._send_trajectory(session, p)
        if op == "trajectory.status":
            return await call("trajectory_status", p["goal"])
        if op == "trajectory.cancel":
            self._audit(session, op, p["goal"], "cancel")
            return await call("cancel_trajectory", p["goal"])
        if op == "ffc.input":
            return await self._ffc_input(session, p["rates"])
        if op == "subscribe":
            return self._subscribe(session, p["kinds"], p["max_rate"])
        if op == "unsubscribe":
            sub = session.subs.pop(p["sub"], None)
            if sub is None:
                raise S.RequestError(S.NOT_FOUND, f"no subscription {p['sub']} on this connection")
            for kind in sub.kinds:
                self._by_kind[kind].pop(sub, None)
            self._update_stream_wanted()
            return {
                "sub": sub.sid,
                "sent": sub.sent,
                "dropped": sub.dropped,
                "thinned": sub.thinned,
            }
        raise S.RequestError(S.UNKNOWN_OP, f"unknown op {op!r}")  # pragma: no cover - schema guards

    def _status(self) -> Any:
        text = self._link.status_text
        if text is None:
            raise S.RequestError(S.UNAVAILABLE, "no status from the daemon yet")
        if text.startswith('{"__error__"'):
            err = json.loads(text)["__error__"]
            raise S.RequestError(err["code"], err["message"])
        return _Raw(text)

    async def _ffc_input(self, session: _Session, rates: dict) -> Any:
        # Remember before calling: if the call fails half-way the input may still be set,
        # and a disconnect must then zero it.
        before = set(session.ffc_active)
        deflected = {n for n, (x, y) in rates.items() if x or y}
        if deflected != session.ffc_audited:  # a 50 Hz stream is audited when its sticks change
            session.ffc_audited = deflected
            self._audit(session, "ffc.input", None, f"deflected {sorted(deflected)}")
        session.ffc_active.update(deflected)
        try:
            result = await self._link.call("ffc_input", rates)
        except RemoteError as exc:
            if exc.code == S.REJECTED:
                session.ffc_active = before  # refused: the daemon did not take this input
            raise
        session.ffc_active.difference_update(n for n, (x, y) in rates.items() if not (x or y))
        if isinstance(result, dict) and result.get("takeover"):
            self._audit(session, "ffc.takeover", None, str(result.get("takeover")))
        return result

    async def _send_trajectory(self, session: _Session, p: dict) -> dict:
        points = p["points"] or []
        if p.get("upload") is not None:
            up = session.upload
            if up is None or up.uid != p["upload"]:
                raise S.RequestError(S.NOT_FOUND, f"no upload {p['upload']} on this connection")
            if points and points[0]["time_from_start"] <= up.last_t:
                raise S.RequestError(
                    S.INVALID_PARAMS, "points[0].time_from_start: must continue after the upload"
                )
            points = up.points + points
            self._end_upload(session)
            if len(points) > S.MAX_POINTS:
                raise S.RequestError(S.INVALID_PARAMS, f"at most {S.MAX_POINTS} waypoints")
        if not points:
            raise S.RequestError(S.INVALID_PARAMS, "points: needs at least one waypoint")
        goal = await self._link.call("send_trajectory", points, p["controller"])
        session.goals[goal] = None
        t_end = points[-1]["time_from_start"]
        self._audit(
            session,
            "trajectory.send",
            goal,
            f"{len(points)} waypoint(s) over {t_end:g} s, segments "
            f"{sorted({n for pt in points for n in pt['segments']})}, controller {p['controller']}",
        )
        return {"goal": goal}

    def _upload(self, session: _Session, p: dict) -> dict:
        up = session.upload
        if p.get("upload") is None:
            if up is not None:
                self._end_upload(session)  # a new upload replaces an unfinished one
            up = session.upload = _Upload(self._next_upload)
            self._next_upload += 1
        elif up is None or up.uid != p["upload"]:
            raise S.RequestError(S.NOT_FOUND, f"no upload {p['upload']} on this connection")
        pts = p["points"]
        if pts[0]["time_from_start"] <= up.last_t:
            raise S.RequestError(
                S.INVALID_PARAMS,
                f"points[0].time_from_start: times must increase strictly across chunks "
                f"({pts[0]['time_from_start']:g} s after {up.last_t:g} s)",
            )
        if len(up.points) + len(pts) > S.MAX_POINTS:
            raise S.RequestError(
                S.INVALID_PARAMS, f"an upload holds at most {S.MAX_POINTS} waypoints"
            )
        if self._upload_points + len(pts) > self.opts.upload_points_total:
            raise S.RequestError(S.UNAVAILABLE, "too many uploads in progress; try again later")
        up.points.extend(pts)
        up.last_t = pts[-1]["time_from_start"]
        up.t_touched = time.monotonic()
        self._upload_points += len(pts)
        return {"upload": up.uid, "points": len(up.points)}

    def _end_upload(self, session: _Session) -> None:
        up, session.upload = session.upload, None
        if up is not None:
            self._upload_points -= len(up.points)

    def _subscribe(self, session: _Session, kinds: list[str], max_rate: float | None) -> dict:
        if len(session.subs) >= self.opts.max_subscriptions:
            raise S.RequestError(
                S.REJECTED, f"at most {self.opts.max_subscriptions} subscriptions per connection"
            )
        sid = self._next_sub
        self._next_sub += 1
        sub = _Subscription(sid, kinds, max_rate)
        session.subs[sid] = sub
        for kind in kinds:
            self._by_kind[kind][sub] = session
        self._update_stream_wanted()
        return {"sub": sid, "kinds": kinds, "max_rate": max_rate}

    # ------------------------------------------------------------------ goal progress
    async def _goal_pump(self) -> None:
        """Push the status of every goal a client sent while it changes, until it ends."""
        while True:
            await asyncio.sleep(self.opts.goal_poll_s)
            for session in list(self._sessions):
                if session.goals and not session.closed:
                    try:
                        await self._poll_goals(session)
                    except Exception:  # noqa: BLE001 - the pump must outlive any one goal
                        log.exception("API: goal progress failed")

    async def _poll_goals(self, session: _Session) -> None:
        for goal, last in list(session.goals.items()):
            try:
                status = await self._link.call("trajectory_status", goal)
            except (RemoteError, BridgeClosed) as exc:
                session.goals.pop(goal, None)
                status = {"state": "unknown", "error": str(exc)}
                self._push_priority(
                    session,
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": True}),
                )
                continue
            done = goal_done(status)
            if _progress_key(status) != _progress_key(last) or done:
                self._push_priority(
                    session,
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": done}),
                )
                session.goals[goal] = status
            if done:
                session.goals.pop(goal, None)


def _release_memory() -> None:
    """Collect garbage and return free heap pages to the OS (glibc ``malloc_trim``), so the
    process shrinks back after a burst of connections instead of keeping its peak."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


class _Raw:
    """A result that is already JSON text (the status snapshot): spliced, not re-encoded."""

    __slots__ = ("text",)

    def __init__(self, text: str) -> None:
        self.text = text


def _progress_key(status: Any) -> Any:
    """What makes a status worth pushing again: everything but time stamps, progress rounded."""
    if not isinstance(status, dict):
        return status
    key = []
    for k, v in sorted(status.items()):
        if k in ("t", "time", "elapsed", "stamp"):
            continue
        if isinstance(v, float) and math.isfinite(v):
            v = round(v, 2)
        key.append((k, repr(v)))
    return tuple(key)


def start_server(
    daemon: Any,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    token: str | None = None,
    **kwargs: Any,
) -> ApiServer:
    """Create and start an in-process :class:`ApiServer` (tests, embedding)."""
    return ApiServer(daemon, host, port, token, **kwargs).start()
