"""Frames: ``COBS(header + payload + 00 + crc16) 0x00``: building, incremental reading, forwarding.

Version 2 puts a 0x00 pad between the payload and the CRC: the CRC's COBS encoding is then always
the last three wire bytes, so a cut-through forwarder (``protocol.relay``) can pass a frame on as it
arrives and replace only those (and the hop byte). Version-1 frames (no pad) are still read, so a
segment or host can answer/refuse them.

Device hot path (no allocation in steady state): ``seal`` writes header + CRC around a payload
already placed at ``raw[5:]``, ``wire_into`` COBS-encodes it with the delimiter, ``forward_into``
re-frames a received frame with a new hop byte, and ``FrameReader.scan`` consumes received bytes
and exposes one checked frame at a time in preallocated buffers.
Host conveniences (allocate): ``encode_frame``, ``decode_frame``, ``FrameReader.feed``, ``Frame``.
"""

from array import array

from protocol import cobs
from protocol.cbor import dumps
from protocol.constants import (
    CRC_LEN,
    HEADER_LEN,
    LEGACY_VERSION,
    MAX_FRAME,
    MIN_FRAME,
    TRAILER_LEN,
    VERSION,
)
from protocol.crc import _TABLE, crc16
from protocol.errors import MalformedError

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


# --------------------------------------------------------------------------------------------
# building (no allocation)
# --------------------------------------------------------------------------------------------
def _trailer(ver):
    """Bytes after the payload: pad + CRC (3), or the CRC alone in version 1 (2)."""
    return CRC_LEN if ver == LEGACY_VERSION else TRAILER_LEN


def seal(raw, payload_end, flags, hop, mtype, seq, ver=VERSION):
    """Write the header into ``raw[0:5]`` and the pad + CRC after ``raw[5:payload_end]``.

    The payload must already be at ``raw[HEADER_LEN:payload_end]``. Returns the raw frame length
    (``payload_end + 3``; version 1: + 2, no pad). Raises ValueError when it would exceed
    MAX_FRAME or ``raw``.
    """
    n = payload_end + _trailer(ver)
    if payload_end < HEADER_LEN or n > MAX_FRAME or n > len(raw):
        raise ValueError("frame too long")
    raw[0] = ver
    raw[1] = flags
    raw[2] = hop & 0xFF
    raw[3] = mtype
    raw[4] = seq & 0xFF
    p = n - CRC_LEN
    if p != payload_end:
        raw[payload_end] = 0  # the pad
    c = crc16(raw, 0, p)
    raw[p] = c >> 8
    raw[p + 1] = c & 0xFF
    return n


def wire_into(raw, raw_len, out, off=0):
    """COBS-encode ``raw[0:raw_len]`` into ``out`` at ``off`` and append 0x00; return end offset.

    ``out`` needs ``raw_len + 2`` bytes from ``off``.
    """
    end = cobs.encode_into(raw, 0, raw_len, out, off)
    out[end] = 0
    return end + 1


def forward_into(raw, raw_len, hop, out, off=0):
    """Re-frame a received raw frame with hop byte ``hop`` (CRC recomputed) into ``out``.

    ``raw`` is modified in place (hop and CRC bytes). Returns the end offset in ``out``.
    """
    p = raw_len - CRC_LEN
    raw[2] = hop & 0xFF
    c = crc16(raw, 0, p)
    raw[p] = c >> 8
    raw[p + 1] = c & 0xFF
    return wire_into(raw, raw_len, out, off)


def frame_into(raw, payload_end, flags, hop, mtype, seq, out, off=0, ver=VERSION):
    """``seal`` + ``wire_into`` in one call: return the end offset of the wire bytes in ``out``."""
    n = seal(raw, payload_end, flags, hop, mtype, seq, ver)
    return wire_into(raw, n, out, off)


# --------------------------------------------------------------------------------------------
# host conveniences
# --------------------------------------------------------------------------------------------
class Frame:
    """One received frame: header fields and the payload bytes (CBOR, possibly empty)."""

    def __init__(self, ver, flags, hop, mtype, seq, payload):
        self.ver = ver
        self.flags = flags
        self.hop = hop
        self.mtype = mtype
        self.seq = seq
        self.payload = payload

    def __eq__(self, other):
        return (
            isinstance(other, Frame)
            and self.ver == other.ver
            and self.flags == other.flags
            and self.hop == other.hop
            and self.mtype == other.mtype
            and self.seq == other.seq
            and bytes(self.payload) == bytes(other.payload)
        )

    def __repr__(self):
        return "Frame(ver=%d, flags=0x%02x, hop=%d, mtype=0x%02x, seq=%d, payload=%s)" % (
            self.ver,
            self.flags,
            self.hop,
            self.mtype,
            self.seq,
            bytes(self.payload).hex(),
        )

    def raw(self):
        """The raw frame bytes (header + payload + CRC)."""
        buf = bytearray(HEADER_LEN + len(self.payload) + _trailer(self.ver))
        buf[HEADER_LEN : HEADER_LEN + len(self.payload)] = self.payload
        seal(
            buf,
            HEADER_LEN + len(self.payload),
            self.flags,
            self.hop,
            self.mtype,
            self.seq,
            self.ver,
        )
        return bytes(buf)


