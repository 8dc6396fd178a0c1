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
from collections import deque
from typing import Any

import serial

from host.link_frames import (
    LinkError,
    LinkTimeoutError,
    ProtocolVersionError,
    SegmentError,
    _Collector,
    _FramePlumbing,
    _small_int,
    exchange_floor_s,
)
from host.positions import label, labels
from host.serialport import describe_open_error
from protocol import constants as C
from protocol import messages as M
from protocol.frame import FrameReader

#: cycles :meth:`ChainLink.sync_send` may keep open at once
MAX_IN_FLIGHT = 4


class PendingCycle:
    """A SYNC sent by :meth:`ChainLink.sync_send` whose STATEs are still to be collected."""

    def __init__(self, col: _Collector, cycle: int, expected: int) -> None:
        self.col = col
        self.cycle = cycle  # the cycle number the STATEs echo
        self.expected = expected


class ChainLink(_FramePlumbing):
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
        self._pipelined: dict[int, _Collector] = {}  # seq -> cycle started with sync_send
        self._events: deque[dict] = deque(maxlen=1024)
        self._seq = 0
        self._cycle = 0
        self._expected: int | None = None
        #: the segment of another protocol version the last discovery stopped before (a hot-plug)
        self.version_refusal: ProtocolVersionError | None = None
        #: position -> (length m, spool radius m) from the last discovery: STATE (version 2)
        #: carries servo angles, the host derives the tendon lengths from them
        self._geometry: dict[int, tuple[float | None, float | None]] = {}
        self._error: BaseException | None = None
        self._closed = False
        self._counters = {
            "tx_frames": 0,
            "tx_bytes": 0,
            "rx_bytes": 0,
            "timeouts": 0,
            "unmatched": 0,
            "stale": 0,  # a STATE with the request's seq but another cycle (a late answer)
            "error_replies": 0,
            "bad_payloads": 0,
            "alive": 0,
            "events": 0,
            "events_dropped": 0,
            "boots_before_discovery": 0,  # BOOTs of the lives the first discovery found
        }
        self._discovered = False  # a discovery succeeded on this link
        self._init_timing()
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

    def discover(self, timeout: float = 0.5, *, upto_other_version: bool = False) -> list[dict]:
        """Broadcast DISCOVER; descriptors in chain order (with ``position``).

        Stops as soon as the tip (``downstream_present`` false) and every position before it have
        answered, else after ``timeout`` s with the contiguous answers from position 0: never
        longer than ``timeout``, also on a line measured slow (a caller that may wait as long
        as the descriptors need there asks for :meth:`discover_need_s`; one that must keep the
        segments fed retries: the next try goes on collecting the answers still due). Raises
        :class:`LinkError` if a segment's answer is missing between others (a lost reply).

        A segment speaking another protocol version raises :class:`ProtocolVersionError`; with
        ``upto_other_version`` (a hot-plug: the chain before it stays under control) only when
        it is the first, else the segments before it are returned and the refusal is kept in
        :attr:`version_refusal` (None when every segment speaks this host's version).
        """
        with self._call_lock:
            with self._cond:  # a rediscovery ends every pipelined cycle still open
                self._pipelined.clear()
            col = self._discover_send()  # or the one still collecting on a slow line
            tip: list[int] = []

            def done(c: _Collector) -> bool:
                for pos in list(c.replies):
                    if pos in tip:
                        continue
                    p = self._payload(c.replies[pos])
                    if isinstance(p, dict) and p.get(C.KD_DOWNSTREAM_PRESENT) is False:
                        tip.append(pos)
                if c.errors:  # a segment refused the DISCOVER: nothing passes it
                    return all(i in c.replies for i in range(min(c.errors)))
                return bool(tip) and all(i in c.replies for i in range(min(tip) + 1))

            col = self._discover_wait(col, timeout, done)
            self.version_refusal = None
            try:
                self._refuse_other_versions(col)
            except ProtocolVersionError as exc:
                if not upto_other_version or exc.position == 0:
                    raise
                self.version_refusal = exc  # the chain ends before that segment
                cut = exc.position
                col.replies = {p: f for p, f in col.replies.items() if p < cut}
                tip = [cut - 1]
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
                raise LinkError(f"incomplete discovery: answers from {labels(positions)}")
            if not tip:
                self._counters["timeouts"] += 1
            self._drop_boots_before(col.arrived)  # on the first discovery only
            self._expected = len(descs)
            self._geometry = {
                d["position"]: (d.get("length"), d.get("spool_radius")) for d in descs
            }
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
        return self._states(col, expected, timeout, payload[C.K_CYCLE])

    def _states(
        self, col: _Collector, expected: int, timeout: float, cycle: int
    ) -> list[dict | None]:
        """Wait for the STATEs of ``col``'s cycle; decode them, None where one is missing.

        A STATE is matched to its request by ``seq``, which wraps after 256 requests; it must
        also echo ``cycle`` (docs/protocol.md 8.4), else it is a late answer to an older request
        that had the same seq: counted as ``stale`` and treated as missing, never as this
        cycle's measurement."""
        self._wait(col, timeout, lambda c: all(i in c.replies for i in range(expected)))
        states: list[dict | None] = []
        for pos in range(expected):
            frame = col.replies.get(pos)
            if frame is None:
                states.append(None)
                continue
            try:
                st = M.decode_state(frame.payload, pos)
                if st["cycle"] != cycle:
                    with self._cond:
                        self._counters["stale"] += 1
                        self._late(pos)
                    states.append(None)
                    continue
                length, spool = self._geometry.get(pos, (None, None))
                st["tendon_lengths"] = M.tendon_lengths(length, spool, st["servo_angles"])
                states.append(st)
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

    def sync_send(
        self,
        setpoints: list[tuple[float, float] | None],
        *,
        expected: int | None = None,
        resume: bool = False,
    ) -> PendingCycle:
        """Pipelining (docs/protocol.md 8.4): send one SYNC now and return at once; the STATEs
        are collected later with :meth:`sync_collect`, so the next SYNC may leave before the last
        STATE of this one arrived. Cycles are applied in the order sent: the links are FIFO and
        every segment handles its frames one after the other (tests/chain/test_chain_pipelining.py).
        At most :data:`MAX_IN_FLIGHT` cycles may be open at once.
        """
        with self._call_lock:
            with self._cond:
                if len(self._pipelined) >= MAX_IN_FLIGHT:
                    raise LinkError(f"more than {MAX_IN_FLIGHT} pipelined cycles open")
            cycle = self._next_cycle()
            payload = M.sync_payload(cycle, setpoints, resume=resume)
            n = len(setpoints) if expected is None else expected
            col = self._send(C.FLAG_BCAST, 0, C.T_SYNC, payload, (C.T_STATE,), pipelined=True)
            return PendingCycle(col, cycle, n)

    def sync_abandon(self, pending: PendingCycle) -> None:
        """Close a cycle begun with :meth:`sync_send` without waiting for its STATEs: any that
        still come are counted as unmatched, never returned."""
        with self._cond:
            if self._pipelined.get(pending.col.seq) is pending.col:
                del self._pipelined[pending.col.seq]

    def sync_collect(self, pending: PendingCycle, timeout: float = 0.1) -> list[dict | None]:
        """The STATEs (SI, per position, None if missing) of a cycle begun with :meth:`sync_send`,
        waiting at most ``timeout`` s; the cycle is closed afterwards."""
        return self._states(pending.col, pending.expected, timeout, pending.cycle)

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
                    f"no answer from the segment at {label(position)} "
                    f"within {timeout * 1000:.0f} ms"
                )
            payload_in = self._payload(frame)
            if not isinstance(payload_in, dict) or C.K_VALUE not in payload_in:
                raise LinkError(f"the segment at {label(position)} sent a malformed PARAM_VALUE")
            return payload_in[C.K_VALUE]

    def request(
        self, position: int, mtype: int, payload: dict, reply_type: int, timeout: float = 0.5
    ) -> Any:
        """Send request ``mtype`` to ``position``; the decoded payload of its ``reply_type``
        answer (an ERROR answer raises, as for PARAM_GET). For slow-path messages (CALIBRATE)."""
        with self._call_lock:
            col = self._send(0, self._position(position), mtype, payload, (reply_type,))
            self._wait(col, timeout, lambda c: position in c.replies or position in c.errors)
            if position in col.errors:
                self._raise_error(position, col.errors[position])
            frame = col.replies.get(position)
            if frame is None:
                self._counters["timeouts"] += 1
                raise LinkTimeoutError(
                    f"no answer from the segment at {label(position)} "
                    f"within {timeout * 1000:.0f} ms"
                )
            return self._payload(frame)

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

    @property
    def stats(self) -> dict:
        """Counters: frames ok, crc/framing errors, oversize, timeouts, unmatched, tx/rx."""
        with self._cond:
            out = dict(self._counters)
            r = self._reader.stats()
            out.update(
                frames_ok=r["ok"],
                crc_errors=r["crc_error"],
                framing_errors=r["framing_error"],
                oversize=r["oversize"],
            )
            return out


__all__ = [
    "MAX_IN_FLIGHT",
    "PendingCycle",
    "ChainLink",
    "LinkError",
    "LinkTimeoutError",
    "ProtocolVersionError",
    "SegmentError",
    "exchange_floor_s",
]
