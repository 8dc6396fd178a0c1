"""The API server's connection side, two parts the server composes:

- :class:`Outboxes`: fan-out and the outboxes. Each published message arrives encoded once and is
  fanned out by kind to the subscribers' outboxes, bounded in messages and bytes (per client and
  in total); trajectory progress goes first.
- :class:`Connections`: one loop per client connection. Requests are paced by a budget weighted
  by their bytes and the work they cause (``_OP_WORK``) and answered by the request side
  (:class:`host.api.dispatch.Dispatcher`); a janitor closes clients that stopped reading.

Each gets what it needs at construction (options, the shared counters, callables); neither reads
the server's fields.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import gc
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any, Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from host.api import schema as S
from host.api.audit import audit_log
from host.api.auth import CONTROL
from host.api.session import _Session, _Subscription

log = logging.getLogger("ucr.api")

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


class Requests(Protocol):
    """What a connection needs from the request side."""

    async def serve_frame(self, session: _Session, frame: str | bytes) -> dict | str: ...

    def end_upload(self, session: _Session) -> None: ...


class Outboxes:
    """Subscriptions by kind and every client's outbox (``queued_bytes``: all of them).

    ``want_stream(kinds)`` tells the daemon side which kinds anyone subscribes to.
    """

    def __init__(
        self, opts: Any, counters: dict[str, int], want_stream: Callable[[set[str]], None]
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

    def publish(self, kind: str, text: str) -> None:
        """One published message (JSON text, encoded once) to every subscriber of its kind."""
        subs = self.by_kind.get(kind)
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
        self._want_stream({kind for kind, subs in self.by_kind.items() if subs})


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
        self._global_tokens = opts.global_request_rate / 5
        self._global_refill = time.monotonic()
        self.bytes_in = 0  # request bytes read from all clients (the janitor's memory rule)

    async def handle(self, ws: ServerConnection) -> None:
        """Serve one client until it goes; then release what it held."""
        token = getattr(ws, "ucr_token", None)
        session = _Session(ws, token, CONTROL)
        session.tokens = self.request_burst
        self.sessions.add(session)
        self.counters["connections"] += 1
        log.info("API: client %s connected (%s, %s)", session.peer, session.who, session.scope)
        sender = asyncio.create_task(self._sender(session))
        try:
            async for frame in ws:
                await self._throttle(session, frame)
                reply = await self._requests.serve_frame(session, frame)
                text = reply if isinstance(reply, str) else self._encode_reply(reply)
                await ws.send(text)
        except ConnectionClosed:
            pass
        finally:
            session.closed = True
            session.wakeup.set()
            sender.cancel()
            self.sessions.discard(session)
            self._outboxes.drop(session)
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
        self.bytes_in += len(frame)
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
            audit_log(
                session.peer, session.who, session.scope, "ffc.input", None, "zeroed on disconnect"
            )
            try:
                await self._call("ffc_input", zeros)
            except Exception:  # noqa: BLE001 - e.g. a segment gone meanwhile: try one by one
                for name in sorted(session.ffc_active):
                    with contextlib.suppress(Exception):
                        await self._call("ffc_input", {name: (0.0, 0.0)})

    async def janitor(self) -> None:
        """Once a second: close clients that stopped reading; forget stale uploads; give memory
        back to the OS once a crowd of connections has gone, or once the requests parsed since
        the last time add up to RELEASE_AFTER_BYTES and a second passed without any."""
        peak = 0
        seen = released = 0  # self.bytes_in at the last tick and at the last release
        while True:
            await asyncio.sleep(min(1.0, self.opts.slow_close_s / 2))
            now = time.monotonic()
            total = self._tcp_total()
            peak = max(peak, total)
            crowd_gone = peak >= 32 and total <= peak // 8
            quiet = self.bytes_in == seen
            seen = self.bytes_in
            if crowd_gone or (quiet and seen - released >= RELEASE_AFTER_BYTES):
                peak, released = total, seen
                self.counters["memory_releases"] += 1
                _release_memory()
            for session in list(self.sessions):
                stuck = session.stream or session.priority
                if stuck and now - session.t_progress > self.opts.slow_close_s:
                    self.counters["slow_closed"] += 1
                    log.warning("API: closing %s: it stopped reading", session.peer)
                    self._outboxes.drop(session)
                    session.closed = True
                    session.ws.transport.abort()
                up = session.upload
                if up is not None and now - up.t_touched > 60.0:
                    self._requests.end_upload(session)


#: request bytes after which a quiet second returns free memory to the OS (see janitor)
RELEASE_AFTER_BYTES = 8 * 1024 * 1024


def _release_memory() -> None:
    """Collect garbage and return free heap pages to the OS (glibc ``malloc_trim``), so the
    process shrinks back after a burst of connections instead of keeping its peak."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)
