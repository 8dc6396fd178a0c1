"""Small CBOR (RFC 8949) codec: the subset the link protocol needs, byte-identical to cbor2.

Encoding rule (identical to ``cbor2.dumps(obj, canonical=True)``): shortest head for every int and
length, definite lengths only, map keys sorted by their encoded bytes (length first, then
bytewise), floats in the shortest of float16/float32/float64 that holds the value exactly
(NaN -> f9 7e00). Supported types: int (|n| < 2**64), bool, None, float, str, bytes, list/tuple,
dict. Decoding (``loads`` and ``Reader`` alike) rejects ints and lengths outside the wire range
(|n| < 2**30: a 4-byte argument >= 0x40000000, -2**30, any 8-byte argument; docs/protocol.md
"Integer range"), tags, indefinite lengths, undefined/simple values, duplicate map keys,
nesting deeper than ``MAX_DEPTH``, text that is not UTF-8 (checked by ``utf8_ok`` on both
runtimes: MicroPython's ``bytes.decode`` does not validate), map keys other than an int, text or
bytes (no float, bool, null, array or map keys) and trailing bytes, raising ``MalformedError``.
The in-place ``Reader.skip`` applies the same rules to items it skips, so content a decoder
ignores is still validated.

``dumps``/``loads`` allocate (slow path). ``put_*`` write into caller buffers and ``Reader``
walks a buffer in place: both allocate nothing, for the device hot path.
"""

import math
import struct
from array import array

from protocol.errors import MalformedError

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


MAX_DEPTH = const(8)  # nesting limit when decoding
_KMAX = const(48)  # Reader: keys of the open maps remembered for the duplicate check
_LIMIT = const(0x40000000)  # Reader: ints must be within +-2**30 (small ints on a 32-bit MCU)

# Reader.head() results besides majors 0..7
END = const(-2)  # no more bytes
BAD = const(-1)  # malformed or not allowed in the in-place reader

# simple values as returned by Reader.head() for major 7 (in Reader.arg)
SIMPLE_FALSE = const(20)
SIMPLE_TRUE = const(21)
SIMPLE_NULL = const(22)
FLOAT16 = const(25)
FLOAT32 = const(26)
FLOAT64 = const(27)


# --------------------------------------------------------------------------------------------
# in-place writer helpers (no allocation)
# --------------------------------------------------------------------------------------------
def put_head(buf, off, major, arg):
    """Write a CBOR head (major type 0..7, argument 0 <= arg < 2**32) at ``off``; return new off."""
    mt = major << 5
    if arg < 24:
        buf[off] = mt | arg
        return off + 1
    if arg < 0x100:
        buf[off] = mt | 24
        buf[off + 1] = arg
        return off + 2
    if arg < 0x10000:
        buf[off] = mt | 25
        buf[off + 1] = arg >> 8
        buf[off + 2] = arg & 0xFF
        return off + 3
    buf[off] = mt | 26
    buf[off + 1] = (arg >> 24) & 0xFF
    buf[off + 2] = (arg >> 16) & 0xFF
    buf[off + 3] = (arg >> 8) & 0xFF
    buf[off + 4] = arg & 0xFF
    return off + 5


def put_int(buf, off, v):
    """Write a signed int (|v| < 2**32) at ``off``; return new off."""
    if v >= 0:
        return put_head(buf, off, 0, v)
    return put_head(buf, off, 1, -1 - v)


def put_bool(buf, off, v):
    """Write true/false at ``off``; return new off."""
    buf[off] = 0xF5 if v else 0xF4
    return off + 1


def put_null(buf, off):
    """Write null at ``off``; return new off."""
    buf[off] = 0xF6
    return off + 1


def put_bytes_str(buf, off, data, major):
    """Write ``data`` (bytes-like, already UTF-8 for text) as major 2 (bytes) or 3 (text)."""
    n = len(data)
    off = put_head(buf, off, major, n)
    for i in range(n):
        buf[off + i] = data[i]
    return off + n