def encode_frame(flags, hop, mtype, seq, payload_obj=None, ver=VERSION):
    """Wire bytes ``COBS(raw) 0x00`` of one frame.

    ``payload_obj``: a dict/list (CBOR-encoded here), bytes (an already encoded payload) or None
    (empty payload). Raises ValueError if a header field is out of range or the frame is too long.
    """
    for name, v in (("flags", flags), ("hop", hop), ("mtype", mtype), ("seq", seq), ("ver", ver)):
        if not isinstance(v, int) or not 0 <= v <= 255:
            raise ValueError("header field %s must be an int 0..255, got %r" % (name, v))
    if payload_obj is None:
        payload = b""
    elif isinstance(payload_obj, (bytes, bytearray, memoryview)):
        payload = bytes(payload_obj)
    else:
        payload = dumps(payload_obj)
    n = HEADER_LEN + len(payload)
    t = _trailer(ver)
    if n + t > MAX_FRAME:
        raise ValueError(
            "payload of %d bytes exceeds the %d-byte frame" % (len(payload), MAX_FRAME)
        )
    raw = bytearray(n + t)
    raw[HEADER_LEN:n] = payload
    seal(raw, n, flags, hop, mtype, seq, ver)
    out = bytearray(n + t + 2)
    end = wire_into(raw, n + t, out, 0)
    return bytes(out[:end])


def decode_frame(wire):
    """Decode exactly one frame from its wire bytes (trailing 0x00 optional) into a Frame.

    Raises MalformedError on bad COBS, bad length or bad CRC.
    """
    data = bytes(wire)
    if data and data[-1] == 0:
        data = data[:-1]
    if 0 in data:
        raise MalformedError("delimiter inside a frame")
    if len(data) > MAX_FRAME + 1:
        raise MalformedError("frame longer than MAX_FRAME")
    buf = bytearray(len(data))
    m = cobs.decode_into(data, 0, len(data), buf, 0)
    if m < 0:
        raise MalformedError("invalid COBS")
    pe = _payload_end(buf, m)
    if pe < 0:
        raise MalformedError("frame shorter than header + trailer, or no pad before the CRC")
    if crc16(buf, 0, m - CRC_LEN) != (buf[m - 2] << 8) | buf[m - 1]:
        raise MalformedError("CRC mismatch")
    return Frame(buf[0], buf[1], buf[2], buf[3], buf[4], bytes(buf[HEADER_LEN:pe]))


def _payload_end(buf, m):
    """End of the payload of the decoded raw frame ``buf[0:m]``; -1 if too short or the pad is
    missing (version 2+), -1 for a version-1 frame shorter than header + CRC."""
    if m < HEADER_LEN + CRC_LEN:
        return -1
    if buf[0] == LEGACY_VERSION:
        return m - CRC_LEN
    if m < MIN_FRAME or buf[m - TRAILER_LEN] != 0:
        return -1
    return m - TRAILER_LEN


# --------------------------------------------------------------------------------------------
# incremental reader
# --------------------------------------------------------------------------------------------
# FrameReader state: one array 'i' the scan loop (machine code or its bytecode twin) works on
_N = const(0)  # bytes collected of the frame being received
_OVER = const(1)  # more than fit arrived before the delimiter
_MAXF = const(2)  # max_frame
_OK = const(3)
_CRC_ERR = const(4)
_FRAMING = const(5)
_OVERSIZE = const(6)
_RAW_LEN = const(7)  # of the frame just completed
_PE = const(8)  # its payload end
_CAP = const(9)  # len(raw)
_ST_LEN = const(10)


