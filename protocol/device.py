"""Segment-side helpers for the cyclic messages that allocate nothing (fixed-point ints only).

Decoders walk CBOR in place (``protocol.cbor.Reader``) and write results into a caller list;
encoders write the CBOR payload into a caller buffer. Return codes instead of exceptions, so a
malformed frame costs no allocation either: ``OK``/``HOLD`` >= 0, ``MALFORMED`` < 0 (answer ERROR
with code ERR_MALFORMED). Slow-path messages (descriptor, params, error text) use
``protocol.messages``.
"""

from struct import pack_into

from protocol.cbor import Reader, put_head, put_int
from protocol.constants import (
    FLAG_BCAST,
    FLAG_LOCAL,
    FLAG_UP,
    HEADER_LEN,
    SP_HOLD,
    SP_LEN,
    STATE_FIXED,
    T_ALIVE,
    T_EVENT,
    T_STATE,
    VERSION_MAX,
    VERSION_MIN,
)
from protocol.frame import frame_into

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


# STATE report offsets (docs/protocol.md 0x83); private consts cost no heap on the board
_O_PHI = const(11)  # after cycle (0, u32), t_ms (4, u32), kappa (8, i24)
_O_SERVOS = const(15)  # after phi (11, i16), status (13, u8), position (14, u8)
_I16_MAX = const(0x7FFF)

OK = const(1)  # decoded; SYNC: this segment's entry present
HOLD = const(0)  # SYNC without an entry for this position: hold the current setpoint
MALFORMED = const(-1)  # not a valid message of this type

# indices into the ``out`` list filled by decode_sync
SYNC_CYCLE = const(0)
SYNC_KAPPA = const(1)
SYNC_PHI = const(2)
SYNC_RESUME = const(3)

_R = Reader()  # module-level: decoders reuse it (not re-entrant, not thread safe)


def version_supported(ver):
    """True if this implementation speaks protocol version ``ver``."""
    return VERSION_MIN <= ver <= VERSION_MAX


def decode_sync(buf, start, end, position, out):
    """Decode SYNC ``{0: cycle, 1: packed setpoints, 2: resume?}`` for segment ``position``.

    Fills ``out`` (a list of >= 4 ints): [SYNC_CYCLE] cycle, [SYNC_KAPPA] kappa (1e-4 1/m),
    [SYNC_PHI] phi (1e-4 rad), [SYNC_RESUME] 1 if key 2 is true/1 else 0 (any other value is
    MALFORMED). Key 1 is a byte string of SP_LEN bytes per position (kappa int24, phi int16,
    big-endian); returns OK when the entry for ``position`` is present, HOLD when the string is
    too short or the entry is the hold marker, MALFORMED otherwise, including a hold marker with
    non-zero phi bytes in any position's entry (out is then undefined). Unknown keys are skipped.
    The usual encoding is decoded by one machine-code call where the port has the viper emitter
    (``protocol._fast.sync_entry``, the same results); anything else is decoded here.
    """
    if _sync_entry is not None and 0 <= start <= end <= len(buf):
        rc = _sync_entry(buf, start, end, position, out)
        if rc >= 0:
            return rc
    r = _R
    r.reset(buf, start, end)
    if r.head() != 5:
        return MALFORMED
    pairs = r.arg
    seen = 0
    found = HOLD
    out[SYNC_RESUME] = 0
    for _ in range(pairs):
        if not r.top_key() or r.val < 0:
            return MALFORMED  # not a non-negative int, or a duplicate key
        key = r.arg
        if key < 2:
            seen |= 1 << key
        if key == 0:
            if r.head() != 0:
                return MALFORMED
            out[SYNC_CYCLE] = r.arg
        elif key == 1:
            if r.head() != 2:
                return MALFORMED
            q = r.pos
            ln = r.arg
            r.pos = q + ln
            if ln % SP_LEN:
                return MALFORMED  # whole entries only
            e = q  # every entry's hold marker is exactly 80 00 00 00 00, not only ours
            while e < r.pos:
                if buf[e] == 0x80 and not (buf[e + 1] | buf[e + 2]) and buf[e + 3] | buf[e + 4]:
                    return MALFORMED
                e += SP_LEN
            q += SP_LEN * position
            if q + SP_LEN <= r.pos:
                b0 = buf[q]
                k = (b0 << 16) | (buf[q + 1] << 8) | buf[q + 2]
                if b0 & 0x80:
                    k -= 0x1000000
                p = (buf[q + 3] << 8) | buf[q + 4]
                if p & 0x8000:
                    p -= 0x10000
                if k == SP_HOLD:
                    if p:
                        return MALFORMED  # the hold marker is exactly 80 00 00 00 00
                    found = HOLD
                else:
                    out[SYNC_KAPPA] = k
                    out[SYNC_PHI] = p
                    found = OK
        elif key == 2:
            m = r.head()
            if m == 7 and (r.arg == 20 or r.arg == 21):
                out[SYNC_RESUME] = 1 if r.arg == 21 else 0
            elif m == 0 and r.arg < 2:  # true (or 1) / false (or 0) only
                out[SYNC_RESUME] = r.arg
            else:
                return MALFORMED
        elif not r.skip(1):
            return MALFORMED  # unknown keys are ignored, but must be valid (cbor.Reader.skip)
    if not (seen & 3 == 3) or not r.at_end():
        return MALFORMED  # cycle and setpoint list are mandatory
    return found


