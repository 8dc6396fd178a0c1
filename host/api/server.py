"""The daemon's network API: JSON over WebSocket (``websockets`` asyncio server) in its own thread.

The server runs its own event loop in a background thread beside the daemon's control loop and only
talks to the daemon through the thread-safe facade (``status()``, ``subscribe()``, ...). It never
blocks the loop: daemon calls run in a small worker pool, published messages are drained from the
daemon's queues by polling, and every client has a bounded outbox that drops the oldest stream
messages (counted) when the client reads too slowly. Malformed requests get an error reply; the
connection and everyone else carry on.

Security: listens on 127.0.0.1 by default. Any other address needs a token; clients present it in
the opening handshake as ``Authorization: Bearer <token>`` (checked with ``hmac.compare_digest``).
"""

from __future__ import annotations

import asyncio
import collections
import hmac
import ipaddress
import logging
import math
import queue
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from host.api import DEFAULT_HOST, DEFAULT_PORT
from host.api import schema as S

log = logging.getLogger("ucr.api")

# websockets closes the connection (code 1009) above this; between MAX_REQUEST_BYTES and this we
# still answer with a "too_large" error reply and keep the connection.
_HARD_FRAME_LIMIT = 1024 * 1024
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


class ApiServerError(RuntimeError):
    """The API server cannot start (bad bind address, missing token, port in use)."""