def utf8_ok(buf, p, end):
    """True if ``buf[p:end]`` is well-formed UTF-8 (RFC 3629: no overlongs, no surrogates, no
    code points above U+10FFFF), as CPython's strict decoder and cbor2 require. No allocation."""
    while p < end:
        b = buf[p]
        if b < 0x80:
            p += 1
            continue
        lo = 0x80
        hi = 0xBF
        if 0xC2 <= b <= 0xDF:
            n = 1
        elif b == 0xE0:
            n = 2
            lo = 0xA0
        elif b == 0xED:
            n = 2
            hi = 0x9F
        elif 0xE1 <= b <= 0xEF:
            n = 2
        elif b == 0xF0:
            n = 3
            lo = 0x90
        elif 0xF1 <= b <= 0xF3:
            n = 3
        elif b == 0xF4:
            n = 3
            hi = 0x8F
        else:
            return False
        if p + n >= end:
            return False
        c = buf[p + 1]
        if c < lo or c > hi:
            return False
        i = 2
        while i <= n:
            if buf[p + i] & 0xC0 != 0x80:
                return False
            i += 1
        p += n + 1
    return True


# --------------------------------------------------------------------------------------------
# in-place reader (no allocation)
# --------------------------------------------------------------------------------------------
class Reader:
    """Walks CBOR in ``buf[start:end]`` without building objects.

    ``head()`` reads one item head and returns its major type (0..7), ``END`` or ``BAD``; the
    argument is left in ``arg`` (for major 0 the value, for 1 the value ``val = -1 - arg``, for
    2/3/4/5 the length, for 7 the simple value or FLOAT16/32/64 with the float bytes skipped and
    their offset in ``fpos``). Ints must be below 2**30 in magnitude (else ``BAD``), so nothing
    here ever builds a big int on a 32-bit MCU.
    """

    def __init__(self):
        self.buf = b""
        self.pos = 0
        self.end = 0
        self.arg = 0
        self.val = 0
        self.fpos = 0
        # skip(): items left per open container level, map flag, first key index per level
        self._rem = array("i", [0] * (MAX_DEPTH + 2))
        self._map = bytearray(MAX_DEPTH + 2)
        self._kb = array("i", [0] * (MAX_DEPTH + 2))
        # keys of the open maps (and of the top-level map, see key_new): major, arg/start, length
        self._km = bytearray(_KMAX)
        self._ka = array("i", [0] * _KMAX)
        self._kl = bytearray(_KMAX)  # text/bytes key lengths (< 256 in a frame)
        self._kn = 0

    def reset(self, buf, start, end):
        """Point the reader at ``buf[start:end]``."""
        self.buf = buf
        self.pos = start
        self.end = end
        self._kn = 0

    def head(self):
        """Read one head; return major type, END (no bytes left) or BAD."""
        p = self.pos
        end = self.end
        if p >= end:
            return END
        buf = self.buf
        ib = buf[p]
        p += 1
        major = ib >> 5
        ai = ib & 0x1F
        if major == 7:
            if ai < 20 or ai == 23 or ai == 24 or ai > 27:
                return BAD  # only false/true/null and floats
            if ai >= 25:
                n = 2 if ai == 25 else (4 if ai == 26 else 8)
                if p + n > end:
                    return BAD
                self.fpos = p
                p += n
            self.arg = ai
            self.pos = p
            return 7
        if major == 6:
            return BAD  # tags are not used by the protocol
        if ai < 24:
            arg = ai
        elif ai == 24:
            if p + 1 > end:
                return BAD
            arg = buf[p]
            p += 1
        elif ai == 25:
            if p + 2 > end:
                return BAD
            arg = (buf[p] << 8) | buf[p + 1]
            p += 2
        elif ai == 26:
            if p + 4 > end or buf[p] >= 0x40:
                return BAD  # >= 2**30: outside the wire int range
            arg = (buf[p] << 24) | (buf[p + 1] << 16) | (buf[p + 2] << 8) | buf[p + 3]
            if major == 1 and arg == 0x3FFFFFFF:
                return BAD  # -1 - arg = -2**30: outside the wire range too (|n| < 2**30)
            p += 4
        else:
            return BAD  # 8-byte arguments and indefinite lengths are not used
        if major >= 2 and arg > end - p:
            return BAD  # a length cannot exceed the remaining bytes (each element >= 1 byte)
        self.arg = arg
        self.val = arg if major == 0 else -1 - arg
        self.pos = p
        return major

    def int(self):
        """Read an int item into ``val``; return True, or False if it is not an int."""
        m = self.head()
        return m == 0 or m == 1

    def _key(self, m, base):
        """Record key (major ``m``, just read by head) against keys[base:]; False if invalid."""
        n = self._kn
        if n >= _KMAX:
            return False
        if m == 0 or m == 1:
            a = self.arg
            for i in range(base, n):
                if self._km[i] == m and self._ka[i] == a:
                    return False
        elif m == 2 or m == 3:
            a = self.pos
            ln = self.arg
            buf = self.buf
            if m == 3 and not utf8_ok(buf, a, a + ln):
                return False
            for i in range(base, n):
                if self._km[i] == m and self._kl[i] == ln:
                    b = self._ka[i]
                    j = 0
                    while j < ln and buf[a + j] == buf[b + j]:
                        j += 1
                    if j == ln:
                        return False
            self._kl[n] = ln
            self.pos = a + ln
        else:
            return False  # keys are ints (protocol maps), or text / bytes (nested maps)
        self._km[n] = m
        self._ka[n] = a
        self._kn = n + 1
        return True

    def top_key(self):
        """Read one key of the top-level map: an int not seen before in it (``val``); False if
        it is not an int or repeats one. Call ``reset`` before the map's head."""
        m = self.head()
        if m != 0 and m != 1:
            return False
        return self._key(m, 0)

    def skip(self, depth=0):
        """Skip one complete item that sits at nesting ``depth`` (the payload map is depth 0);
        return False if it is malformed: any rule of ``loads`` broken inside it (nesting deeper
        than MAX_DEPTH, text not UTF-8, duplicate map keys, truncation); map keys inside must be
        ints, text or bytes (the protocol uses no others)."""
        rem = self._rem
        ismap = self._map
        kb = self._kb
        lvl = 0
        rem[0] = 1
        ismap[0] = 0
        kb[0] = self._kn
        while lvl >= 0:
            r = rem[lvl]
            if r == 0:
                self._kn = kb[lvl]  # forget the keys of a closed map
                lvl -= 1
                continue
            rem[lvl] = r - 1
            m = self.head()
            if m < 0:
                return False
            if ismap[lvl] and r & 1 == 0:  # a key of the map open at this level
                if not self._key(m, kb[lvl]):
                    return False
                continue
            if m == 2:
                self.pos += self.arg
            elif m == 3:
                p = self.pos
                if not utf8_ok(self.buf, p, p + self.arg):
                    return False
                self.pos = p + self.arg
            elif m == 4 or m == 5:
                n = self.arg if m == 4 else 2 * self.arg
                if n:
                    if depth + lvl + 1 > MAX_DEPTH:
                        return False  # a child would sit deeper than loads() accepts
                    if n > self.end - self.pos:
                        return False
                    lvl += 1
                    rem[lvl] = n
                    ismap[lvl] = 1 if m == 5 else 0
                    kb[lvl] = self._kn
        return True

    def at_end(self):
        """True when every byte has been consumed."""
        return self.pos == self.end


