"""Consistent Overhead Byte Stuffing: removes every 0x00 so 0x00 can delimit frames.

The ``*_into`` functions work on caller buffers and allocate nothing (device hot path); ``encode``
and ``decode`` are host conveniences. For inputs below 254 bytes the overhead is exactly one byte.
"""


def encode_into(src, start, end, dst, off):
    """COBS-encode ``src[start:end]`` into ``dst`` at ``off``; return the end offset in ``dst``.

    ``dst`` needs ``end - start + 1 + (end - start) // 254`` bytes from ``off``. No delimiter is
    written. Allocates nothing.
    """
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
    byte pointing past the end). ``dst`` may be ``src`` with ``off <= start`` (in place).
    Allocates nothing.
    """
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
