"""The seam between the control loop's process and the API server: a socket carrying RPCs,
published messages (encoded once) and status snapshots.

Daemon side, :class:`DaemonBridge`: calls the Daemon facade for RPCs (a small worker pool),
holds ONE daemon subscription to the kinds clients subscribe to, JSON-encodes each published
message once and sends it on, and sends a status snapshot every ``status_period`` s and after
every op that changes state. The loop's cost per published message does not grow with the number
of clients: a ``put_nowait`` into the bridge's feed, which for a joint_states message that finds
the socket free and nothing queued before it means encoding it (tens of µs) and one write that
never blocks — saving the ~0.4 ms a hand-over to the feeder thread waits for the interpreter lock
(host/api/feed.py); everything else is encoded and written by the feeder thread.

API side, :class:`DaemonLink`: the facade as the API server sees it — ``await call(...)``, the
latest status snapshot (read without locks), and a callback per published message.

Wire: frames ``[u32 length][u8 type][body]``; types ``Q`` request ``{"id", "m", "a"}``, ``A``
answer ``{"id", "ok", "r" | "code", "message"}``, ``P`` publication ``kind "\\n" stamp "\\n" json``
(``stamp``: the message's time, by which subscriptions are thinned, host/api/feed.py), ``S``
status JSON, ``U`` the kinds clients subscribe to (comma-separated; ``kind@p1;p2`` when every
subscriber of a periodic kind thins it, with their distinct periods in s), ``Q``/``q`` a
request whose waypoints follow in parts, ``C``/``Y`` configuration and ready message of a
separate API process. JSON only: the API side never sends anything the daemon executes
beyond the whitelisted facade methods with JSON arguments.

One piece: the two classes are the two ends of this one wire (its frame types and what each
body holds), which change together; each end is one class, and the feed's thinning and the ``U``
frame's syntax live in host/api/feed.py.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import logging
import queue
import socket
import struct
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from host.api import schema as S
from host.api.feed import HEAD, Feed, FrameSender, format_wanted, parse_wanted, publication

log = logging.getLogger("ucr.api")

_HEAD = HEAD  # [u32 length][u8 type] (host/api/feed.py)
MAX_FRAME = 64 * 1024 * 1024  # a wire frame above this is a protocol error (bridge closes)
PART_POINTS = 250  # waypoints per bridge frame (~40 KB: a json.loads of well under 1 ms)
DAEMON_KINDS = ("joint_states", "transforms", "event", "topology")

# facade methods an RPC may name; True: changes state (a fresh status snapshot follows)
METHODS: dict[str, bool] = {
    "status": False,
    "topology": False,
    "robot_description": False,
    "loop_stats": False,
    "controllers": False,
    "trajectory_status": False,
    "switch_controllers": True,
    "hand_back": True,
    "clear_fault": True,
    "send_trajectory": True,
    "cancel_trajectory": True,
    "ffc_input": False,  # a snapshot follows only if it took over (see DaemonBridge._serve)
}


class BridgeClosed(ConnectionError):
    """The other side of the bridge went away."""


class RemoteError(Exception):
    """A facade call failed on the daemon side; ``code`` is an API error code."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


def send_frame(sock: socket.socket, lock: threading.Lock, kind: bytes, body: bytes) -> None:
    with lock:
        sock.sendall(_HEAD.pack(len(body), kind[0]) + body)


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), 1 << 20))
        if not chunk:
            raise BridgeClosed("bridge closed")
        buf += chunk
    return bytes(buf)


def recv_frame(sock: socket.socket) -> tuple[bytes, bytes]:
    """(type byte, body); BridgeClosed at EOF or on a malformed frame."""
    length, kind = _HEAD.unpack(_recv_exact(sock, _HEAD.size))
    if length > MAX_FRAME:
        raise BridgeClosed(f"bridge frame of {length} bytes")
    return bytes([kind]), _recv_exact(sock, length)


