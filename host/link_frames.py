"""Frame plumbing of :class:`host.link.ChainLink`: errors, reader thread, reply collection.

The reader thread turns bytes into CRC-checked frames and hands replies to the waiting request
by ``seq`` and source position; ERROR replies become :class:`SegmentError`. Mixed into
``ChainLink``, which owns the port, lock, condition and queues used here; the request API
(discover, sync, params) lives in :mod:`host.link`.

One piece: the reader thread, the dispatch and the request waits (discovery resends, a slow
line's open DISCOVER) share the link's lock, condition and collectors; split, each part would
reach into the other's state.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

import serial

from host import floors, realtime
from host.positions import label
from protocol import constants as C
from protocol.cbor import loads
from protocol.errors import ProtocolError
from protocol.frame import Frame, FrameReader, encode_frame

#: a DISCOVER with not a byte back this long is sent again (and again, s)
DISCOVER_RESEND_S = 0.05
#: a DESCRIPTOR frame on the wire, bytes (upper estimate)
DESCRIPTOR_BYTES = 200
#: a line measured below this share of the configured baud rate is slow (:meth:`discover_need_s`)
SLOW_LINE_SHARE = 0.5
#: recent STATE arrival times kept per position (s after their request left)
ARRIVALS_KEPT = 16
#: an arrival later than this after its request is not timed (its seq may have wrapped)
ARRIVAL_MAX_S = 2.0
#: reads closer than this, the later one continuing a frame, measure the line's byte rate (s)
STREAM_GAP_S = 0.02
#: stream samples kept for the line's byte rate, and for how long (s)
RATE_SAMPLES = 32
RATE_KEPT_S = 2.0
#: frames per position kept for its rate (:meth:`_FramePlumbing.line_rate_by_position`)
POSITION_FRAMES = 8


class LinkError(OSError):
    """The chain link failed: port cannot be opened, vanished, or a segment answered ERROR."""


class LinkTimeoutError(LinkError, TimeoutError):
    """No (complete) answer within the timeout."""


class ProtocolVersionError(LinkError):
    """A segment speaks a protocol version this host does not: it must be reflashed."""

    def __init__(self, position: int, versions: str) -> None:
        self.position = position
        super().__init__(
            f"the segment at {label(position)} speaks protocol version {versions}, "
            "this host speaks "
            f"{C.VERSION_MIN}..{C.VERSION_MAX}: reflash it with `ucr flash` "
            "(docs/protocol.md section 10)"
        )


class SegmentError(LinkError):
    """A segment answered a request with an ERROR frame (``code``, ``code_name``, ``text``)."""

    def __init__(self, position: int, code: int, offending_type: int | None, text: str) -> None:
        self.position = position
        self.code = code
        self.code_name = C.ERROR_NAMES.get(code, f"error {code}")
        self.offending_type = offending_type
        self.text = text
        super().__init__(f"the segment at {label(position)} answered {self.code_name}: {text}")


def exchange_floor_s(n: int, baudrate: int) -> float:
    """The daemon's bound of one SYNC -> all-STATEs exchange (s) on a chain of ``n``.

    ``host.floors.store_and_forward_floor_s`` at the largest frames (docs/protocol.md
    "Floors"), although protocol-v2 segments relay cut-through: the cut-through floor leaves
    out every segment's processing time, which dominates on a real chain (docs/daemon.md "Rate
    versus baud rate"); the daemon's rate warning uses it.
    """
    return floors.store_and_forward_floor_s(n, baudrate)


def _small_int(value: Any, lo: int, hi: int) -> bool:
    """An int (not a bool) within [lo, hi]: what a CBOR field from a segment must be to be used."""
    return isinstance(value, int) and not isinstance(value, bool) and lo <= value <= hi


def _shown(value: Any) -> str:
    """A short, safe rendering of an untrusted value for a message."""
    try:
        text = repr(value)
    except Exception:  # noqa: BLE001 - e.g. too deep
        text = f"<{type(value).__name__}>"
    return text[:80]


class _Collector:
    """Replies to one request: by position, of the accepted types; ERRORs kept aside."""

    def __init__(self, seq: int, types: tuple[int, ...]) -> None:
        self.seq = seq
        self.types = types
        self.replies: dict[int, Frame] = {}
        self.errors: dict[int, Frame] = {}
        self.arrived: dict[int, float] = {}  # position -> when its reply was dispatched (s)
        self.sent = 0.0  # when the request left (monotonic s)


class _FramePlumbing:
    """Reader thread, frame dispatch and request/reply matching (see module docstring).

    Link timing, for the link health (host/link_health.py): the time each request left
    (``_sent_at`` by seq), each position's recent STATE arrival times after their request,
    matched or late (:meth:`arrival_offsets`), STATEs per position that came too late to be
    used (:meth:`late_by_position`), the byte rate the host's port receives at while bytes
    stream in (:meth:`line_rate_bps`) and how late the last wait for replies woke
    (``wait_overrun_s``). ``ChainLink.__init__`` calls :meth:`_init_timing`.
    """

    def _init_timing(self) -> None:
        self._sent_at = [0.0] * 256  # seq -> when that request left (monotonic s)
        # how long after its deadline the last wait for replies returned (s; 0 when they all
        # came in time): a wait that woke late was held up in this process (link health)
        self.wait_overrun_s = 0.0
        self._late_pos: list[int] = []  # per position: STATEs too late for their exchange
        self._arrivals: dict[int, deque[float]] = {}  # position -> recent arrival offsets (s)
        self._rx_t = 0.0  # when the bytes being dispatched were read
        self._rx_last: float | None = None  # when the previous read returned
        self._rate_samples: deque[tuple[int, float, float]] = deque(maxlen=RATE_SAMPLES)
        # the same samples by the position whose frame they carried: those of the frame being
        # read wait here until it completes (line_rate_by_position)
        self._frame_samples: list[tuple[int, float, float]] = []
        self._pos_samples: dict[int, deque[tuple[int, float, float]]] = {}
        self._discover_open: _Collector | None = None  # a DISCOVER on a slow line, answers due

    def _late(self, position: int) -> None:
        """Count a STATE from ``position`` that came after its exchange ended (lock held)."""
        late = self._late_pos
        if position >= len(late):
            late.extend([0] * (position + 1 - len(late)))
        late[position] += 1

    def late_by_position(self) -> list[int]:
        """Per position (0-based): STATEs that came too late to be used (unmatched: their
        exchange had ended; stale: they echoed an older cycle). A slow link's replies arrive
        late; a corrupting link's never arrive at all."""
        with self._cond:
            return list(self._late_pos)

    def arrival_offsets(self) -> list[float | None]:
        """Per position (0-based): the median of its recent STATE arrival times after their
        request left (s), late ones included; None for a position not heard from."""
        with self._cond:
            out: list[float | None] = []
            for pos in range(max(self._arrivals, default=-1) + 1):
                got = sorted(self._arrivals.get(pos, ()))
                out.append(got[len(got) // 2] if got else None)
            return out

    def line_rate_bps(self) -> float | None:
        """The rate bytes reach the host's port at while they stream in (bit/s, 10 bits a byte):
        the median over recent reads that continued a frame begun by a read within
        STREAM_GAP_S before, in the last RATE_KEPT_S. None with fewer than 8 (a fast line
        delivers frames whole). A throttled link (a slower baud rate somewhere) shows here as
        a low rate; an idle line never lowers it (gaps between frames are left out)."""
        with self._cond:
            since = time.monotonic() - RATE_KEPT_S
            samples = [n / dt for n, dt, t in self._rate_samples if dt > 0 and t > since]
        if len(samples) < 8:
            return None
        samples.sort()
        return samples[len(samples) // 2] * 10.0

    def _samples_of(self, frame: Frame) -> None:
        """The stream samples read since the last frame completed carried ``frame`` (the first
        one this read completed): kept by its source position if it came up the chain (lock
        held)."""
        got, self._frame_samples = self._frame_samples, []
        if got and frame.flags & C.FLAG_UP and not frame.flags & C.FLAG_LOCAL:
            # one figure per frame: its streamed bytes over their time (the reads of one frame
            # alternate between a byte that waited and a burst: each alone says little)
            kept = self._pos_samples.setdefault(frame.hop, deque(maxlen=POSITION_FRAMES))
            kept.append((sum(s[0] for s in got), sum(s[1] for s in got), got[-1][2]))

    def line_rate_by_position(self, at_least: int = 5) -> list[float | None]:
        """Per position (0-based): the rate its frames reach the host's port at (bit/s, the
        median over its last POSITION_FRAMES frames read in several parts, in the last
        RATE_KEPT_S, of each one's bytes over their time); None with fewer than ``at_least``.
        A frame crosses every link between its segment and the host and the segments relay its
        bytes as they come (cut-through), so it arrives at the rate of the slowest of them: the
        first position whose frames arrive slowly names the slow link. A read the host made late
        makes one frame look slow; the median over several does not (unlike the arrival times
        after the request, which a busy host shifts)."""
        with self._cond:
            since = time.monotonic() - RATE_KEPT_S
            out: list[float | None] = []
            for pos in range(max(self._pos_samples, default=-1) + 1):
                got = sorted(
                    n / dt for n, dt, t in self._pos_samples.get(pos, ()) if dt > 0 and t > since
                )
                out.append(got[len(got) // 2] * 10.0 if len(got) >= at_least else None)
            return out

    def _timed(self, frame: Frame, position: int) -> None:
        """Keep the arrival time of a STATE after its request (lock held)."""
        off = self._rx_t - self._sent_at[frame.seq & 0xFF]
        if 0.0 <= off < ARRIVAL_MAX_S:
            got = self._arrivals.get(position)
            if got is None:
                got = self._arrivals[position] = deque(maxlen=ARRIVALS_KEPT)
            got.append(off)

    # -- reader thread --------------------------------------------------------------------------
    def _read_loop(self) -> None:
        """Read bytes, cut frames, dispatch them. Any way out of this loop other than close() is
        a link failure (``_error`` set), which the daemon's normal reopen path handles."""
        realtime.enter("link reader")  # the loop waits on this thread's STATEs
        try:
            self._read_frames()
        except BaseException as exc:  # noqa: BLE001 - the reader must never die silently
            if not self._closed and self._error is None:
                self._error = exc
        finally:
            if not self._closed and self._error is None:
                self._error = LinkError("link reader stopped unexpectedly")
            with self._cond:
                self._cond.notify_all()

    def _read_frames(self) -> None:
        ser = self._ser
        while not self._closed:
            try:
                data = ser.read(ser.in_waiting or 1)
            except (serial.SerialException, OSError, TypeError) as exc:
                if not self._closed:
                    self._error = exc
                return
            if not data:
                continue
            t = time.monotonic()
            last, self._rx_last, self._rx_t = self._rx_last, t, t
            # mid-frame (bytes of a frame already in): these came at the line's rate
            streaming = last is not None and t - last < STREAM_GAP_S and self._reader.st[0] > 0
            bad = self._reader.errors()
            try:
                frames = self._reader.feed(data)
            except Exception:  # noqa: BLE001 - a framer failure costs these bytes, no more
                self._reader = FrameReader()
                with self._cond:
                    self._counters["bad_payloads"] += 1
                    self._frame_samples.clear()
                continue
            with self._cond:  # line_rate_bps reads the samples under this lock
                if streaming:
                    self._rate_samples.append((len(data), t - last, t))
                    self._frame_samples.append((len(data), t - last, t))
                if self._reader.errors() != bad:
                    self._frame_samples.clear()  # a frame that failed its check carried them
                elif frames:
                    self._samples_of(frames[0])
                self._counters["rx_bytes"] += len(data)
                for frame in frames:
                    try:
                        self._dispatch(frame)
                    except Exception:  # noqa: BLE001 - total: one bad frame is dropped, counted
                        self._counters["bad_payloads"] += 1
                if frames:
                    self._cond.notify_all()

    def _dispatch(self, frame: Frame) -> None:
        """Route one good frame (called with the condition held)."""
        if not frame.flags & C.FLAG_UP:
            self._counters["unmatched"] += 1  # a downstream frame reaching the host: echo/loop
            return
        if frame.flags & C.FLAG_LOCAL:
            if frame.mtype == C.T_ALIVE:
                self._counters["alive"] += 1
            else:
                self._counters["unmatched"] += 1
            return
        position = frame.hop
        if frame.mtype == C.T_EVENT:
            self._on_event(frame, position)
            return
        if frame.mtype == C.T_STATE:
            self._timed(frame, position)
        col = self._collector
        if col is None or frame.seq != col.seq:
            col = self._pipelined.get(frame.seq)  # a cycle started with sync_send
            if col is None and frame.seq == getattr(self._discover_open, "seq", -1):
                col = self._discover_open  # a DISCOVER on a slow line: answers still due
            if col is None:
                self._counters["unmatched"] += 1
                if frame.mtype == C.T_STATE:
                    self._late(position)
                return
        if frame.mtype == C.T_ERROR:
            self._counters["error_replies"] += 1
            col.errors[position] = frame
        elif frame.mtype in col.types:
            col.replies[position] = frame
            col.arrived[position] = time.monotonic()  # after every event dispatched before it
        else:
            self._counters["unmatched"] += 1

    def _on_event(self, frame: Frame, position: int) -> None:
        """Queue an EVENT whose fields have the documented types; count anything else as bad."""
        try:
            payload = loads(frame.payload) if frame.payload else {}
        except ProtocolError:
            payload = None
        code = payload.get(C.KE_CODE) if isinstance(payload, dict) else None
        if not _small_int(code, 0, 0xFFFF):
            self._counters["bad_payloads"] += 1
            return
        detail = payload.get(C.KE_DETAIL)
        t_ms = payload.get(C.KE_T_MS)
        if len(self._events) == self._events.maxlen:
            self._counters["events_dropped"] += 1
        self._counters["events"] += 1
        ev = {
            "position": position,
            "code": code,
            "name": C.EVENT_NAMES.get(code, f"EVENT_{code}"),
            # detail and t_ms are ints on the wire; anything else is shown as absent
            "detail": detail if _small_int(detail, -(2**31), 2**32) else None,
            "t_ms": t_ms if _small_int(t_ms, 0, 2**32) else None,
            "t": time.monotonic(),
        }
        text = payload.get(C.KE_TEXT)
        if isinstance(text, str):
            ev["text"] = text[:200]  # e.g. a FAULT's reason (untrusted: bounded)
        self._events.append(ev)

    def events(self) -> list[dict]:
        """Unsolicited events received so far, oldest first (the queue is drained)."""
        with self._cond:
            out = list(self._events)
            self._events.clear()
            return out

    def _drop_boots_before(self, arrived: dict[int, float]) -> None:
        """After the first discovery on this link (``arrived``: position -> when its DESCRIPTOR
        was dispatched): drop each position's BOOT received before its DESCRIPTOR. That BOOT
        began the life the descriptor describes (a segment sends its BOOT before any reply, and
        relays keep each position's order), so it is no restart after the discovery; taken for
        one, it was a topology change that aborted the first goal. Later discoveries drop
        nothing: a known segment's BOOT then tells the daemon it restarted."""
        with self._cond:
            if self._discovered or not arrived:
                return  # (a discovery that found nobody leaves the first one still to come)
            self._discovered = True
            kept = [
                e
                for e in self._events
                if not (e["name"] == "BOOT" and e["t"] <= arrived.get(e["position"], -1.0))
            ]
            self._counters["boots_before_discovery"] += len(self._events) - len(kept)
            self._events.clear()
            self._events.extend(kept)

    # -- requests -------------------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise LinkError("link is closed")
        if self._error is not None:
            raise LinkError(f"chain port {self.url!r} failed: {self._error}") from self._error

    def _send(
        self,
        flags: int,
        hop: int,
        mtype: int,
        payload: Any,
        types: tuple[int, ...],
        pipelined: bool = False,
        lead: bool = False,
    ) -> _Collector:
        """Send one request; its collector. ``lead``: a 0x00 first, which ends any partial
        frame segment_1's receiver still holds (garbage from a corrupting or cut first link
        would otherwise swallow this frame: a receiver resynchronises on 0x00 only). A relay
        drops an idle 0x00, so a receiver further down ends its garbage only with the frame
        that garbage swallows: the next resend passes it."""
        self._check_open()
        with self._cond:
            self._seq = (self._seq + 1) & 0xFF
            while self._seq in self._pipelined:  # never reuse the seq of a cycle still open
                self._seq = (self._seq + 1) & 0xFF
            col = _Collector(self._seq, types)
            self._sent_at[col.seq] = col.sent = time.monotonic()
            if pipelined:
                self._pipelined[col.seq] = col
            else:
                self._collector = col
        wire = encode_frame(flags, hop, mtype, col.seq, payload)
        if lead:
            wire = b"\x00" + wire
        with self._write_lock:
            try:
                self._ser.write(wire)
            except (serial.SerialException, OSError) as exc:
                raise LinkError(f"write to {self.url!r} failed: {exc}") from exc
        with self._cond:
            self._counters["tx_frames"] += 1
            self._counters["tx_bytes"] += len(wire)
        return col

    def _wait(self, col: _Collector, timeout: float, done, close: bool = True) -> None:
        """Wait until ``done(col)`` or ``timeout`` s; then close the request (unless
        ``close`` is false: a DISCOVER may be sent again and keep collecting)."""
        end = time.monotonic() + timeout
        with self._cond:
            while not done(col):
                left = end - time.monotonic()
                if left <= 0 or self._closed or self._error is not None:
                    break
                self._cond.wait(left)
            self.wait_overrun_s = max(time.monotonic() - end, 0.0)
            if close and self._collector is col:
                self._collector = None
            if close and self._pipelined.get(col.seq) is col:
                del self._pipelined[col.seq]
        if self._error is not None:
            self._check_open()

    def _discover_wait(self, col: _Collector, timeout: float, done) -> _Collector:
        """Wait for the DISCOVER answers, never longer than ``timeout``; while none came, send
        the DISCOVER again (each with a leading 0x00): a request lost on a corrupting or briefly
        cut link is not waited for until the timeout — a link clean again answers within one
        resend. A resend goes out no sooner than :meth:`discover_resend_s` after the last one
        (one descriptor's time at the configured baud rate and a margin: a healthy chain at a
        low baud rate answers once) and never while bytes are arriving (a frame under way is
        an answer coming). Answers to any of these DISCOVERs count (the same collector: a
        segment answers each with the same descriptor). On a line measured slower than the
        configured baud rate (:meth:`discover_need_s` > 0) nothing is resent (the answers would
        only queue behind the first ones); the caller's ``timeout`` still bounds the wait: a
        caller that can wait longer asks for ``discover_need_s()``."""
        end = time.monotonic() + timeout
        need = self.discover_need_s()
        step = self.discover_resend_s() if need == 0.0 else timeout
        aliases: list[int] = []
        complete = False
        try:
            while True:
                left = end - time.monotonic()
                self._wait(col, min(step, max(left, 0.0)), done, close=False)
                if done(col) or time.monotonic() >= end or col.replies or col.errors:
                    if not done(col):
                        self._wait(col, max(end - time.monotonic(), 0.0), done, close=False)
                    complete = done(col)
                    return col
                if self._arriving(step):
                    continue  # an answer under way: wait for it, do not ask again
                with self._cond:  # alias the old seq to this collector, then send again
                    aliases.append(col.seq)
                    self._pipelined[col.seq] = col
                again = self._send(C.FLAG_BCAST, 0, C.T_DISCOVER, {}, (C.T_DESCRIPTOR,), lead=True)
                with self._cond:
                    again.replies, again.errors = col.replies, col.errors
                    again.arrived = col.arrived  # (when each answer came: _drop_boots_before)
                    for seq in aliases:
                        self._pipelined[seq] = again
                col = again
        finally:
            with self._cond:
                for seq in aliases:
                    self._pipelined.pop(seq, None)
                if self._collector is col:
                    self._collector = None
                self._discover_open = None
                if need > 0.0 and not complete and self._error is None:
                    self._discover_open = col  # its answers are due: keep collecting

    def _discover_send(self) -> _Collector:
        """Send a DISCOVER (a 0x00 first) — unless one sent on a line measured slow, whose
        answers are still due (within :meth:`discover_need_s` of it), is open: its collector
        goes on instead. A caller whose timeout is shorter than the descriptors need there
        collects them over its tries, and no second set queues behind the first."""
        need = self.discover_need_s()
        with self._cond:
            col, self._discover_open = self._discover_open, None
            if col is not None and time.monotonic() - col.sent < need:
                self._collector = col
                return col
        return self._send(C.FLAG_BCAST, 0, C.T_DISCOVER, {}, (C.T_DESCRIPTOR,), lead=True)

    def discover_resend_s(self) -> float:
        """How long a DISCOVER is given before it is sent again (s): DISCOVER_RESEND_S past
        one descriptor's time on the wire at the configured baud rate (with half again for
        the segment's turnaround) — below ~30 kbaud one descriptor alone outlasts 50 ms."""
        return 1.5 * DESCRIPTOR_BYTES * 10.0 / self.baudrate + DISCOVER_RESEND_S

    def _arriving(self, within: float) -> bool:
        """Bytes are arriving: a read returned within STREAM_GAP_S, or within ``within`` s
        with a frame partly in (garbage older than that, never ended, is no answer)."""
        with self._cond:
            last = self._rx_last
        if last is None:
            return False
        ago = time.monotonic() - last
        return ago < STREAM_GAP_S or (ago < within and self._reader.st[0] > 0)

    def discover_need_s(self) -> float:
        """The time a DISCOVER's answers need on a line measured slower than the configured
        baud rate (:meth:`line_rate_bps`): every descriptor of the last discovery and one more
        at the measured rate, twice over (s); 0 while the line keeps its configured rate."""
        rate = self.line_rate_bps()
        if rate is None or rate >= SLOW_LINE_SHARE * self.baudrate:
            return 0.0
        n = (self._expected or 1) + 1
        return 2.0 * n * DESCRIPTOR_BYTES * 10.0 / rate + 0.05

    def _payload(self, frame: Frame) -> Any:
        try:
            return loads(frame.payload) if frame.payload else {}
        except Exception:  # noqa: BLE001 - untrusted bytes: any decoder failure is a bad payload
            self._counters["bad_payloads"] += 1
            return None

    def _raise_error(self, position: int, frame: Frame) -> None:
        """Raise :class:`SegmentError` from an ERROR frame, whatever its payload holds."""
        payload = self._payload(frame)
        if not isinstance(payload, dict):
            self._counters["bad_payloads"] += 1
            raise SegmentError(position, 0, None, f"malformed ERROR payload {_shown(payload)}")
        code = payload.get(C.KR_CODE, 0)
        mtype = payload.get(C.KR_TYPE)
        text = payload.get(C.KR_TEXT, "")
        raise SegmentError(
            position,
            code if _small_int(code, 0, 0xFFFF) else 0,
            mtype if _small_int(mtype, 0, 0xFF) else None,
            text[:200] if isinstance(text, str) else _shown(text),
        )
