"""Host side of the segment chain: frames over a serial port, requests matched to replies.

``ChainLink`` opens any pyserial URL (``/dev/ttyUSB0``, an emulated chain's pty, ``socket://``),
runs one reader thread that turns bytes into CRC-checked frames (``protocol.frame.FrameReader``)
and hands replies to the waiting request by ``seq`` and source position (the hop count of an
upstream frame). Unsolicited EVENT frames go to a queue drained by :meth:`ChainLink.events`.
Requests are serialised by a lock, so the daemon's loop thread and other threads may share one
link. Payloads are built and checked by ``protocol.messages`` (SI on this side, fixed-point ints
on the wire: docs/architecture.md), the same code the protocol tests and vectors prove.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any

import serial

from host import floors
from host.serialport import describe_open_error
from protocol import constants as C
from protocol import messages as M
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
            f"segment {position} speaks protocol version {versions}, this host speaks "
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
        super().__init__(f"segment {position} answered {self.code_name}: {text}")


def exchange_floor_s(n: int, baudrate: int) -> float:
    """Shortest SYNC -> all-STATEs exchange (s) on today's store-and-forward chain of ``n``.

    ``host.floors.store_and_forward_floor_s`` at the largest frames (docs/protocol.md
    "Floors"); the daemon's rate warning uses it.
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


