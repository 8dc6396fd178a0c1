"""Frame plumbing of :class:`host.link.ChainLink`: errors, reader thread, reply collection.

The reader thread turns bytes into CRC-checked frames and hands replies to the waiting request
by ``seq`` and source position; ERROR replies become :class:`SegmentError`. Mixed into
``ChainLink``, which owns the port, lock, condition and queues used here; the request API
(discover, sync, params) lives in :mod:`host.link`.
"""

from __future__ import annotations

import time
from typing import Any

import serial

from host import floors, realtime
from host.positions import label
from protocol import constants as C
from protocol.cbor import loads
from protocol.errors import ProtocolError
from protocol.frame import Frame, FrameReader, encode_frame


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


class _FramePlumbing:
    """Reader thread, frame dispatch and request/reply matching (see module docstring)."""

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
            try:
                frames = self._reader.feed(data)
            except Exception:  # noqa: BLE001 - a framer failure costs these bytes, no more
                self._reader = FrameReader()
                with self._cond:
                    self._counters["bad_payloads"] += 1
                continue
            with self._cond:
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
        col = self._collector
        if col is None or frame.seq != col.seq:
            col = self._pipelined.get(frame.seq)  # a cycle started with sync_send
            if col is None:
                self._counters["unmatched"] += 1
                return
        if frame.mtype == C.T_ERROR:
            self._counters["error_replies"] += 1
            col.errors[position] = frame
        elif frame.mtype in col.types:
            col.replies[position] = frame
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
    ) -> _Collector:
        self._check_open()
        with self._cond:
            self._seq = (self._seq + 1) & 0xFF
            while self._seq in self._pipelined:  # never reuse the seq of a cycle still open
                self._seq = (self._seq + 1) & 0xFF
            col = _Collector(self._seq, types)
            if pipelined:
                self._pipelined[col.seq] = col
            else:
                self._collector = col
        wire = encode_frame(flags, hop, mtype, col.seq, payload)
        with self._write_lock:
            try:
                self._ser.write(wire)
            except (serial.SerialException, OSError) as exc:
                raise LinkError(f"write to {self.url!r} failed: {exc}") from exc
        with self._cond:
            self._counters["tx_frames"] += 1
            self._counters["tx_bytes"] += len(wire)
        return col

    def _wait(self, col: _Collector, timeout: float, done) -> None:
        end = time.monotonic() + timeout
        with self._cond:
            while not done(col):
                left = end - time.monotonic()
                if left <= 0 or self._closed or self._error is not None:
                    break
                self._cond.wait(left)
            if self._collector is col:
                self._collector = None
            if self._pipelined.get(col.seq) is col:
                del self._pipelined[col.seq]
        if self._error is not None:
            self._check_open()

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
