"""One direction of an emulated UART link: plug state, baud-rate throttle, latency, corruption.

A :class:`Pipe` is pure bookkeeping with an explicit clock (``now`` in seconds), so it can be unit
tested on plain byte streams; the proxy thread feeds it what it reads from one pty master and
writes what :meth:`Pipe.due` releases to the other.
"""

from __future__ import annotations

import random
import time
from collections import deque

#: Bits on the wire per byte of an 8N1 UART frame (start + 8 data + stop).
BITS_PER_BYTE = 10
#: The largest latency a link takes (s): beyond it the link is better unplugged.
MAX_LATENCY_S = 60.0
#: Throttled bytes are released in chunks lasting at most this long (s), so a long burst arrives
#: progressively as on a real wire, without one timer per byte ...
CHUNK_S = 0.0005
#: ... and of at most this many bytes. A segment's chain UART hands bytes on as they arrive (RX
#: FIFO threshold 1 on an ESP32, docs/firmware.md), which cut-through forwarding relies on; in
#: 0.5 ms chunks a fast link (46 bytes at 921600 baud) delivered a whole STATE frame at once,
#: after its last byte, and made every hop store-and-forward. Eight bytes is 87 µs at 921600
#: baud; smaller pieces cost the proxy thread more wake-ups for little.
CHUNK_MAX_BYTES = 8