# --------------------------------------------------------------------------------------------
# general encoder / decoder (allocate; slow path and host)
# --------------------------------------------------------------------------------------------
def _head(out, major, arg):
    mt = major << 5
    if arg < 24:
        out.append(mt | arg)
    elif arg < 0x100:
        out.append(mt | 24)
        out.append(arg)
    elif arg < 0x10000:
        out.append(mt | 25)
        out.extend(struct.pack(">H", arg))
    elif arg < 0x100000000:
        out.append(mt | 26)
        out.extend(struct.pack(">I", arg))
    elif arg < 0x10000000000000000:
        out.append(mt | 27)
        out.extend(struct.pack(">Q", arg))
    else:
        raise ValueError("CBOR int out of range (|n| >= 2**64)")


def _half_bits(f32):
    """IEEE half bits of the float32 with bits ``f32`` if exactly representable, else -1.

    Done by hand: struct's "e" on MicroPython mis-rounds half subnormals.
    """
    sign = (f32 >> 16) & 0x8000
    exp = (f32 >> 23) & 0xFF
    mant = f32 & 0x7FFFFF
    if exp == 0xFF:
        return sign | 0x7C00 if mant == 0 else -1  # infinity (NaN is handled by the caller)
    if exp == 0:
        return sign if mant == 0 else -1  # zero; float32 subnormals are below half's range
    e = exp - 127
    if -14 <= e <= 15:
        return sign | ((e + 15) << 10) | (mant >> 13) if mant & 0x1FFF == 0 else -1
    if -24 <= e < -14:  # half subnormal: m * 2**-24
        sig = mant | 0x800000
        shift = -e - 1
        return sign | (sig >> shift) if sig & ((1 << shift) - 1) == 0 else -1
    return -1


