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


@micropython.viper
def state_wire(
    raw, out, seq: int, cycle: int, t_ms: int, kappa: int, phi: int, sp: int, servos, n: int, table
) -> int:
    """A whole STATE wire frame (``protocol.device.state_frame``) in one call: header, payload
    ``{0: report}`` (docs/protocol.md 0x83), pad, CRC, COBS and the delimiter; ``sp`` = status |
    position << 8, ``servos`` the angles (1e-4 rad ints, sent as int16 1e-3 rad, clamped). The
    caller checks that ``raw`` holds 26 + 2 n bytes and ``out`` 28 + 2 n. Returns the wire
    length."""
    r = ptr8(raw)
    d = ptr8(out)
    t = ptr16(table)
    ln = 15 + 2 * n
    r[0] = 2  # VERSION
    r[1] = 0x01  # FLAG_UP
    r[2] = 0
    r[3] = 0x83  # T_STATE
    r[4] = seq & 0xFF
    r[5] = 0xA1
    r[6] = 0
    o = 8
    if ln < 24:
        r[7] = 0x40 + ln
    else:
        r[7] = 0x58
        r[8] = ln
        o = 9
    r[o] = (cycle >> 24) & 0xFF
    r[o + 1] = (cycle >> 16) & 0xFF
    r[o + 2] = (cycle >> 8) & 0xFF
    r[o + 3] = cycle & 0xFF
    r[o + 4] = (t_ms >> 24) & 0xFF
    r[o + 5] = (t_ms >> 16) & 0xFF
    r[o + 6] = (t_ms >> 8) & 0xFF
    r[o + 7] = t_ms & 0xFF
    r[o + 8] = (kappa >> 16) & 0xFF
    r[o + 9] = (kappa >> 8) & 0xFF
    r[o + 10] = kappa & 0xFF
    r[o + 11] = (phi >> 8) & 0xFF
    r[o + 12] = phi & 0xFF
    r[o + 13] = sp & 0xFF
    r[o + 14] = (sp >> 8) & 0xFF
    q = o + 15
    for i in range(n):
        a = (int(servos[i]) + 5) // 10
        if a > 0x7FFF:
            a = 0x7FFF
        elif a < -0x7FFF:
            a = -0x7FFF
        r[q] = (a >> 8) & 0xFF
        r[q + 1] = a & 0xFF
        q += 2
    r[q] = 0  # the pad
    q += 1
    crc = 0xFFFF
    for i in range(q):
        crc = ((crc << 8) & 0xFFFF) ^ t[((crc >> 8) ^ r[i]) & 0xFF]
    r[q] = crc >> 8
    r[q + 1] = crc & 0xFF
    q += 2
    # COBS (a STATE is far below 254 bytes: one code per zero) and the delimiter
    code_pos = 0
    w = 1
    code = 1
    for i in range(q):
        b = r[i]
        if b == 0:
            d[code_pos] = code
            code_pos = w
            code = 1
        else:
            d[w] = b
            code += 1
        w += 1
    d[code_pos] = code
    d[w] = 0
    return w + 1


@micropython.viper
def sync_entry(buf, start: int, end: int, position: int, out) -> int:
    """SYNC ``{0: cycle, 1: setpoints, 2: resume}`` in its usual encoding, in one call
    (``protocol.device.decode_sync``): keys in that order, key 2 optional and ``false``/``true``/
    0/1, cycle any int head below 2**30, setpoints a byte string with a one-byte or direct length
    that is a whole number of entries. Returns 1 (OK: ``out`` [cycle, kappa, phi, resume]) or 0
    (HOLD: [cycle, -, -, resume]) exactly as the general decoder would; -2 for anything else
    (another encoding, or malformed): the general decoder decides then. The caller checks
    ``0 <= start <= end <= len(buf)``."""
    b = ptr8(buf)
    p = start
    if end - p < 5:
        return -2
    h = b[p]
    if h != 0xA2 and h != 0xA3:
        return -2
    if b[p + 1] != 0:
        return -2
    p += 2
    ai = b[p]
    p += 1
    if ai < 24:
        cycle = ai
    elif ai == 24:
        if p + 1 > end:
            return -2
        cycle = b[p]
        p += 1
    elif ai == 25:
        if p + 2 > end:
            return -2
        cycle = (b[p] << 8) | b[p + 1]
        p += 2
    elif ai == 26:
        if p + 4 > end or b[p] >= 0x40:
            return -2
        cycle = (b[p] << 24) | (b[p + 1] << 16) | (b[p + 2] << 8) | b[p + 3]
        p += 4
    else:
        return -2
    if p + 2 > end or b[p] != 1:
        return -2
    hb = b[p + 1]
    p += 2
    if hb >= 0x40 and hb < 0x58:
        ln = hb - 0x40
    elif hb == 0x58 and p < end:
        ln = b[p]
        p += 1
    else:
        return -2
    q = p
    p += ln
    if p > end or ln % 5:
        return -2
    resume = 0
    if h == 0xA3:
        if p + 2 != end or b[p] != 2:
            return -2
        v = b[p + 1]
        if v == 0xF5 or v == 1:
            resume = 1
        elif v != 0xF4 and v != 0:
            return -2
    elif p != end:
        return -2
    rc = 0
    q += 5 * position
    if q + 5 <= p:
        k = (b[q] << 16) | (b[q + 1] << 8) | b[q + 2]
        if k & 0x800000:
            k -= 0x1000000
        ph = (b[q + 3] << 8) | b[q + 4]
        if ph & 0x8000:
            ph -= 0x10000
        if k == -0x800000:  # SP_HOLD
            if ph:
                return -2  # the hold marker is exactly 80 00 00 00 00: malformed
        else:
            out[1] = k
            out[2] = ph
            rc = 1
    out[0] = cycle
    out[3] = resume
    return rc