def classify(exc: BaseException) -> tuple[str, str]:
    """Map a daemon exception onto an API error code without leaking a traceback.

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


def _args_for(method: str, args: list) -> list:
    """JSON brings lists where the facade takes tuples (cFFC deflections)."""
    if method == "ffc_input" and args and isinstance(args[0], dict):
        rates = {k: tuple(v) if isinstance(v, list) else v for k, v in args[0].items()}
        return [rates, *args[1:]]  # (and who sent it)
    return args


class DaemonBridge:
    """Daemon side of the bridge (see module docstring). ``start()``, then ``stop()``."""

    def __init__(
        self,
        daemon: Any,
        sock: socket.socket,
        *,
        workers: int = 2,
        status_period: float = 0.05,
        queue_size: int = 1000,
    ) -> None:
        self.daemon = daemon
        self.sock = sock
        self.status_period = status_period
        self.queue_size = queue_size
        self._sender = FrameSender(sock)
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="ucr-api-call")
        self._stop = threading.Event()
        self._sub_lock = threading.Lock()
        self._sub: Any = None  # the daemon queue while any client subscribes
        self._sub_kinds: list[str] = []
        self._threads: list[threading.Thread] = []
        self.closed = threading.Event()
        self.counters = {"published": 0, "direct": 0, "unencodable": 0, "calls": 0}
        self._partial: dict[Any, tuple[dict, list]] = {}  # requests whose points are arriving

    def start(self) -> DaemonBridge:
        for target, name in ((self._reader, "ucr-api-bridge"), (self._feeder, "ucr-api-feed")):
            t = threading.Thread(target=target, name=name, daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout)
        self._set_subscribed([])
        self._pool.shutdown(wait=False, cancel_futures=True)
        with contextlib.suppress(OSError):
            self.sock.close()

    def _send(self, kind: bytes, body: bytes) -> None:
        try:
            self._sender.send(kind, body)
        except OSError:
            self._stop.set()

    # -- requests from the API side ----------------------------------------------------------
    def _reader(self) -> None:
        try:
            while not self._stop.is_set():
                self._on_frame(*recv_frame(self.sock))
        except (BridgeClosed, OSError, RuntimeError, struct.error, ValueError, KeyError):
            pass
        finally:
            self._stop.set()
            self._set_subscribed([])
            self.closed.set()

    def _on_frame(self, kind: bytes, body: bytes) -> None:
        """One frame from the API side. A method of its own, so nothing of a request (a
        10,000-waypoint goal is ~15 MB of parsed JSON) outlives its handling in the reader's
        locals while the reader waits for the next frame."""
        if kind == b"Q":
            head = json.loads(body)
            if head.get("parts"):  # the points follow in parts: parse them piecewise
                self._partial[head["id"]] = (head, [])
            else:
                self._pool.submit(self._serve, head)
        elif kind == b"q":
            part = json.loads(body)
            head, points = self._partial[part["id"]]
            points.extend(part["p"])
            if len(points) >= head["parts"]:
                del self._partial[part["id"]]
                head["a"][0] = points
                # none of it stays in these locals: the pool may answer it before this thread
                del points, part  # runs again (CI saw 757 waypoints alive after the answer)
                self._pool.submit(self._serve, head)
        elif kind == b"U":
            self._set_subscribed(*parse_wanted(body.decode()))
        else:
            log.warning("API bridge: unexpected frame type %r", kind)

    def _serve(self, req: dict) -> None:
        rid: Any = None
        args: list | None = None
        try:
            rid, method, args = req["id"], req["m"], _args_for(req["m"], list(req["a"]))
            if method not in METHODS:
                raise RemoteError(S.UNKNOWN_OP, f"no facade method {method!r}")
            fn = getattr(self.daemon, method, None)
            if fn is None:
                # an op of the API this facade does not serve (e.g. an older daemon's)
                raise RemoteError(S.UNAVAILABLE, f"this daemon does not offer {method!r}")
            self.counters["calls"] += 1
            result = fn(*args)
            text = S.encode({"id": rid, "ok": True, "r": result})
            changed = METHODS[method] or (
                method == "ffc_input" and isinstance(result, dict) and result.get("takeover")
            )
        except Exception as exc:  # noqa: BLE001 - every failure becomes an answer
            code, message = classify(exc)
            if isinstance(exc, TypeError | ValueError) and "encod" in str(exc):
                code, message = S.INTERNAL, f"internal error: result not encodable ({exc})"
            if code == S.INTERNAL:
                log.error("API: %s failed: %s", req.get("m"), message)
            text = S.encode({"id": rid, "ok": False, "code": code, "message": message})
            changed = False
        # the request (a long goal's waypoints: ~15 MB parsed) is dropped before the answer
        # goes: the pool's work item still holds ``req`` until this returns, which on a loaded
        # host came after the API side had its answer
        req.clear()
        args = None
        if changed:
            self._send_status()
        self._send(b"A", text.encode())

    # -- published messages and status ---------------------------------------------------------
    def _set_subscribed(
        self, kinds: list[str], caps: dict[str, tuple[float, ...]] | None = None
    ) -> None:
        """Hold one daemon subscription to exactly the kinds some client wants (none: none), so
        the daemon encodes nothing nobody reads (e.g. the large transforms), thinned to what
        the subscriptions' periods admit (``caps``, host/api/feed.py ``Feed.set_caps``)."""
        want = sorted({"event" if k == "events" else k for k in kinds} & set(DAEMON_KINDS))
        caps = caps or {}
        with self._sub_lock:
            if want == self._sub_kinds:
                if isinstance(self._sub, Feed):
                    self._sub.set_caps(caps)
                return
            if self._sub is not None:
                q, self._sub = self._sub, None
                with contextlib.suppress(Exception):
                    self.daemon.unsubscribe(q)
            self._sub_kinds = want
            if want and not self._stop.is_set():
                try:
                    if "into" in inspect.signature(self.daemon.subscribe).parameters:
                        feed = Feed(self._sender, self.queue_size, self.counters)
                        feed.set_caps(caps)
                        self._sub = self.daemon.subscribe(want, into=feed)
                    else:  # a facade without it (test stubs): a plain queue, all via the feeder
                        self._sub = self.daemon.subscribe(want)
                except Exception as exc:  # noqa: BLE001 - reported; streams stay empty
                    log.error("API bridge: cannot subscribe: %s", exc)

    def _send_status(self) -> None:
        try:
            text = S.encode(self.daemon.status())
        except Exception as exc:  # noqa: BLE001 - the API answers status with this error
            code, message = classify(exc)
            text = S.encode({"__error__": {"code": code, "message": message}})
        self._send(b"S", text.encode())

    def _feeder(self) -> None:
        next_status = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_status:
                next_status = now + self.status_period
                self._send_status()
            q = self._sub
            if q is None:
                self._stop.wait(min(self.status_period, max(0.0, next_status - now)))
                continue
            timeout = max(0.001, next_status - time.monotonic())
            if isinstance(q, Feed):
                if q.wait(timeout):
                    self._feed_one(q)
                continue
            try:
                msg = q.get(timeout=timeout)
            except queue.Empty:
                continue
            except Exception:  # noqa: BLE001 - a broken queue: forget it
                continue
            body = self._publication(msg)
            if body is not None:
                self._send(b"P", body)

    def _feed_one(self, feed: Feed) -> None:
        """Write a pending tail and the oldest queued message, both under the sender's lock (the
        direct path then sees the queue non-empty and cannot overtake the message)."""
        try:
            with self._sender.lock:
                self._sender.flush_locked()
                msg = feed.take_locked()
                body = None if msg is None else self._publication(msg)
                if body is not None:
                    self._sender.send_locked(b"P", body)
        except OSError:
            self._stop.set()

    def _publication(self, msg: Any) -> bytes | None:
        try:
            body = publication(msg)
        except (TypeError, ValueError, RecursionError) as exc:
            kind = msg.get("kind", "") if isinstance(msg, dict) else ""
            self.counters["unencodable"] += 1
            log.warning("API: dropped a %s message that JSON cannot carry: %s", kind, exc)
            return None
        self.counters["published"] += 1
        return body


