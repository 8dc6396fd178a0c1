"""How published messages leave the daemon's process for the API side of the bridge, with the
least delay and without ever making the control loop wait.

A message handed from the loop thread to another thread of the daemon's process waits for that
thread to get the interpreter lock, and right after a cycle publishes, the link reader and the
publisher thread (cRSP's FK) want it too: measured on the emulated rig, a joint_states message
waited 0.35–0.45 ms p50 (1.2–1.8 ms p90) between the loop's ``publish`` and the bridge's feeder
thread encoding it (docs/api.md "Latency"). So the small, latency-critical kinds
(:data:`DIRECT_KINDS`) are encoded and written by the publishing thread itself — only when that
costs no waiting: the socket is free (a lock taken without blocking), nothing is queued before the
message (order is kept), and the socket takes bytes without blocking. Everything else, and any
message that finds the way busy, queues for the feeder thread as before.

:class:`FrameSender` is the bridge socket's one writing discipline: frames are written whole and in
order. ``send`` blocks (the bridge's own threads); ``try_send`` never does: a frame the socket takes
only in part leaves its rest as the *tail*, which the next writer sends before anything else (the
feeder is woken to do it).

:class:`Feed` is the bridge's one daemon subscription: ``Fanout.publish`` calls its
``put_nowait``, and a full feed drops its oldest message as any subscriber queue does. The feeder
takes a message out only while holding the sender's lock and writes it before releasing it, and the
direct path checks under that lock that nothing is queued: a message never overtakes one published
before it.
"""

from __future__ import annotations

import queue
import socket
import struct
import threading
from collections import deque
from typing import Any

from host.api import schema as S

HEAD = struct.Struct("!IB")  # [u32 length][u8 type]: the bridge's frame header
DIRECT_KINDS = frozenset({"joint_states"})  # small (a few hundred bytes), and latency matters


def publication(msg: Any) -> bytes:
    """The body of a ``P`` frame: ``kind "\\n" json``. Raises TypeError/ValueError/RecursionError
    for a message JSON cannot carry."""
    kind = msg.get("kind", "") if isinstance(msg, dict) else ""
    return S.normalize_kind(str(kind)).encode() + b"\n" + S.encode(msg).encode()


class FrameSender:
    """Writes bridge frames on ``sock``: whole, in order, from any thread (see module docstring)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.lock = threading.Lock()
        self._tail = b""  # the rest of a frame try_send could write only in part
        self.partial = 0  # frames try_send wrote only in part (their rest went as the tail)

    @property
    def tail_pending(self) -> bool:
        return bool(self._tail)

    def send(self, kind: bytes, body: bytes) -> None:
        """Write one frame, waiting as long as the socket needs (OSError when it is gone)."""
        with self.lock:
            self.send_locked(kind, body)

    def send_locked(self, kind: bytes, body: bytes) -> None:
        """:meth:`send` for a caller that holds :attr:`lock`."""
        self.flush_locked()
        self.sock.sendall(HEAD.pack(len(body), kind[0]) + body)

    def flush_locked(self) -> None:
        """Write the tail of a partly written frame, if any (caller holds :attr:`lock`)."""
        if self._tail:
            tail, self._tail = self._tail, b""
            self.sock.sendall(tail)

    def try_send(self, kind: bytes, body: bytes, busy: Any = None) -> bool:
        """Write one frame without ever waiting; False (nothing written) when the lock is taken,
        a tail is pending, ``busy()`` says so (checked under the lock), the socket takes no byte
        now, or it is broken (the bridge's threads find that out themselves)."""
        if not self.lock.acquire(blocking=False):
            return False
        try:
            if self._tail or (busy is not None and busy()):
                return False
            data = HEAD.pack(len(body), kind[0]) + body
            try:
                n = self.sock.send(data, socket.MSG_DONTWAIT)
            except OSError:  # BlockingIOError: full; anything else: the bridge is going
                return False
            if n < len(data):
                self._tail = data[n:]
                self.partial += 1
            return True
        finally:
            self.lock.release()


class Feed:
    """The bridge's daemon subscription (see module docstring). ``put_nowait`` / ``get_nowait``
    as ``queue.Queue`` (what ``Fanout.publish`` uses: ``queue.Full`` when full); the feeder
    thread uses :meth:`wait` and :meth:`take_locked`."""

    def __init__(
        self, sender: FrameSender, maxsize: int = 1000, counters: dict[str, int] | None = None
    ) -> None:
        self._sender = sender
        self._items: deque[Any] = deque()
        self._cond = threading.Condition(threading.Lock())
        self.maxsize = maxsize
        # "published" (also the direct ones), "direct" (written by the publishing thread),
        # "unencodable" (messages JSON cannot carry: dropped): the bridge's counters
        self.counters = counters if counters is not None else {}
        for key in ("published", "direct", "unencodable"):
            self.counters.setdefault(key, 0)

    def put_nowait(self, msg: Any) -> None:
        if (
            not self._items
            and isinstance(msg, dict)
            and msg.get("kind") in DIRECT_KINDS
            and not self._sender.lock.locked()
        ):
            try:
                body = publication(msg)
            except (TypeError, ValueError, RecursionError):
                self.counters["unencodable"] += 1
                return
            if self._sender.try_send(b"P", body, busy=lambda: bool(self._items)):
                self.counters["direct"] += 1
                self.counters["published"] += 1
                if self._sender.tail_pending:
                    self._wake()
                return
        with self._cond:
            if len(self._items) >= self.maxsize:
                raise queue.Full
            self._items.append(msg)
            self._cond.notify()

    def get_nowait(self) -> Any:
        with self._cond:
            if not self._items:
                raise queue.Empty
            return self._items.popleft()

    def qsize(self) -> int:
        return len(self._items)

    def wait(self, timeout: float) -> bool:
        """Wait at most ``timeout`` s for a queued message or a tail to write; True if there is."""
        with self._cond:
            if not self._items and not self._sender.tail_pending:
                self._cond.wait(timeout)
            return bool(self._items) or self._sender.tail_pending

    def take_locked(self) -> Any:
        """The oldest queued message or None; the caller holds the sender's lock and writes the
        message before releasing it (so the direct path cannot overtake it)."""
        try:
            return self.get_nowait()
        except queue.Empty:
            return None

    def _wake(self) -> None:
        with self._cond:
            self._cond.notify()