def decode_cycle(buf, start, end):
    """Decode HEARTBEAT ``{0: cycle}``: return the cycle (>= 0) or MALFORMED."""
    r = _R
    r.reset(buf, start, end)
    if r.head() != 5:
        return MALFORMED
    cycle = MALFORMED
    for _ in range(r.arg):
        if not r.top_key() or r.val < 0:
            return MALFORMED
        if r.arg == 0:
            if r.head() != 0:
                return MALFORMED
            cycle = r.arg
        elif not r.skip(1):
            return MALFORMED
    if not r.at_end():
        return MALFORMED
    return cycle


def decode_empty(buf, start, end):
    """Check an empty-map payload (DISCOVER, HOLD, ALIVE): OK, or MALFORMED.

    An empty payload (no bytes) counts as ``{}``; unknown keys are skipped.
    """
    if start == end:
        return OK
    r = _R
    r.reset(buf, start, end)
    if r.head() != 5:
        return MALFORMED
    for _ in range(r.arg):
        if not r.top_key() or not r.skip(1):
            return MALFORMED
    return OK if r.at_end() else MALFORMED


def encode_state(buf, off, cycle, t_ms, kappa, phi, servos, n_servos, status, pos=0):
    """Write a STATE payload ``{0: packed report}`` into ``buf`` at ``off``; return its end.

    Layout of the report (docs/protocol.md 0x83): cycle, t_ms (uint32), kappa (int24, 1e-4 1/m),
    phi (int16, 1e-4 rad), status, pos (uint8: the chain position whose SYNC entry this segment
    applies), then the first ``n_servos`` of ``servos`` (1e-4 rad ints) as int16 in 1e-3 rad,
    clamped to the int16 range. struct.pack_into is C code on MicroPython and allocates nothing.
    """
    ln = STATE_FIXED + 2 * n_servos
    buf[off] = 0xA1  # map of 1 pair
    buf[off + 1] = 0  # key 0
    if ln < 24:
        buf[off + 2] = 0x40 + ln
        o = off + 3
    else:
        buf[off + 2] = 0x58
        buf[off + 3] = ln
        o = off + 4
    pack_into(">i", buf, o + 7, kappa)  # int32 at 7..10; bytes 8..10 are the int24
    pack_into(">II", buf, o, cycle, t_ms)  # overwrites byte 7 with the last byte of t_ms
    pack_into(">hBB", buf, o + _O_PHI, phi, status, pos)
    q = o + _O_SERVOS
    for i in range(n_servos):
        a = (servos[i] + 5) // 10
        if a > _I16_MAX:
            a = _I16_MAX
        elif a < -_I16_MAX:
            a = -_I16_MAX
        pack_into(">h", buf, q, a)
        q += 2
    return q


def encode_event(buf, off, code, detail, t_ms, text=None, tlen=0):
    """Write an EVENT payload ``{0: code, 1: detail, 2: t_ms}`` at ``off``; return end.

    With ``tlen`` > 0, key 3 carries ``text[:tlen]`` (UTF-8 bytes, e.g. a FAULT's reason).
    """
    buf[off] = 0xA4 if tlen else 0xA3
    buf[off + 1] = 0
    off = put_int(buf, off + 2, code)
    buf[off] = 1
    off = put_int(buf, off + 1, detail)
    buf[off] = 2
    off = put_int(buf, off + 1, t_ms)
    if tlen:
        buf[off] = 3
        off = put_head(buf, off + 1, 3, tlen)
        for i in range(tlen):
            buf[off + i] = text[i]
        off += tlen
    return off