class ChainLink:
    """Client of one segment chain (see module docstring). Close it, or use it as a context manager.

    ``baudrate`` in bit/s; ``url`` anything ``serial.serial_for_url`` opens.
    """

    def __init__(self, url: str, baudrate: int = 921600, *, exclusive: bool = True) -> None:
        try:
            self._ser = serial.serial_for_url(
                url, baudrate=baudrate, timeout=0.02, exclusive=exclusive
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(describe_open_error(url, exc)) from exc
        self.url = url
        self.baudrate = baudrate
        try:
            self._ser.reset_input_buffer()  # stale bytes from before we opened the port
        except (serial.SerialException, OSError):
            pass
        self._reader = FrameReader()
        self._cond = threading.Condition()
        self._call_lock = threading.RLock()
        self._write_lock = threading.Lock()
        self._collector: _Collector | None = None
        self._events: deque[dict] = deque(maxlen=1024)
        self._seq = 0
        self._cycle = 0
        self._expected: int | None = None
        self._error: BaseException | None = None
        self._closed = False
        self._counters = {
            "tx_frames": 0,
            "tx_bytes": 0,
            "rx_bytes": 0,
            "timeouts": 0,
            "unmatched": 0,
            "error_replies": 0,
            "bad_payloads": 0,
            "alive": 0,
            "events": 0,
            "events_dropped": 0,
        }
        self._thread = threading.Thread(target=self._read_loop, name="ucr-link-reader", daemon=True)
        self._thread.start()

    # -- lifecycle ------------------------------------------------------------------------------
    def __enter__(self) -> ChainLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the reader thread and close the port (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self._ser.cancel_read()
        except (AttributeError, serial.SerialException, OSError):
            pass
        self._thread.join(timeout=1.0)
        try:
            self._ser.close()
        except (serial.SerialException, OSError):
            pass
        with self._cond:
            self._cond.notify_all()

    # -- reader thread --------------------------------------------------------------------------
    def _read_loop(self) -> None:
        """Read bytes, cut frames, dispatch them. Any way out of this loop other than close() is
        a link failure (``_error`` set), which the daemon's normal reopen path handles."""
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
        self, flags: int, hop: int, mtype: int, payload: Any, types: tuple[int, ...]
    ) -> _Collector:
        self._check_open()
        with self._cond:
            self._seq = (self._seq + 1) & 0xFF
            col = _Collector(self._seq, types)
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

    def discover(self, timeout: float = 0.5) -> list[dict]:
        """Broadcast DISCOVER; descriptors in chain order (with ``position``).

        Stops as soon as the tip (``downstream_present`` false) and every position before it have
        answered, else after ``timeout`` s with the contiguous answers from position 0. Raises
        :class:`LinkError` if a segment's answer is missing between others (a lost reply).
        """
        with self._call_lock:
            col = self._send(C.FLAG_BCAST, 0, C.T_DISCOVER, {}, (C.T_DESCRIPTOR,))
            tip: list[int] = []

            def done(c: _Collector) -> bool:
                for pos in list(c.replies):
                    if pos in tip:
                        continue
                    p = self._payload(c.replies[pos])
                    if isinstance(p, dict) and p.get(C.KD_DOWNSTREAM_PRESENT) is False:
                        tip.append(pos)
                if c.errors:  # a segment refused the DISCOVER: nothing passes it
                    return True
                return bool(tip) and all(i in c.replies for i in range(min(tip) + 1))

            self._wait(col, timeout, done)
            self._refuse_other_versions(col)
            descs = []
            for pos in sorted(col.replies):
                try:
                    desc = M.decode_descriptor(col.replies[pos].payload)
                except Exception:  # noqa: BLE001 - any malformed descriptor is a bad payload
                    self._counters["bad_payloads"] += 1
                    continue
                desc["position"] = pos
                descs.append(desc)
            if tip:
                descs = [d for d in descs if d["position"] <= min(tip)]
            positions = [d["position"] for d in descs]
            if positions != list(range(len(positions))):
                self._counters["timeouts"] += 1
                raise LinkError(f"incomplete discovery: answers from positions {positions}")
            if not tip:
                self._counters["timeouts"] += 1
            self._expected = len(descs)
            return descs

    def _refuse_other_versions(self, col: _Collector) -> None:
        """Raise :class:`ProtocolVersionError` for the first segment that answered DISCOVER with
        ERROR UNSUPPORTED_VERSION or a DESCRIPTOR announcing a version outside this host's range
        (docs/protocol.md section 10: no common version, the host reports it and does not start).
        """
        found: list[tuple[int, str]] = []
        for pos, frame in col.errors.items():
            p = self._payload(frame)
            if isinstance(p, dict) and p.get(C.KR_CODE) == C.ERR_UNSUPPORTED_VERSION:
                rng = p.get(3)
                ok = isinstance(rng, list) and len(rng) == 2
                ok = ok and all(_small_int(v, 0, 255) for v in rng)
                found.append((pos, f"{rng[0]}..{rng[1]}" if ok else f"ver {frame.ver}"))
        for pos, frame in col.replies.items():
            p = self._payload(frame)
            v = p.get(C.KD_PROTOCOL_VERSION) if isinstance(p, dict) else None
            if _small_int(v, 0, 0xFFFF) and not C.VERSION_MIN <= v <= C.VERSION_MAX:
                found.append((pos, str(v)))
            elif frame.ver != C.VERSION:
                found.append((pos, str(frame.ver)))
        if found:
            raise ProtocolVersionError(*min(found))

    def _cyclic(
        self, mtype: int, payload: dict, expected: int, timeout: float
    ) -> list[dict | None]:
        col = self._send(C.FLAG_BCAST, 0, mtype, payload, (C.T_STATE,))
        self._wait(col, timeout, lambda c: all(i in c.replies for i in range(expected)))
        states: list[dict | None] = []
        for pos in range(expected):
            frame = col.replies.get(pos)
            if frame is None:
                states.append(None)
                continue
            try:
                states.append(M.decode_state(frame.payload, pos))
            except Exception:  # noqa: BLE001 - any malformed STATE is a bad payload
                self._counters["bad_payloads"] += 1
                states.append(None)
        if any(s is None for s in states):
            self._counters["timeouts"] += 1
        return states

    def _next_cycle(self) -> int:
        self._cycle = (self._cycle + 1) % C.TIME_WRAP
        return self._cycle

    def sync(
        self,
        setpoints: list[tuple[float, float]],
        timeout: float = 0.1,
        *,
        expected: int | None = None,
        resume: bool = False,
    ) -> list[dict | None]:
        """Broadcast one SYNC with (kappa 1/m, phi rad) per position; STATE (SI) per position.

        Waits until ``expected`` positions (default: the number of setpoints) answered or
        ``timeout`` s passed; a missing answer is None. ``resume`` ends a HOLD.
        """
        with self._call_lock:
            payload = M.sync_payload(self._next_cycle(), setpoints, resume=resume)
            n = len(setpoints) if expected is None else expected
            return self._cyclic(C.T_SYNC, payload, n, timeout)

    def heartbeat(self, timeout: float = 0.1, *, expected: int | None = None) -> list[dict | None]:
        """Broadcast HEARTBEAT (feeds watchdogs); STATE per position (default: last discovery)."""
        with self._call_lock:
            n = expected if expected is not None else (self._expected or 0)
            return self._cyclic(C.T_HEARTBEAT, {C.K_CYCLE: self._next_cycle()}, n, timeout)

    def hold(self, position: int | None = None) -> None:
        """HOLD every segment (broadcast) or the one at ``position``; no reply is expected."""
        with self._call_lock:
            if position is None:
                self._send(C.FLAG_BCAST, 0, C.T_HOLD, {}, ())
            else:
                self._send(0, self._position(position), C.T_HOLD, {}, ())
            with self._cond:
                self._collector = None

    def clear_fault(self, position: int | None = None, uid: str | None = None) -> None:
        """CLEAR_FAULT to every segment (broadcast) or the one at ``position`` (``uid`` checked
        by the segment); no reply: the next STATE shows the FAULT bit gone."""
        payload: dict[int, Any] = {} if uid is None else {C.K_UID: uid}
        with self._call_lock:
            if position is None:
                self._send(C.FLAG_BCAST, 0, C.T_CLEAR_FAULT, payload, ())
            else:
                self._send(0, self._position(position), C.T_CLEAR_FAULT, payload, ())
            with self._cond:
                self._collector = None

    @staticmethod
    def _position(position: int) -> int:
        if not isinstance(position, int) or not 0 <= position <= 255:
            raise ValueError(f"position must be an int 0..255, got {position!r}")
        return position

    def _addressed(self, position: int, mtype: int, payload: dict, timeout: float) -> Any:
        with self._call_lock:
            col = self._send(0, self._position(position), mtype, payload, (C.T_PARAM_VALUE,))
            self._wait(col, timeout, lambda c: position in c.replies or position in c.errors)
            if position in col.errors:
                self._raise_error(position, col.errors[position])
            frame = col.replies.get(position)
            if frame is None:
                self._counters["timeouts"] += 1
                raise LinkTimeoutError(
                    f"no answer from segment {position} within {timeout * 1000:.0f} ms"
                )
            payload_in = self._payload(frame)
            if not isinstance(payload_in, dict) or C.K_VALUE not in payload_in:
                raise LinkError(f"segment {position} sent a malformed PARAM_VALUE")
            return payload_in[C.K_VALUE]

    def param_get(
        self, position: int, param_id: int, uid: str | None = None, *, timeout: float = 0.2
    ) -> Any:
        """Read parameter ``param_id`` of the segment at ``position`` (verified by ``uid``)."""
        payload: dict[int, Any] = {C.K_PARAM_ID: param_id}
        if uid is not None:
            payload[C.K_UID] = uid
        return self._addressed(position, C.T_PARAM_GET, payload, timeout)

    def param_set(
        self,
        position: int,
        param_id: int,
        value: Any,
        uid: str | None = None,
        *,
        timeout: float = 0.2,
    ) -> Any:
        """Write a parameter; returns the value the segment stored (its echo)."""
        payload: dict[int, Any] = {C.K_PARAM_ID: param_id, C.K_VALUE: value}
        if uid is not None:
            payload[C.K_UID] = uid
        return self._addressed(position, C.T_PARAM_SET, payload, timeout)

    def send_raw(self, data: bytes) -> None:
        """Write raw bytes on the port (tests: garbage, hand-made frames)."""
        self._check_open()
        with self._write_lock:
            self._ser.write(bytes(data))

    @property
    def port_ok(self) -> bool:
        """False once the port failed or was closed (a missing answer alone leaves it True)."""
        return not self._closed and self._error is None

    def events(self) -> list[dict]:
        """Unsolicited events received so far, oldest first (the queue is drained)."""
        with self._cond:
            out = list(self._events)
            self._events.clear()
            return out

    @property
    def stats(self) -> dict:
        """Counters: frames ok, crc/framing errors, oversize, timeouts, unmatched, tx/rx."""
        with self._cond:
            out = dict(self._counters)
            r = self._reader
            out.update(
                frames_ok=r.ok,
                crc_errors=r.crc_error,
                framing_errors=r.framing_error,
                oversize=r.oversize,
            )
            return out


__all__ = [
    "ChainLink",
    "LinkError",
    "LinkTimeoutError",
    "ProtocolVersionError",
    "SegmentError",
    "exchange_floor_s",
]
