# ruff: noqa: F821 - ptr8/ptr16 are viper built-ins, resolved by the MicroPython compiler
"""Viper (machine code) versions of the byte loops; MicroPython only, used when available.

``import micropython`` fails on CPython, and compiling fails on ports without the viper emitter:
``crc``, ``cobs`` and ``frame`` then keep their pure-Python loops (same results, tested on both).
Viper pointers have no bounds checks, so every caller checks the ranges first (see the wrappers in
``crc.py``, ``cobs.py`` and ``frame.py``). Nothing here allocates.
"""

import micropython


@micropython.viper
def crc16(buf, start: int, end: int, crc: int, table) -> int:
    """CRC-16/CCITT-FALSE of buf[start:end] from ``crc`` with a 256-entry uint16 ``table``."""
    b = ptr8(buf)
    t = ptr16(table)
    for i in range(start, end):
        crc = ((crc << 8) & 0xFFFF) ^ t[((crc >> 8) ^ b[i]) & 0xFF]
    return crc


@micropython.viper
def cobs_encode(src, start: int, end: int, dst, off: int) -> int:
    """COBS-encode src[start:end] into dst at off; return the end offset."""
    s = ptr8(src)
    d = ptr8(dst)
    code_pos = off
    out = off + 1
    code = 1
    for i in range(start, end):
        b = s[i]
        if b == 0:
            d[code_pos] = code
            code_pos = out
            out += 1
            code = 1
        else:
            d[out] = b
            out += 1
            code += 1
            if code == 0xFF:
                d[code_pos] = code
                code_pos = out
                out += 1
                code = 1
    d[code_pos] = code
    return out


@micropython.viper
def cobs_decode(src, start: int, end: int, dst, off: int) -> int:
    """Decode COBS src[start:end] into dst at off; return the length or -1 if invalid."""
    s = ptr8(src)
    d = ptr8(dst)
    i = start
    o = off
    while i < end:
        code = s[i]
        if code == 0:
            return -1
        i += 1
        stop = i + code - 1
        if stop > end:
            return -1
        while i < stop:
            b = s[i]
            if b == 0:
                return -1
            d[o] = b
            o += 1
            i += 1
        if code != 0xFF and i < end:
            d[o] = 0
            o += 1
    return o - off


@micropython.viper
def collect(data, start: int, end: int, buf, n_cap: int) -> int:
    """Copy non-zero bytes of data[start:end] to buf[n:cap] up to and including the first 0x00.

    ``n_cap`` = n | cap << 10. Returns i << 10 | hit << 9 | n' where i is the next position,
    hit = 1 if a delimiter was consumed, and n' = cap + 1 if bytes had to be dropped (overflow).
    """
    s = ptr8(data)
    d = ptr8(buf)
    n = n_cap & 0x3FF
    cap = n_cap >> 10
    i = start
    while i < end:
        b = s[i]
        i += 1
        if b == 0:
            return (i << 10) | 0x200 | n
        if n < cap:
            d[n] = b
            n += 1
        else:
            n = cap + 1
    return (i << 10) | n


@micropython.viper
def relay(data, start: int, end: int, out, o: int, st) -> int:
    """Cut-through core (``protocol.relay``): pass data[start:end] to out[o:] through a 3-byte
    hold-back until a 0x00. ``st`` (array 'i'): [run, held, h0, h1, h2, count]; ``run`` counts the
    data bytes left in the current COBS run of what was passed on. Returns i << 10 | hit << 9 | o.
    """
    s = ptr8(data)
    d = ptr8(out)
    t = ptr32(st)
    run = t[0]
    nh = t[1]
    h0 = t[2]
    h1 = t[3]
    h2 = t[4]
    cnt = t[5]
    i = start
    hit = 0
    while i < end:
        b = s[i]
        i += 1
        if b == 0:
            hit = 1
            break
        cnt += 1
        if nh == 3:
            d[o] = h0
            o += 1
            if run == 0:
                run = h0 - 1
            else:
                run -= 1
            h0 = h1
            h1 = h2
            h2 = b
        elif nh == 0:
            h0 = b
            nh = 1
        elif nh == 1:
            h1 = b
            nh = 2
        else:
            h2 = b
            nh = 3
    t[0] = run
    t[1] = nh
    t[2] = h0
    t[3] = h1
    t[4] = h2
    t[5] = cnt
    return (i << 10) | (hit << 9) | o


@micropython.viper
def move(src, s0: int, dst, d0: int, n: int):
    """dst[d0:d0 + n] = src[s0:s0 + n] without a slice object."""
    s = ptr8(src)
    d = ptr8(dst)
    for k in range(n):
        d[d0 + k] = s[s0 + k]