def encode_empty(buf, off):
    """Write ``{}`` at ``off``; return end."""
    buf[off] = 0xA0
    return off + 1


def state_frame(raw, out, seq, cycle, t_ms, kappa, phi, servos, n_servos, status, pos=0):
    """Build a complete STATE wire frame (UP, hop 0) into ``out``; return its length.

    ``raw`` is scratch space of MAX_FRAME bytes. Allocates nothing. Where the port has the viper
    emitter, one machine-code call (``protocol._fast.state_wire``, byte-identical) does it all.
    """
    if _state_wire is not None and 26 + 2 * n_servos <= len(raw) and 28 + 2 * n_servos <= len(out):
        return _state_wire(
            raw, out, seq, cycle, t_ms, kappa, phi, status | pos << 8, servos, n_servos, _CRC_TABLE
        )
    end = encode_state(raw, HEADER_LEN, cycle, t_ms, kappa, phi, servos, n_servos, status, pos)
    return frame_into(raw, end, FLAG_UP, 0, T_STATE, seq, out, 0)


def event_frame(raw, out, seq, code, detail, t_ms, text=None, tlen=0):
    """Build a complete EVENT wire frame (UP, hop 0) into ``out``; return its length."""
    end = encode_event(raw, HEADER_LEN, code, detail, t_ms, text, tlen)
    return frame_into(raw, end, FLAG_UP, 0, T_EVENT, seq, out, 0)


def alive_frame(raw, out, seq):
    """Build an ALIVE wire frame (UP|LOCAL, hop 0, payload {}) into ``out``; return its length."""
    end = encode_empty(raw, HEADER_LEN)
    return frame_into(raw, end, FLAG_UP | FLAG_LOCAL, 0, T_ALIVE, seq, out, 0)


# forwarding decisions (header only) ---------------------------------------------------------
FWD_NONE = const(0)  # do not forward
FWD_UP = const(1)  # forward upstream with hop + 1
FWD_DOWN = const(2)  # forward downstream with new hop


def route(flags, hop):
    """Decide what a segment does with a good frame from its header.

    Returns ``(mine << 2) | forward`` as one small int without allocating: ``mine`` (bit 2) is
    set when this segment must process the frame, ``forward`` is FWD_NONE/FWD_UP/FWD_DOWN; the
    hop byte to forward with is ``next_hop(flags, hop)``. Frames with FLAG_UP that arrive from
    downstream are never processed, only forwarded (unless LOCAL).
    """
    if flags & FLAG_LOCAL:
        return 4  # link-local: consume, never forward
    if flags & FLAG_UP:
        return FWD_UP
    if flags & FLAG_BCAST:
        return 4 | FWD_DOWN
    if hop == 0:
        return 4
    return FWD_DOWN


def next_hop(flags, hop):
    """The hop byte a forwarded frame carries (UP: +1, BCAST: +1, addressed: -1)."""
    if flags & (FLAG_UP | FLAG_BCAST):
        return (hop + 1) & 0xFF
    return hop - 1


# The usual SYNC decoded in machine code (protocol/_fast.py) where the port has the viper emitter.
try:
    from protocol._fast import sync_entry as _sync_entry
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    _sync_entry = None

# The STATE frame in machine code (protocol/_fast.py) where the port has the viper emitter,
# checked against the bytecode path once, as crc.py and cobs.py check theirs.
try:
    from array import array

    from protocol import _fast
    from protocol.crc import _TABLE as _CRC_TABLE

    _a = bytearray(48)
    _b = bytearray(48)
    _c = bytearray(48)
    _sv = array("i", [12345, -99999, 5])
    _n = _fast.state_wire(_a, _b, 7, 0x3FFFFFF1, 123456, -54321, -1234, 0x215, _sv, 3, _CRC_TABLE)
    _m = encode_state(_a, HEADER_LEN, 0x3FFFFFF1, 123456, -54321, -1234, _sv, 3, 0x15, 2)
    _m = frame_into(_a, _m, FLAG_UP, 0, T_STATE, 7, _c, 0)
    _state_wire = _fast.state_wire if _n == _m and _b[:_n] == _c[:_m] else None
    del _a, _b, _c, _sv, _n, _m
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    _state_wire = None
