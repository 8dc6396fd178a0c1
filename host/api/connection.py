"""The API server's connection side, two parts the server composes:

- :class:`Outboxes`: fan-out and the outboxes. Each published message arrives encoded once and is
  fanned out by kind to the subscribers' outboxes, bounded in messages and bytes (per client and
  in total); trajectory progress goes first.
- :class:`Connections`: one loop per client connection. Requests are parsed, charged by their
  bytes and the work their op causes (``_OP_WORK``, looked up by the parsed op) and answered by
  the request side (:class:`host.api.dispatch.Dispatcher`); a janitor closes clients that
  stopped reading.

The request budget has two levels. Each connection has its own bucket: a client above it is read
later (TCP back-pressure), which delays that client alone. All clients together have the global
bucket, shared fairly: while it has room anyone may use it; once it is empty, each token (each
connection when no token is configured) may go on at an equal share of the global rate, and a
request above its token's share is refused at once with ``rate_limited`` (nobody waits for
another client's cost). The global bucket stays within one burst of debt. A control token's
requests that stop motion (``trajectory.cancel``, a switch that only stops, an all-zero
``ffc.input``) are never refused for budget.

Each gets what it needs at construction (options, the shared counters, callables); neither reads
the server's fields.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from host.api import schema as S
from host.api.audit import audit_log
from host.api.auth import CONTROL
from host.api.memory import MemoryRelease
from host.api.session import _Request, _Session, _Subscription, command_source

log = logging.getLogger("ucr.api")

# Extra budget units per op, on top of 1 per request and 1 per KiB: what it costs the daemon.
_OP_WORK = {
    "topology": 4,
    "robot.description": 8,  # one topology call; its reply carries the description's text
    "loop_stats": 4,
    "controllers.list": 4,
    "trajectory.status": 2,
    "trajectory.cancel": 4,
    "controllers.switch": 20,
    "controllers.hand_back": 20,
    "trajectory.send": 20,
    "ffc.input": 1,
}


def _stops_motion(op: str, params: dict) -> bool:
    """Whether a request only stops motion (never refused for budget when a control token's)."""
    if op == "trajectory.cancel":
        return True
    if op == "controllers.switch":
        return not params["start"]
    if op == "ffc.input":
        return not any(x or y for x, y in params["rates"].values())
    return False


def _frame_bytes(frame: str | bytes) -> int:
    """The size of a frame in bytes (as it came on the wire, uncompressed)."""
    if isinstance(frame, str) and not frame.isascii():
        return len(frame.encode("utf-8", "surrogatepass"))
    return len(frame)


class _Share:
    """One token's share of the global request budget (a bucket; see the module docstring)."""

    __slots__ = ("sessions", "t_refill", "tokens")

    def __init__(self, tokens: float) -> None:
        self.sessions = 0
        self.tokens = tokens
        self.t_refill = time.monotonic()


class Requests(Protocol):
    """What a connection needs from the request side."""

    def parse(self, session: _Session, frame: str | bytes) -> _Request | dict: ...

    async def serve(self, session: _Session, request: _Request) -> dict | str: ...

    def end_upload(self, session: _Session) -> None: ...

    def drop_stale_uploads(self, now: float) -> None: ...


class Outboxes:
    """Subscriptions by kind and every client's outbox (``queued_bytes``: all of them).

    ``want_stream(kinds)`` tells the daemon side which kinds anyone subscribes to, each with
    the distinct periods its subscribers thin it to (None: someone wants every message), so the
    daemon sends only what some subscription admits (host/api/feed.py, "Thinning").
    """

    def __init__(
        self,
        opts: Any,
        counters: dict[str, int],
        want_stream: Callable[[dict[str, tuple[float, ...] | None]], None],
    ) -> None:
        self.opts = opts
        self.counters = counters
        self._want_stream = want_stream
        self.by_kind: dict[str, dict[_Subscription, _Session]] = {k: {} for k in S.KINDS}
        self.queued_bytes = 0

    def add(self, session: _Session, sub: _Subscription) -> None:
        """Fan ``sub``'s kinds out to ``session`` from now on."""
        for kind in sub.kinds:
            self.by_kind[kind][sub] = session
        self._update_stream_wanted()

    def remove(self, sub: _Subscription) -> None:
        for kind in sub.kinds:
            self.by_kind[kind].pop(sub, None)
        self._update_stream_wanted()

    def publish(self, kind: str, text: str, stamp: float | None = None) -> None:
        """One published message (JSON text, encoded once) to every subscriber of its kind;
        ``stamp``: its time (s, the daemon's monotonic clock), by which ``max_rate`` thins
        (default: now)."""
        subs = self.by_kind.get(kind)
        if not subs:
            return
        t = time.monotonic() if stamp is None else stamp
        for sub, session in list(subs.items()):
            if session.closed or not sub.admit(kind, t):
                continue
            push = f'{{"push":"stream","sub":{sub.sid},"dropped":{sub.dropped},"msg":{text}}}'
            self._push_stream(session, sub, push)

    def _push_stream(self, session: _Session, sub: _Subscription, push: str) -> None:
        size = len(push)
        opts = self.opts
        while session.stream and (
            len(session.stream) >= opts.outbox_size
            or session.queued_bytes + size > opts.outbox_bytes
            or self.queued_bytes + size > opts.global_outbox_bytes
        ):
            victim, old = session.stream.popleft()
            session.queued_bytes -= len(old)
            self.queued_bytes -= len(old)
            victim.dropped += 1
            self.counters["dropped"] += 1
        if self.queued_bytes + size > opts.global_outbox_bytes:
            sub.dropped += 1
            self.counters["dropped"] += 1
            return
        if not session.stream and not session.priority:
            session.t_progress = time.monotonic()  # idle until now: not a slow reader
        session.stream.append((sub, push))
        session.queued_bytes += size
        self.queued_bytes += size
        sub.sent += 1
        session.wakeup.set()

    def push_priority(self, session: _Session, text: str) -> None:
        """Queue ``text`` ahead of the stream messages (trajectory progress)."""
        if not session.stream and not session.priority:
            session.t_progress = time.monotonic()
        session.priority.append(text)
        session.queued_bytes += len(text)
        self.queued_bytes += len(text)
        session.wakeup.set()

    def take(self, session: _Session) -> str | None:
        """The next text to send to ``session`` (progress first), or None when it is empty."""
        if session.priority:
            text = session.priority.popleft()
        elif session.stream:
            _, text = session.stream.popleft()
        else:
            return None
        session.queued_bytes -= len(text)
        self.queued_bytes -= len(text)
        return text

    def drop(self, session: _Session) -> None:
        """Forget ``session``'s outbox and stop fanning out to its subscriptions."""
        self.queued_bytes -= session.queued_bytes
        session.queued_bytes = 0
        session.stream.clear()
        session.priority.clear()
        for sub in session.subs.values():
            for kind in sub.kinds:
                self.by_kind[kind].pop(sub, None)
        self._update_stream_wanted()

    def _update_stream_wanted(self) -> None:
        wanted: dict[str, tuple[float, ...] | None] = {}
        for kind, subs in self.by_kind.items():
            if not subs:
                continue
            periods = {sub.min_period for sub in subs}
            thinned = kind in S.RATE_LIMITED_KINDS and min(periods) > 0.0
            wanted[kind] = tuple(sorted(periods)) if thinned else None
        self._want_stream(wanted)


class Connections:
    """The connected clients (``sessions``) and the loop serving each.

    ``requests`` answers frames; ``call(name, *args)`` reaches the daemon (a departed client's
    cFFC input is zeroed); ``tcp_total()`` is the server's count of open TCP connections.
    """

    def __init__(
        self,
        opts: Any,
        counters: dict[str, int],
        outboxes: Outboxes,
        requests: Requests,
        call: Callable[..., Awaitable[Any]],
        tcp_total: Callable[[], int],
    ) -> None:
        self.opts = opts
        self.counters = counters
        self._outboxes = outboxes
        self._requests = requests
        self._call = call
        self._tcp_total = tcp_total
        self.sessions: set[_Session] = set()
        self.max_request_rate = opts.max_request_rate
        self.request_burst = max(1.0, opts.max_request_rate / 5)
        self.global_burst = max(1.0, opts.global_request_rate / 5)
        self._global_tokens = self.global_burst  # never below -global_burst
        self._global_refill = time.monotonic()
        self._shares: dict[Any, _Share] = {}  # by token (by session when anonymous)
        # the dearest request that parses: 1 + its KiB + the dearest op
        self.max_request_cost = 1.0 + opts.max_request_bytes / 1024.0 + max(_OP_WORK.values())
        self.bytes_in = 0  # request bytes read from all clients (the janitor's memory rule)

    async def handle(self, ws: ServerConnection) -> None:
        """Serve one client until it goes; then release what it held."""
        token = getattr(ws, "ucr_token", None)
        session = _Session(ws, token, CONTROL)
        session.tokens = self.request_burst
        key = token if token is not None else session
        share = self._shares.get(key)
        if share is None:
            share = self._shares[key] = _Share(self._share_burst(len(self._shares) + 1))
        share.sessions += 1
        session.share = share
        self.sessions.add(session)
        self.counters["connections"] += 1
        log.info("API: client %s connected (%s, %s)", session.peer, session.who, session.scope)
        sender = asyncio.create_task(self._sender(session))
        account = getattr(ws, "ucr_account", None)  # the server's count of held request bytes
        try:
            async for frame in ws:
                # A connection closed for holding too much input is not answered; any other
                # (a client that sent a cancel and closed at once) still has its requests run.
                if getattr(ws, "ucr_shed", False):
                    break
                if account is not None:
                    ws.ucr_handling = len(frame)
                    account()
                reply = await self._answer(session, frame)
                if getattr(ws, "ucr_shed", False):
                    break
                await ws.send(reply)
                if account is not None:
                    ws.ucr_handling = 0
                    account()
        except ConnectionClosed:
            pass
        finally:
            session.closed = True
            session.wakeup.set()
            sender.cancel()
            self.sessions.discard(session)
            share.sessions -= 1
            if share.sessions <= 0:
                self._shares.pop(key, None)
            self._outboxes.drop(session)
            await self._cleanup(session)
            log.info("API: client %s gone", session.peer)

    async def _answer(self, session: _Session, frame: str | bytes) -> str:
        """The reply to one frame: parsed, charged (bytes + the parsed op's work), then served
        or refused with ``rate_limited`` when its token's share of the global budget is used up.
        """
        request = self._requests.parse(session, frame)
        cost = 1.0 + _frame_bytes(frame) / 1024.0
        self.bytes_in += len(frame)
        if isinstance(request, dict):  # an error reply: already made, so answered (and charged)
            await self._pace(session, cost)
            self._admit(session, cost, must=True)
            return self._encode_reply(request)
        cost += _OP_WORK.get(request.op, 0)
        await self._pace(session, cost)
        must = session.scope == CONTROL and _stops_motion(request.op, request.params)
        retry = self._admit(session, cost, must=must)
        if retry > 0:
            session.rate_limited += 1
            self.counters["rate_limited"] += 1
            self.counters["errors"] += 1
            return self._encode_reply(
                S.error_reply(
                    request.rid,
                    S.RATE_LIMITED,
                    f"rate limited: the share of the server's request budget of this token "
                    f"({session.who}) is used up while other clients are busy; retry in "
                    f"{retry:.2f} s",
                )
            )
        reply = await self._requests.serve(session, request)
        return reply if isinstance(reply, str) else self._encode_reply(reply)

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

    async def _pace(self, session: _Session, cost: float) -> None:
        """The connection's own bucket: a client above it is read later (TCP back-pressure),
        which delays that client alone. Waits exactly until the bucket holds ``cost`` (a frame
        dearer than the burst waits for its whole cost), so it never goes into debt."""
        rate = self.max_request_rate
        now = time.monotonic()
        session.tokens = min(self.request_burst, session.tokens + (now - session.t_refill) * rate)
        session.t_refill = now
        if session.tokens < cost:
            session.throttled += 1
            self.counters["throttled"] += 1
            gone = getattr(session.ws, "connection_lost_waiter", None)
            if isinstance(gone, asyncio.Future):  # a client that goes is not waited for
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(asyncio.shield(gone), (cost - session.tokens) / rate)
            else:
                await asyncio.sleep((cost - session.tokens) / rate)
            session.tokens = cost
            session.t_refill = time.monotonic()
        session.tokens -= cost

    def _share_burst(self, shares: int) -> float:
        """A share's burst: its part of the global burst, but at least the dearest request that
        parses (so any request fits in a share, however many tokens are connected)."""
        return max(self.max_request_cost, self.global_burst / max(1, shares))

    def _admit(self, session: _Session, cost: float, *, must: bool = False) -> float:
        """Charge ``cost`` to the global budget; 0.0 if admitted, else the seconds until the
        session's token could afford it (the request is then refused, nothing charged).

        While the global bucket holds ``cost`` anyone takes from it. Otherwise the token's share
        (the global rate divided by the tokens connected) decides; ``must`` (a stop, or an
        error reply already made) is admitted regardless. What a share admits is charged to the
        global bucket too, which never goes below minus one burst."""
        now = time.monotonic()
        grate = self.opts.global_request_rate
        self._global_tokens = min(
            self.global_burst, self._global_tokens + (now - self._global_refill) * grate
        )
        self._global_refill = now
        if self._global_tokens >= cost:
            self._global_tokens -= cost
            return 0.0
        share = session.share
        if share is None:  # a session not served by handle() (tests): a share of its own
            share = session.share = _Share(self._share_burst(1))
        n = max(1, len(self._shares))
        rate, burst = grate / n, self._share_burst(n)
        share.tokens = min(burst, share.tokens + (now - share.t_refill) * rate)
        share.t_refill = now
        if share.tokens < cost and not must:
            return (cost - share.tokens) / rate
        share.tokens = max(share.tokens - cost, -burst)
        self._global_tokens = max(self._global_tokens - cost, -self.global_burst)
        return 0.0

    async def _sender(self, session: _Session) -> None:
        """Send pushes in order: trajectory progress first, then stream messages."""
        ws = session.ws
        try:
            while not session.closed:
                await session.wakeup.wait()
                session.wakeup.clear()
                while (text := self._outboxes.take(session)) is not None:
                    await ws.send(text)
                    session.t_progress = time.monotonic()
        except ConnectionClosed:
            pass

    async def _cleanup(self, session: _Session) -> None:
        """Release what a departed client held: uploads, subscriptions and its cFFC stream."""
        self._requests.end_upload(session)
        session.subs.clear()
        if session.ffc_active:
            # Stop its cFFC input at once rather than waiting for the daemon's deadman.
            zeros = {name: (0.0, 0.0) for name in session.ffc_active}
            s = session
            audit_log(s.peer, s.who, s.scope, "ffc.input", None, "zeroed on disconnect", s.agent)
            source = command_source(s)  # (outside a request: for no one, the API zeroes it)
            try:
                await self._call("ffc_input", zeros, source)
            except Exception:  # noqa: BLE001 - e.g. a segment gone meanwhile: try one by one
                for name in sorted(session.ffc_active):
                    with contextlib.suppress(Exception):
                        await self._call("ffc_input", {name: (0.0, 0.0)}, source)

    async def janitor(self) -> None:
        """Once a second: close clients that stopped reading; forget stale uploads; give memory
        back to the OS after a burst (:class:`host.api.memory.MemoryRelease`)."""
        memory = MemoryRelease(self.opts.release_after_growth)
        while True:
            await asyncio.sleep(min(1.0, self.opts.slow_close_s / 2))
            now = time.monotonic()
            if memory.tick(self._tcp_total(), self.bytes_in):
                self.counters["memory_releases"] += 1
            for session in list(self.sessions):
                stuck = session.stream or session.priority
                if stuck and now - session.t_progress > self.opts.slow_close_s:
                    self.counters["slow_closed"] += 1
                    log.warning("API: closing %s: it stopped reading", session.peer)
                    self._outboxes.drop(session)
                    session.closed = True
                    session.ws.transport.abort()
            self._requests.drop_stale_uploads(now)
