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

Thinning (:meth:`Feed.set_caps`): while every subscriber of a periodic kind
(``schema.RATE_LIMITED_KINDS``) asked for a ``max_rate``, the API side sends each distinct period
(``U`` frame, host/api/bridge.py) and the feed passes on only the messages that at least one of
those subscriptions will admit: the rule of ``session._Subscription.admit`` (:func:`admits`: a
message stamped at least 0.9 period after the last one admitted), run here on the same time stamps
(the message's ``t``, sent in the frame). Nothing a subscriber would have received is lost, and
nobody encodes, writes, reads or fans out the rest (``ucr view`` with no page open subscribes at
2 Hz to a 50 Hz stream).

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

import math
import queue
import socket
import struct
import threading
import time
from collections import deque
from typing import Any

from host.api import schema as S

HEAD = struct.Struct("!IB")  # [u32 length][u8 type]: the bridge's frame header
DIRECT_KINDS = frozenset({"joint_states"})  # small (a few hundred bytes), and latency matters
#: A subscription admits a message stamped at least this share of its period after the last one
#: it admitted (slack, so a 100 Hz stream thinned to 50 Hz does not alias down to 33 Hz).
ADMIT_SLACK = 0.9
#: Distinct periods per kind the feed thins by; more (many subscribers at many rates): that kind
#: is not thinned, which costs what it cost before thinning existed.
MAX_CAPS = 8


def stamp(msg: Any) -> float:
    """A message's time stamp (s, the daemon's monotonic clock): its ``t`` when that is a finite
    number, else now. Subscriptions thin by it, not by when a message reaches the API process
    (which the scheduling of two processes jitters)."""
    t = msg.get("t") if isinstance(msg, dict) else None
    if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
        return float(t)
    return time.monotonic()


def admits(t: float, last: float | None, period: float) -> bool:
    """The admission rule of a subscription thinned to one message per ``period`` s: the first
    message, then each stamped at least :data:`ADMIT_SLACK` periods after the last admitted."""
    return last is None or t - last >= period * ADMIT_SLACK


def publication(msg: Any, t: float | None = None) -> bytes:
    """The body of a ``P`` frame: ``kind "\\n" stamp "\\n" json`` (``stamp``: ``t``, default
    :func:`stamp`, as ``repr``, which a float round-trips exactly). Raises
    TypeError/ValueError/RecursionError for a message JSON cannot carry."""
    kind = msg.get("kind", "") if isinstance(msg, dict) else ""
    ts = repr(stamp(msg) if t is None else t).encode()
    return S.normalize_kind(str(kind)).encode() + b"\n" + ts + b"\n" + S.encode(msg).encode()


def format_wanted(kinds: dict[str, tuple[float, ...] | None]) -> str:
    """The ``U`` frame's body: ``kind`` or ``kind@p1;p2`` (periods in s, ``repr``: exact)."""
    parts = []
    for kind in sorted(kinds):
        periods = kinds[kind]
        parts.append(kind + ("@" + ";".join(map(repr, periods)) if periods else ""))
    return ",".join(parts)


def parse_wanted(text: str) -> tuple[list[str], dict[str, tuple[float, ...]]]:
    """(kinds, caps) of a ``U`` frame's body; a period that is not a number leaves its kind
    unthinned (everything is sent, as before thinning existed)."""
    kinds: list[str] = []
    caps: dict[str, tuple[float, ...]] = {}
    for item in text.split(",") if text else []:
        kind, _, periods = item.partition("@")
        kinds.append(kind)
        if periods:
            try:
                caps[kind] = tuple(float(p) for p in periods.split(";"))
            except ValueError:
                pass
    return kinds, caps


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
        # "unencodable" (messages JSON cannot carry: dropped), "thinned" (no subscription would
        # admit them: not sent): the bridge's counters
        self.counters = counters if counters is not None else {}
        for key in ("published", "direct", "unencodable", "thinned"):
            self.counters.setdefault(key, 0)
        #: kind -> {period (s): stamp of the last message that period's rule admitted}
        self._caps: dict[str, dict[float, float | None]] = {}

    def set_caps(self, caps: dict[str, tuple[float, ...]]) -> None:
        """Thin each kind of ``caps`` to what one of its periods (s) admits (module docstring);
        a kind not named, or named with no usable period or more than :data:`MAX_CAPS`, is
        passed on whole. A period kept from the previous caps keeps its state, so a subscription
        that stays is not re-phased by another one coming or going."""
        old = self._caps
        new: dict[str, dict[float, float | None]] = {}
        for kind, periods in caps.items():
            ps = sorted({float(p) for p in periods})
            if ps and len(ps) <= MAX_CAPS and all(math.isfinite(p) and p > 0.0 for p in ps):
                prev = old.get(kind, {})
                new[kind] = {p: prev.get(p) for p in ps}
        self._caps = new  # replaced whole: the publishing threads read it without a lock

    def _admitted(self, msg: Any) -> float | None:
        """The message's stamp if it is to be sent (some subscription admits it; every rule
        that admits it moves on), else None."""
        t = stamp(msg)
        rules = self._caps.get(msg.get("kind")) if isinstance(msg, dict) else None
        if rules is None:
            return t
        passed = False
        for p, last in rules.items():
            if admits(t, last, p):
                rules[p] = t
                passed = True
        return t if passed else None

    def put_nowait(self, msg: Any) -> None:
        t = self._admitted(msg)
        if t is None:
            self.counters["thinned"] += 1
            return
        if (
            not self._items
            and isinstance(msg, dict)
            and msg.get("kind") in DIRECT_KINDS
            and not self._sender.lock.locked()
        ):
            try:
                body = publication(msg, t)
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