class DaemonLink:
    """API side of the bridge: RPCs as awaitables, the latest status snapshot, publications.

    Runs in the API server's event loop (no thread: one hop less for every published message).
    ``on_publish(kind, json_text, stamp)`` is called for every published message.
    """

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._ids = 0
        self._pending: dict[int, asyncio.Future] = {}
        self._on_publish: Callable[[str, str, float], None] | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task | None = None
        self.status_text: str | None = None  # replaced whole
        self.status_t = 0.0
        self.closed = False
        self._subscribed = ""

    async def start(self, on_publish: Callable[[str, str, float], None]) -> None:
        """Attach to the running event loop and start reading."""
        self._on_publish = on_publish
        reader, self._writer = await asyncio.open_connection(sock=self.sock, limit=MAX_FRAME)
        self._task = asyncio.get_running_loop().create_task(self._read(reader))

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        if self._writer is None:
            with contextlib.suppress(OSError):
                self.sock.close()

    def send_raw(self, kind: bytes, body: bytes) -> None:
        """Queue one frame to the daemon side (from the event loop)."""
        if self.closed or self._writer is None:
            raise BridgeClosed("the daemon side of the API is gone")
        self._writer.write(_HEAD.pack(len(body), kind[0]) + body)

    def want_stream(self, kinds: dict[str, tuple[float, ...] | None]) -> None:
        """Tell the daemon side which kinds any client subscribes to (empty: none), each with
        the distinct periods (s) its subscribers thin it to, or None (someone wants it whole)."""
        want = format_wanted(kinds)
        if want != self._subscribed and not self.closed:
            self._subscribed = want
            with contextlib.suppress(BridgeClosed):
                self.send_raw(b"U", want.encode())

    async def call(self, method: str, *args: Any) -> Any:
        """Call a facade method in the daemon's process; RemoteError if it failed there."""
        if self.closed:
            raise RemoteError(S.UNAVAILABLE, "the daemon is not reachable")
        loop = asyncio.get_running_loop()
        self._ids += 1
        rid = self._ids
        fut = loop.create_future()
        self._pending[rid] = fut
        try:
            args_l = list(args)
            points = args_l[0] if method == "send_trajectory" else None
            if isinstance(points, list) and len(points) > PART_POINTS:
                # Many waypoints: in parts, so the daemon's process never spends long in one
                # json.loads (a C call that holds the interpreter lock the control loop needs).
                head = {"id": rid, "m": method, "a": [None, *args_l[1:]], "parts": len(points)}
                self.send_raw(b"Q", json.dumps(head).encode())
                for i in range(0, len(points), PART_POINTS):
                    part = {"id": rid, "p": points[i : i + PART_POINTS]}
                    self.send_raw(b"q", json.dumps(part, allow_nan=False).encode())
                    await self._writer.drain()
            else:
                body = json.dumps({"id": rid, "m": method, "a": args_l}, allow_nan=False)
                self.send_raw(b"Q", body.encode())
                if len(body) > 65536:
                    await self._writer.drain()
            return await fut
        except (BridgeClosed, ConnectionError) as exc:
            raise RemoteError(S.UNAVAILABLE, str(exc)) from None
        finally:
            self._pending.pop(rid, None)

    async def _read(self, reader: asyncio.StreamReader) -> None:
        try:
            while True:
                head = await reader.readexactly(_HEAD.size)
                length, kind = _HEAD.unpack(head)
                if length > MAX_FRAME:
                    break
                body = await reader.readexactly(length)
                if kind == 0x50:  # P
                    k, _, rest = body.partition(b"\n")
                    ts, _, text = rest.partition(b"\n")
                    self._on_publish(k.decode(), text.decode(), float(ts))
                elif kind == 0x53:  # S
                    self.status_text = body.decode()
                    self.status_t = time.monotonic()
                elif kind == 0x41:  # A
                    self._answer(json.loads(body))
        except (asyncio.IncompleteReadError, OSError, ValueError):
            pass
        except Exception:  # noqa: BLE001 - a bad frame ends the bridge, loudly
            log.exception("API bridge: reading failed")
        finally:
            self.closed = True
            self._fail_all()

    def _answer(self, msg: dict) -> None:
        fut = self._pending.get(msg.get("id"))
        if fut is None or fut.done():
            return
        if msg.get("ok"):
            fut.set_result(msg.get("r"))
        else:
            fut.set_exception(RemoteError(str(msg.get("code")), str(msg.get("message"))))

    def _fail_all(self) -> None:
        for fut in list(self._pending.values()):
            if not fut.done():
                fut.set_exception(RemoteError(S.UNAVAILABLE, "the daemon side of the API closed"))
