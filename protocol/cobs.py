"""Consistent Overhead Byte Stuffing: removes every 0x00 so 0x00 can delimit frames.

The ``*_into`` functions work on caller buffers and allocate nothing (device hot path); ``encode``
and ``decode`` are host conveniences. For inputs below 254 bytes the overhead is exactly one byte.
"""


def encode_into(src, start, end, dst, off):
    """COBS-encode ``src[start:end]`` into ``dst`` at ``off``; return the end offset in ``dst``.

    ``dst`` needs ``end - start + 1 + (end - start) // 254`` bytes from ``off`` (IndexError
    otherwise). No delimiter is written. Allocates nothing.
    """
    n = end - start
    if start < 0 or n < 0 or end > len(src) or off < 0 or off + n + 1 + n // 254 > len(dst):
        raise IndexError("COBS encode range outside the buffers")
    if _fast_enc is not None:
        return _fast_enc(src, start, end, dst, off)
    code_pos = off
    out = off + 1
    code = 1
    for i in range(start, end):
        b = src[i]
        if b == 0:
            dst[code_pos] = code
            code_pos = out
            out += 1
            code = 1
        else:
            dst[out] = b
            out += 1
            code += 1
            if code == 0xFF:
                dst[code_pos] = code
                code_pos = out
                out += 1
                code = 1
    dst[code_pos] = code
    return out


def decode_into(src, start, end, dst, off):
    """Decode COBS ``src[start:end]`` (no delimiter) into ``dst`` at ``off``.

    Returns the decoded length, or -1 when the input is not valid COBS (a 0x00 inside, or a code
    byte pointing past the end). ``dst`` may be ``src`` with ``off <= start`` (in place) and
    needs ``end - start - 1`` bytes from ``off`` (IndexError otherwise). Allocates nothing.
    """
    if start < 0 or start > end or end > len(src) or off < 0 or off + end - start - 1 > len(dst):
        raise IndexError("COBS decode range outside the buffers")
    if _fast_dec is not None:
        return _fast_dec(src, start, end, dst, off)
    i = start
    o = off
    while i < end:
        code = src[i]
        if code == 0:
            return -1
        i += 1
        stop = i + code - 1
        if stop > end:
            return -1
        while i < stop:
            b = src[i]
            if b == 0:
                return -1
            dst[o] = b
            o += 1
            i += 1
        if code != 0xFF and i < end:
            dst[o] = 0
            o += 1
    return o - off


def encode(data):
    """COBS-encode ``data`` (bytes-like) and return bytes, without the delimiter."""
    n = len(data)
    out = bytearray(n + 1 + n // 254)
    m = encode_into(data, 0, n, out, 0)
    return bytes(out[:m])


def decode(data):
    """Decode COBS ``data`` (no delimiter) and return bytes; raise ValueError if invalid."""
    n = len(data)
    out = bytearray(n)
    m = decode_into(data, 0, n, out, 0)
    if m < 0:
        raise ValueError("invalid COBS data")
    return bytes(out[:m])


# Machine-code loops on MicroPython ports with the viper emitter (protocol/_fast.py), checked
# against the pure versions once. Set to None to force the pure-Python loops.
_fast_enc = None
_fast_dec = None
try:
    from protocol import _fast

    _t = bytearray(8)
    if (
        _fast.cobs_encode(b"\x11\x22\x00\x33", 0, 4, _t, 0) == 5
        and _t[:5] == b"\x03\x11\x22\x02\x33"
    ):
        if _fast.cobs_decode(_t, 0, 5, _t, 0) == 4 and _t[:4] == b"\x11\x22\x00\x33":
            _fast_enc = _fast.cobs_encode
            _fast_dec = _fast.cobs_decode
    del _t
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    pass