class Pipe:
    """Bytes travelling one way on a link.

    Settings (change them any time): ``enabled`` (False = cable pulled: bytes are dropped and
    counted), ``baud`` (None = unthrottled; else each byte takes ``10 / baud`` s, order kept
    ), ``latency_s`` (fixed delay added to every byte), ``corrupt_rate`` (probability that a
    byte is replaced by a different value; seeded RNG, every corrupted byte is counted).

    A baud change re-times the bytes still waiting at once, as a UART changes its divisor
    between bytes: bytes fully on the wire keep their time, the byte being shifted out when the
    change comes completes at the old rate, and every byte after it leaves at the new rate (at
    once, plus the latency, when the throttle is removed).
    """

    def __init__(self, name: str, *, seed: int = 0) -> None:
        self.name = name
        self.enabled = True
        self.baud: int | None = None
        self.latency_s = 0.0
        self.corrupt_rate = 0.0
        self._rng = random.Random(seed)
        #: bytes in flight, in order: (delivery time, bytes, time the first of them started on
        #: the wire); read-only outside this class (the proxy's loop looks at its head without a
        #: call for every pipe on every wake-up)
        self.queue: deque[tuple[float, bytes, float]] = deque()
        self._busy_until = 0.0
        self.bytes_in = 0
        self.bytes_out = 0
        self.dropped = 0
        self.corrupted = 0

    # -- settings -------------------------------------------------------------------------------
    def configure(
        self,
        *,
        baud: int | None | bool = False,
        latency_s: float | None = None,
        corrupt_rate: float | None = None,
        seed: int | None = None,
        now: float | None = None,
    ) -> None:
        """Change settings; arguments left at their default keep the current value.

        ``baud=None`` removes the throttle (``False`` means "unchanged"). ``now``: the time of
        the change on the pipe's clock (default ``time.monotonic()``, the proxy's clock); a baud
        change re-times the bytes waiting from there.
        """
        if baud is not False:
            if baud is not None and (not isinstance(baud, int) or baud <= 0):
                raise ValueError(f"baud must be a positive integer or None, got {baud!r}")
            if latency_s is not None and not 0.0 <= latency_s <= MAX_LATENCY_S:
                raise ValueError(
                    f"latency must be within [0, {MAX_LATENCY_S:g}] s, got {latency_s!r}"
                )
            if baud != self.baud:
                self._rebaud(baud, time.monotonic() if now is None else now)
        if latency_s is not None:
            if not 0.0 <= latency_s <= MAX_LATENCY_S:
                raise ValueError(
                    f"latency must be within [0, {MAX_LATENCY_S:g}] s, got {latency_s!r}"
                )
            # bytes in flight follow the new setting (else `latency 1 1e9` then `latency 1 0`
            # left the link dead behind bytes still due in 30 years)
            shift = float(latency_s) - self.latency_s
            if shift and self.queue:
                self.queue = deque((t + shift, d, w) for t, d, w in self.queue)
            self.latency_s = float(latency_s)
        if corrupt_rate is not None:
            if not 0.0 <= corrupt_rate <= 1.0:
                raise ValueError(f"corrupt rate must be within [0, 1], got {corrupt_rate!r}")
            self.corrupt_rate = float(corrupt_rate)
        if seed is not None:
            self._rng.seed(seed)

    def _rebaud(self, baud: int | None, now: float) -> None:
        """Switch the throttle to ``baud`` at ``now``: bytes that left the wire (only the latency
        is left) and the byte being shifted out keep their time; the rest is sent again at the
        new rate from the end of that byte."""
        old = self.baud
        self.baud = baud
        if old is None:
            return  # unthrottled bytes were all on the wire at once: nothing waits to be sent
        byte_s = BITS_PER_BYTE / old
        kept: deque[tuple[float, bytes, float]] = deque()
        rest = bytearray()
        wire_free = now
        for t, d, w in self.queue:
            if rest:
                rest += d
                continue
            if w + len(d) * byte_s <= now + 1e-12:  # all of it on the wire already
                kept.append((t, d, w))
                wire_free = max(wire_free, w + len(d) * byte_s)
                continue
            # the first byte not yet fully sent: it completes at the old rate if it started
            k = int((now - w) / byte_s) + 1 if now > w else 0
            if k:
                end = w + k * byte_s
                kept.append((end + self.latency_s, d[:k], w))
                wire_free = end
            rest += d[k:]
        self.queue = kept
        self._busy_until = wire_free
        if rest:
            self._schedule(bytes(rest), wire_free)

    def set_enabled(self, enabled: bool) -> None:
        """Plug (True) or pull (False) the cable; pulling loses the bytes still in flight."""
        self.enabled = enabled
        if not enabled:
            self.dropped += sum(len(d) for _, d, _ in self.queue)
            self.queue.clear()
            self._busy_until = 0.0

    # -- data -----------------------------------------------------------------------------------
    def feed(self, data: bytes, now: float) -> None:
        """Bytes that entered the wire at time ``now`` (s)."""
        self.bytes_in += len(data)
        if not self.enabled:
            self.dropped += len(data)
            return
        if self.corrupt_rate > 0.0:
            data = self._corrupt(data)
        self._schedule(data, now)

    def _schedule(self, data: bytes, now: float) -> None:
        """Queue ``data`` for the wire from ``now`` on at the current rate."""
        if self.baud is None:
            self.queue.append((now + self.latency_s, bytes(data), now))
            return
        byte_s = BITS_PER_BYTE / self.baud
        chunk = max(1, min(CHUNK_MAX_BYTES, int(CHUNK_S / byte_s)))
        start = max(now, self._busy_until)
        for i in range(0, len(data), chunk):
            piece = bytes(data[i : i + chunk])
            w = start
            start += len(piece) * byte_s
            self.queue.append((start + self.latency_s, piece, w))
        self._busy_until = start

    def _corrupt(self, data: bytes) -> bytes:
        out = bytearray(data)
        rng = self._rng
        rate = self.corrupt_rate
        for i in range(len(out)):
            if rng.random() < rate:
                out[i] ^= rng.randrange(1, 256)  # never 0: the byte really changes
                self.corrupted += 1
        return bytes(out)

    def due(self, now: float) -> bytes:
        """Bytes whose delivery time has come, in order."""
        if not self.queue or self.queue[0][0] > now:
            return b""
        parts = []
        while self.queue and self.queue[0][0] <= now:
            parts.append(self.queue.popleft()[1])
        out = b"".join(parts)
        self.bytes_out += len(out)
        return out

    def next_deadline(self) -> float | None:
        """Time (s) of the next release, None when nothing is in flight."""
        return self.queue[0][0] if self.queue else None

    def in_flight(self) -> int:
        return sum(len(d) for _, d, _ in self.queue)

    def stats(self) -> dict:
        return {
            "enabled": self.enabled,
            "baud": self.baud,
            "latency_s": self.latency_s,
            "corrupt_rate": self.corrupt_rate,
            "bytes_in": self.bytes_in,
            "bytes_out": self.bytes_out,
            "dropped": self.dropped,
            "corrupted": self.corrupted,
            "in_flight": self.in_flight(),
        }