def is_loopback(host: str | None) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, "localhost")."""
    if not host:
        return False  # "" / None means every interface
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: may resolve to anything


def check_bind(host: str | None, token: str | None) -> None:
    """Refuse a non-loopback bind without a token (clear message for the CLI)."""
    if not is_loopback(host) and not token:
        shown = host or "all interfaces"
        raise ApiServerError(
            f"refusing to listen on {shown} without a token: other machines could move the "
            "robot. Set api.token in the daemon config (8+ characters) or bind 127.0.0.1."
        )
    if token is not None and (len(token) < 8 or not token.isprintable() or " " in token):
        raise ApiServerError("the API token must be at least 8 printable characters, no spaces")


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


class _Subscription:
    """One API subscription: a daemon queue plus per-kind rate limiting and a drop counter."""

    def __init__(self, sid: int, kinds: list[str], max_rate: float | None, q: Any) -> None:
        self.sid = sid
        self.kinds = kinds
        self.min_period = 1.0 / max_rate if max_rate else 0.0
        self.queue = q
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


class _Session:
    """State of one connected client."""

    def __init__(self, ws: ServerConnection, outbox_size: int) -> None:
        self.ws = ws
        self.peer = _peer(ws)
        self.subs: dict[int, _Subscription] = {}
        self.goals: dict[Any, Any] = {}  # goal id -> last pushed status
        self.ffc_active: set[str] = set()  # bendables this client last drove with non-zero input
        self.stream: collections.deque[tuple[int, str]] = collections.deque()
        self.priority: collections.deque[str] = collections.deque()
        self.outbox_size = outbox_size
        self.wakeup = asyncio.Event()
        self.closed = False
        self.tokens = 0.0  # request budget (token bucket), refilled at max_request_rate
        self.t_refill = time.monotonic()
        self.throttled = 0

    def push_stream(self, sub: _Subscription, text: str) -> None:
        if len(self.stream) >= self.outbox_size:
            old_sid, _ = self.stream.popleft()
            victim = self.subs.get(old_sid)
            if victim is not None:
                victim.dropped += 1
        self.stream.append((sub.sid, text))
        self.wakeup.set()

    def push_priority(self, text: str) -> None:
        self.priority.append(text)
        self.wakeup.set()


def _peer(ws: ServerConnection) -> str:
    try:
        addr = ws.remote_address
        return f"{addr[0]}:{addr[1]}"
    except Exception:  # noqa: BLE001 - purely cosmetic
        return "?"


class ApiServer:
    """WebSocket API in front of a ``Daemon`` facade; ``start()`` runs it in a background thread.

    ``port=0`` picks a free port (see :attr:`port`). ``outbox_size`` bounds each client's queue of
    stream messages; ``poll_interval`` (s) is how often daemon queues are drained.
    """

    def __init__(
        self,
        daemon: Any,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        token: str | None = None,
        *,
        max_request_bytes: int = S.MAX_REQUEST_BYTES,
        outbox_size: int = 256,
        poll_interval: float = 0.005,
        status_interval: float = 0.05,
        workers: int = 2,
        max_request_rate: float = 500.0,
    ) -> None:
        check_bind(host, token)
        self.daemon = daemon
        self.host = host
        self.requested_port = port
        self.port: int | None = None
        self.token = token
        self.max_request_bytes = max_request_bytes
        self.outbox_size = outbox_size
        self.poll_interval = poll_interval
        self.status_interval = status_interval
        self.max_request_rate = max_request_rate
        self.request_burst = max(1.0, max_request_rate / 5)
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ucr-api-call")
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._start_error: BaseException | None = None
        self._sessions: set[_Session] = set()
        self._next_sub = 1
        self.counters = {"connections": 0, "requests": 0, "errors": 0, "auth_failures": 0}

    # ------------------------------------------------------------------ lifecycle
    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"ws://{host}:{self.port}"

    def start(self, timeout: float = 5.0) -> ApiServer:
        """Bind and serve in a background thread; :class:`ApiServerError` if binding fails."""
        if self._thread is not None:
            raise ApiServerError("API server already started")
        self._thread = threading.Thread(target=self._run, name="ucr-api", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise ApiServerError("API server did not start in time")
        if self._start_error is not None:
            self._thread.join(1.0)
            err = self._start_error
            raise ApiServerError(f"cannot listen on {self.host}:{self.requested_port}: {err}")
        log.info("API listening on %s%s", self.url, " (token required)" if self.token else "")
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Close all connections (their streams end, subscriptions are released) and the thread."""
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:
                pass  # loop already gone
        if self._thread is not None:
            self._thread.join(timeout)
        self._pool.shutdown(wait=False, cancel_futures=True)

    def __enter__(self) -> ApiServer:
        return self.start() if self._thread is None else self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def stats(self) -> dict:
        """Counters for diagnostics: connections, requests, errors, active clients, drops."""
        sessions = list(self._sessions)
        return {
            **self.counters,
            "clients": len(sessions),
            "subscriptions": sum(len(s.subs) for s in sessions),
            "dropped": sum(sub.dropped for s in sessions for sub in s.subs.values()),
            "throttled": sum(s.throttled for s in sessions),
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
            max_size=_HARD_FRAME_LIMIT,
            max_queue=32,
            ping_interval=20,
            ping_timeout=20,
            server_header="ucr-api",
        ) as server:
            sock = next(iter(server.sockets))
            self.port = sock.getsockname()[1]
            self._ready.set()
            pump = asyncio.create_task(self._pump())
            await self._stop.wait()
            pump.cancel()
            server.close(close_connections=True)
            await server.wait_closed()

    # ------------------------------------------------------------------ auth
    def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        if self.token is None:
            return None
        header = request.headers.get("Authorization", "")
        scheme, _, given = header.partition(" ")
        if scheme.lower() == "bearer" and hmac.compare_digest(
            given.strip().encode(), self.token.encode()
        ):
            return None
        self.counters["auth_failures"] += 1
        log.warning("API: refused %s: missing or wrong token", _peer(conn))
        return conn.respond(HTTPStatus.UNAUTHORIZED, "missing or wrong API token\n")

    # ------------------------------------------------------------------ connection
    async def _handle(self, ws: ServerConnection) -> None:
        session = _Session(ws, self.outbox_size)
        session.tokens = self.request_burst
        self._sessions.add(session)
        self.counters["connections"] += 1
        log.info("API: client %s connected", session.peer)
        sender = asyncio.create_task(self._sender(session))
        try:
            async for frame in ws:
                await self._throttle(session)
                reply = await self._serve_frame(session, frame)
                try:
                    text = S.encode(reply)
                except (TypeError, ValueError) as exc:  # a result JSON cannot carry
                    log.error("API: cannot encode the reply to %s: %s", reply.get("id"), exc)
                    text = S.encode(
                        S.error_reply(
                            reply.get("id"),
                            S.INTERNAL,
                            f"internal error: result not encodable ({exc})",
                        )
                    )
                await ws.send(text)
        except ConnectionClosed:
            pass
        finally:
            session.closed = True
            session.wakeup.set()
            sender.cancel()
            self._sessions.discard(session)
            await self._cleanup(session)
            log.info("API: client %s gone", session.peer)

    async def _throttle(self, session: _Session) -> None:
        """Pace a client above ``max_request_rate`` requests/s by reading its requests later
        (TCP back-pressure), so one flooding client cannot load the daemon; nothing is refused."""
        now = time.monotonic()
        session.tokens = min(
            self.request_burst,
            session.tokens + (now - session.t_refill) * self.max_request_rate,
        )
        session.t_refill = now
        if session.tokens < 1.0:
            session.throttled += 1
            await asyncio.sleep((1.0 - session.tokens) / self.max_request_rate)
            session.tokens = 1.0
            session.t_refill = time.monotonic()
        session.tokens -= 1.0

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
                    await ws.send(text)
        except ConnectionClosed:
            pass

    async def _cleanup(self, session: _Session) -> None:
        """Release what a departed client held: subscriptions and its cFFC stream."""
        subs = list(session.subs.values())
        session.subs.clear()
        for sub in subs:
            await self._call_quiet(self.daemon.unsubscribe, sub.queue)
        if session.ffc_active:
            # Stop its cFFC input at once rather than waiting for the daemon's deadman.
            zeros = {name: (0.0, 0.0) for name in session.ffc_active}
            try:
                await self._call(self.daemon.ffc_input, zeros)
            except Exception:  # noqa: BLE001 - e.g. a segment gone meanwhile: try one by one
                for name in sorted(session.ffc_active):
                    await self._call_quiet(self.daemon.ffc_input, {name: (0.0, 0.0)})

    async def _call(self, fn: Any, *args: Any) -> Any:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    async def _call_quiet(self, fn: Any, *args: Any) -> None:
        try:
            await self._call(fn, *args)
        except Exception as exc:  # noqa: BLE001 - cleanup must go on
            log.warning("API cleanup: %s failed: %s", getattr(fn, "__name__", fn), exc)

    # ------------------------------------------------------------------ requests
    async def _serve_frame(self, session: _Session, frame: str | bytes) -> dict:
        self.counters["requests"] += 1
        try:
            rid, op, params = S.parse_request(frame, self.max_request_bytes)
        except S.RequestError as exc:
            self.counters["errors"] += 1
            return S.error_reply(exc.request_id, exc.code, exc.message)
        try:
            result = await self._dispatch(session, op, params)
        except S.RequestError as exc:
            self.counters["errors"] += 1
            return S.error_reply(rid, exc.code, exc.message)
        except Exception as exc:  # noqa: BLE001 - becomes an error reply, never kills the server
            self.counters["errors"] += 1
            code, message = _classify(exc)
            if code == S.INTERNAL:
                log.exception("API: op %s failed", op)
            return S.error_reply(rid, code, message)
        return S.ok_reply(rid, result)

    async def _dispatch(self, session: _Session, op: str, p: dict) -> Any:
        d = self.daemon
        if op == "ping":
            return {"pong": True, "t": time.time()}
        if op == "status":
            return await self._call(d.status)
        if op == "topology":
            return await self._call(d.topology)
        if op == "loop_stats":
            return await self._call(d.loop_stats)
        if op == "controllers.list":
            return await self._call(d.controllers)
        if op == "controllers.switch":
            return await self._call(d.switch_controllers, p["start"], p["stop"])
        if op == "controllers.hand_back":
            hand_back = getattr(d, "hand_back", None)
            if hand_back is None:
                raise S.RequestError(
                    S.UNKNOWN_OP, "this daemon has no manual takeover to hand back"
                )
            return await self._call(hand_back, p["manual"])
        if op == "faults.clear":
            return await self._call(d.clear_fault, p["segment"])
        if op == "trajectory.send":
            goal = await self._call(d.send_trajectory, p["points"], p["controller"])
            session.goals[goal] = None
            return {"goal": goal}
        if op == "trajectory.status":
            return await self._call(d.trajectory_status, p["goal"])
        if op == "trajectory.cancel":
            return await self._call(d.cancel_trajectory, p["goal"])
        if op == "ffc.input":
            rates = p["rates"]
            # Remember before calling: if the call fails half-way the input may still be set,
            # and a disconnect must then zero it.
            before = set(session.ffc_active)
            session.ffc_active.update(n for n, (x, y) in rates.items() if x or y)
            try:
                result = await self._call(d.ffc_input, rates)
            except ValueError:
                session.ffc_active = before  # refused: the daemon did not take this input
                raise
            session.ffc_active.difference_update(n for n, (x, y) in rates.items() if not (x or y))
            return result
        if op == "subscribe":
            return await self._subscribe(session, p["kinds"], p["max_rate"])
        if op == "unsubscribe":
            sub = session.subs.pop(p["sub"], None)
            if sub is None:
                raise S.RequestError(S.NOT_FOUND, f"no subscription {p['sub']} on this connection")
            await self._call(d.unsubscribe, sub.queue)
            return {
                "sub": sub.sid,
                "sent": sub.sent,
                "dropped": sub.dropped,
                "thinned": sub.thinned,
            }
        raise S.RequestError(S.UNKNOWN_OP, f"unknown op {op!r}")  # pragma: no cover - schema guards

    async def _subscribe(self, session: _Session, kinds: list[str], max_rate: float | None) -> dict:
        daemon_kinds = ["event" if k == "events" else k for k in kinds]
        q = await self._call(self.daemon.subscribe, daemon_kinds)
        sid = self._next_sub
        self._next_sub += 1
        session.subs[sid] = _Subscription(sid, kinds, max_rate, q)
        return {"sub": sid, "kinds": kinds, "max_rate": max_rate}

    # ------------------------------------------------------------------ pump
    async def _pump(self) -> None:
        """Move published messages from daemon queues into client outboxes; poll goal status."""
        next_status = 0.0
        while True:
            now = time.monotonic()
            try:
                for session in list(self._sessions):
                    for sub in list(session.subs.values()):
                        self._drain(session, sub, now)
                if now >= next_status:
                    next_status = now + self.status_interval
                    for session in list(self._sessions):
                        if session.goals:
                            await self._poll_goals(session)
            except Exception:  # noqa: BLE001 - the pump must outlive any one bad message
                log.exception("API: forwarding failed")
            busy = any(s.subs or s.goals for s in self._sessions)
            # Nothing to forward: wake up less often (the Pi has better things to do).
            await asyncio.sleep(self.poll_interval if busy else 10 * self.poll_interval)

    def _drain(self, session: _Session, sub: _Subscription, now: float) -> None:
        q = sub.queue
        for _ in range(1000):  # bounded so one flood cannot starve the event loop
            try:
                msg = q.get_nowait()
            except queue.Empty:
                return
            except Exception as exc:  # noqa: BLE001 - a broken queue must not kill the pump
                log.warning("API: subscription %d queue failed: %s", sub.sid, exc)
                return
            kind = S.normalize_kind(msg.get("kind", "")) if isinstance(msg, dict) else ""
            if kind and kind not in sub.kinds:
                continue  # the daemon sent more than asked for
            if not sub.admit(kind, now):
                continue
            push = {"push": "stream", "sub": sub.sid, "dropped": sub.dropped, "msg": msg}
            try:
                text = S.encode(push)
            except (TypeError, ValueError) as exc:
                log.warning("API: dropped a %s message that JSON cannot carry: %s", kind, exc)
                continue
            sub.sent += 1
            session.push_stream(sub, text)

    async def _poll_goals(self, session: _Session) -> None:
        for goal, last in list(session.goals.items()):
            try:
                status = await self._call(self.daemon.trajectory_status, goal)
            except Exception as exc:  # noqa: BLE001 - report and stop following it
                status = {"state": "unknown", "error": str(exc)}
                session.goals.pop(goal, None)
                session.push_priority(
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": True})
                )
                continue
            done = goal_done(status)
            if _progress_key(status) != _progress_key(last) or done:
                session.push_priority(
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": done})
                )
                session.goals[goal] = status
            if done:
                session.goals.pop(goal, None)


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


def _classify(exc: Exception) -> tuple[str, str]:
    """Map a daemon exception onto an error code without leaking a traceback.

    The daemon's ``DaemonError`` (a RuntimeError: not running, chain lost) -> unavailable;
    ``GoalNotFound`` (LookupError) -> not_found; ``ControllerError``/``SwitchError`` (ValueError:
    refused goal, conflicting switch, input for an unknown bendable) -> rejected.
    """
    code = getattr(exc, "code", None)
    if isinstance(code, str) and code in S.ERROR_CODES:
        return code, str(exc)
    if isinstance(exc, LookupError):
        return S.NOT_FOUND, str(exc.args[0]) if exc.args else type(exc).__name__
    if isinstance(exc, ValueError):
        return S.REJECTED, str(exc)
    if any(c.__name__ == "DaemonError" for c in type(exc).__mro__):
        return S.UNAVAILABLE, str(exc)
    return S.INTERNAL, f"internal error ({type(exc).__name__}): {exc}"


def start_server(
    daemon: Any,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    token: str | None = None,
    **kwargs: Any,
) -> ApiServer:
    """Create and start an :class:`ApiServer`; the daemon CLI calls this."""
    return ApiServer(daemon, host, port, token, **kwargs).start()