_INF = float("inf")
_NAN = float("nan")


def _half_value(h):
    """Float value of IEEE half bits ``h``."""
    exp = (h >> 10) & 0x1F
    mant = h & 0x3FF
    if exp == 0:
        v = math.ldexp(mant, -24)
    elif exp == 0x1F:
        v = _INF if mant == 0 else _NAN
    else:
        v = math.ldexp(mant | 0x400, exp - 25)
    return -v if h & 0x8000 else v


def _float(out, x):
    if x != x:  # NaN: canonical half-precision quiet NaN
        out.extend(b"\xf9\x7e\x00")
        return
    try:
        f = struct.pack(">f", x)
        exact32 = struct.unpack(">f", f)[0] == x
    except (OverflowError, ValueError):
        exact32 = False
    if exact32:
        h = _half_bits(struct.unpack(">I", f)[0])
        if h >= 0:
            out.append(0xF9)
            out.append(h >> 8)
            out.append(h & 0xFF)
            return
        out.append(0xFA)
        out.extend(f)
        return
    out.append(0xFB)
    out.extend(struct.pack(">d", x))


def _enc(out, obj, depth):
    if depth > MAX_DEPTH:
        raise ValueError("CBOR nesting too deep")
    if obj is True:
        out.append(0xF5)
    elif obj is False:
        out.append(0xF4)
    elif obj is None:
        out.append(0xF6)
    elif isinstance(obj, int):
        if obj >= 0:
            _head(out, 0, obj)
        else:
            _head(out, 1, -1 - obj)
    elif isinstance(obj, float):
        _float(out, obj)
    elif isinstance(obj, str):
        b = obj.encode("utf-8")
        _head(out, 3, len(b))
        out.extend(b)
    elif isinstance(obj, (bytes, bytearray, memoryview)):
        _head(out, 2, len(obj))
        out.extend(obj)
    elif isinstance(obj, (list, tuple)):
        _head(out, 4, len(obj))
        for item in obj:
            _enc(out, item, depth + 1)
    elif isinstance(obj, dict):
        items = []
        for k, v in obj.items():
            kb = bytearray()
            _enc(kb, k, depth + 1)
            items.append((len(kb), bytes(kb), v))
        items.sort(key=_sort_key)
        _head(out, 5, len(items))
        prev = None
        for _, kb, v in items:
            if kb == prev:
                raise ValueError("duplicate CBOR map key")
            prev = kb
            out.extend(kb)
            _enc(out, v, depth + 1)
    else:
        raise TypeError("cannot CBOR-encode " + str(type(obj)))


def _sort_key(item):
    return (item[0], item[1])