def _scan_py(data, i, end, buf, st, table):
    """Bytecode twin of ``protocol._fast.scan`` (same contract, same results): consume
    data[i:end] until one good frame completes; return the next position << 1 | completed."""
    cap = st[_CAP]
    n = st[_N]
    while i < end:
        b = data[i]
        i += 1
        if b != 0:
            if n < cap:
                buf[n] = b
                n += 1
            else:
                st[_OVER] = 1
            continue
        # delimiter
        if st[_OVER]:
            st[_OVERSIZE] += 1
            st[_OVER] = 0
            n = 0
            continue
        if n == 0:
            continue  # idle padding
        m = cobs.decode_into(buf, 0, n, buf, 0)
        n = 0
        pe = _payload_end(buf, m) if m <= st[_MAXF] else -1
        if pe < 0:
            st[_FRAMING] += 1
            continue
        p = m - CRC_LEN
        if crc16(buf, 0, p) != (buf[p] << 8) | buf[p + 1]:
            st[_CRC_ERR] += 1
            continue
        st[_RAW_LEN] = m
        st[_PE] = pe
        st[_OK] += 1
        st[_N] = 0
        return i << 1 | 1
    st[_N] = n
    return i << 1


class FrameReader:
    """Incremental receiver: bytes in, CRC-checked frames out; resynchronises on every 0x00.

    Device use (allocates nothing in steady state)::

        pos = 0
        while pos < n:
            pos = reader.scan(rxbuf, pos, n)
            if reader.ready:      # one frame: reader.ver/flags/hop/mtype/seq, payload is
                handle(reader)    # reader.raw[HEADER_LEN:reader.payload_end], raw length raw_len

    Host use: ``frames = reader.feed(data)``.

    Counters: ``ok``, ``crc_error``, ``framing_error`` (bad COBS, runt, discarded partial),
    ``oversize`` (more than MAX_FRAME before a delimiter). Empty frames (0x00 0x00) are idle
    padding and are not counted. The byte loop is one call (``_scan``: machine code where the
    port has the viper emitter) over the state array ``st``.
    """

    def __init__(self, max_frame=MAX_FRAME):
        self.max_frame = max_frame
        self.raw = bytearray(max_frame + 1)  # COBS-encoded bytes, decoded in place
        self.st = array("i", [0] * _ST_LEN)
        self.st[_MAXF] = max_frame
        self.st[_CAP] = max_frame + 1
        self.ready = False
        self.ver = 0
        self.flags = 0
        self.hop = 0
        self.mtype = 0
        self.seq = 0
        self.raw_len = 0
        self.payload_end = 0

    def reset(self):
        """Discard a partial frame (e.g. after a silence timeout); counts a framing error if any."""
        st = self.st
        if st[_N] or st[_OVER]:
            st[_FRAMING] += 1
        st[_N] = 0
        st[_OVER] = 0
        self.ready = False

    def scan(self, data, start, end):
        """Consume ``data[start:end]`` until one good frame completes; return the next position.

        After the call ``ready`` tells whether a frame is available (valid until the next call).
        """
        if start < 0 or end > len(data):
            raise IndexError("scan range outside the data")
        st = self.st
        r = _scan(data, start, end, self.raw, st, _TABLE)
        if r & 1:
            raw = self.raw
            self.ver = raw[0]
            self.flags = raw[1]
            self.hop = raw[2]
            self.mtype = raw[3]
            self.seq = raw[4]
            self.raw_len = st[_RAW_LEN]
            self.payload_end = st[_PE]
            self.ready = True
        else:
            self.ready = False
        return r >> 1

    def frame(self):
        """The current frame as a Frame (allocates; host or slow path)."""
        return Frame(
            self.ver,
            self.flags,
            self.hop,
            self.mtype,
            self.seq,
            bytes(self.raw[HEADER_LEN : self.payload_end]),
        )

    def payload(self):
        """Memoryview of the current frame's payload (allocates one small view object)."""
        return memoryview(self.raw)[HEADER_LEN : self.payload_end]

    def feed(self, data):
        """Consume all of ``data``; return the list of good frames it completed."""
        frames = []
        pos = 0
        end = len(data)
        while pos < end:
            pos = self.scan(data, pos, end)
            if self.ready:
                frames.append(self.frame())
        self.ready = False
        return frames

    def errors(self):
        """Frames rejected so far: CRC, framing and oversize errors together."""
        st = self.st
        return st[_CRC_ERR] + st[_FRAMING] + st[_OVERSIZE]

    def stats(self):
        """Counters as a dict: good frames, CRC errors, framing errors, oversize frames. (No
        properties on this class: on MicroPython a class with one makes every attribute store
        on its instances several times slower, and the scan stores ten per frame.)"""
        st = self.st
        return {
            "ok": st[_OK],
            "crc_error": st[_CRC_ERR],
            "framing_error": st[_FRAMING],
            "oversize": st[_OVERSIZE],
        }


# The scan loop in machine code on MicroPython ports with the viper emitter (protocol/_fast.py);
# elsewhere (CPython, a port without the emitter) its bytecode twin above.
try:
    from protocol._fast import scan as _scan
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    _scan = _scan_py