def dumps(obj):
    """Encode ``obj`` canonically (same bytes as cbor2 ``canonical=True``); return bytes."""
    out = bytearray()
    _enc(out, obj, 0)
    return bytes(out)


def dumps_into(obj, buf, off):
    """Encode ``obj`` into ``buf`` at ``off``; return the new offset (IndexError if too long)."""
    b = dumps(obj)
    n = len(b)
    if off + n > len(buf):
        raise IndexError("CBOR item does not fit the buffer")
    for i in range(n):
        buf[off + i] = b[i]
    return off + n


class _Dec:
    """Decoder state for ``loads`` (position in a buffer)."""

    def __init__(self, buf, start, end):
        self.buf = buf
        self.pos = start
        self.end = end

    def take(self, n):
        p = self.pos
        if n > self.end - p:
            raise MalformedError("CBOR item truncated")
        self.pos = p + n
        return p

    def arg(self, ai):
        buf = self.buf
        if ai < 24:
            return ai
        if ai == 24:
            return buf[self.take(1)]
        if ai == 25:
            p = self.take(2)
            return (buf[p] << 8) | buf[p + 1]
        if ai == 26:
            p = self.take(4)
            if buf[p] >= 0x40:  # the wire's int range, as Reader.head: |n| < 2**30
                raise MalformedError("CBOR int or length outside the wire range (2**30)")
            return (buf[p] << 24) | (buf[p + 1] << 16) | (buf[p + 2] << 8) | buf[p + 3]
        if ai == 27:
            raise MalformedError("CBOR 8-byte argument (outside the wire range)")
        raise MalformedError("CBOR indefinite length or reserved additional info")

    def item(self, depth):
        if depth > MAX_DEPTH:
            raise MalformedError("CBOR nesting too deep")
        buf = self.buf
        ib = buf[self.take(1)]
        major = ib >> 5
        ai = ib & 0x1F
        if major == 7:
            if ai == 20:
                return False
            if ai == 21:
                return True
            if ai == 22:
                return None
            if ai == 25:
                p = self.take(2)
                return _half_value((buf[p] << 8) | buf[p + 1])
            if ai == 26:
                p = self.take(4)
                return struct.unpack(">f", bytes(buf[p : p + 4]))[0]
            if ai == 27:
                p = self.take(8)
                return struct.unpack(">d", bytes(buf[p : p + 8]))[0]
            raise MalformedError("CBOR simple value not allowed")
        if major == 6:
            raise MalformedError("CBOR tags not allowed")
        n = self.arg(ai)
        if major == 0:
            return n
        if major == 1:
            if n == 0x3FFFFFFF:
                raise MalformedError("CBOR int -2**30 outside the wire range")
            return -1 - n
        if major == 2 or major == 3:
            p = self.take(n)
            raw = bytes(buf[p : p + n])
            if major == 2:
                return raw
            if not utf8_ok(buf, p, p + n):  # MicroPython's decode() would accept it
                raise MalformedError("CBOR text is not UTF-8")
            return raw.decode("utf-8")
        if n > self.end - self.pos:
            raise MalformedError("CBOR container longer than the data")
        if major == 4:
            out = []
            for _ in range(n):
                out.append(self.item(depth + 1))
            return out
        # major 5: map
        d = {}
        for _ in range(n):
            k = self.item(depth + 1)
            if isinstance(k, bool) or not isinstance(k, (int, str, bytes)):
                # the rule of Reader._key: no float, bool, null, array or map keys
                raise MalformedError("CBOR map key must be int, text or bytes")
            if k in d:
                raise MalformedError("duplicate CBOR map key")
            d[k] = self.item(depth + 1)
        return d


def loads(data, start=0, end=-1):
    """Decode exactly one CBOR item from ``data[start:end]``; raise MalformedError if invalid."""
    if end < 0:
        end = len(data)
    d = _Dec(data, start, end)
    obj = d.item(0)
    if d.pos != end:
        raise MalformedError("trailing bytes after CBOR item")
    return obj
