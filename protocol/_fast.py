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
    e = q  # every entry: a hold marker is exactly 80 00 00 00 00 (else the frame is malformed)
    while e < p:
        if b[e] == 0x80 and b[e + 1] == 0 and b[e + 2] == 0 and (b[e + 3] | b[e + 4]) != 0:
            return -2
        e += 5
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
        if k != -0x800000:  # not SP_HOLD (whose phi bytes are 0: checked above)
            out[1] = k
            out[2] = ph
            rc = 1
    out[0] = cycle
    out[3] = resume
    return rc


@micropython.viper
def relay_feed(data, start: int, end: int, out, st, good: int, raw, raw_len: int, table) -> int:
    """Cut-through step of ``protocol.relay.Relay.feed`` over data[start:end] in one call; the
    same contract and results as its bytecode twin ``protocol.relay_py.feed`` (state ``st``,
    array 'i', layout in relay.py). Returns the bytes written to ``out`` | relayed << 16. The
    caller checks the ranges (``out`` holds end - start + 8 bytes)."""
    s = ptr8(data)
    d = ptr8(out)
    t = ptr32(st)
    w = ptr8(raw)
    tb = ptr16(table)
    o = 0
    i = start
    relayed = 0
    while i < end:
        if t[6] == 1:  # passing the frame on, through a 3-byte hold-back
            run = t[0]
            nh = t[1]
            h0 = t[2]
            h1 = t[3]
            h2 = t[4]
            cnt = t[5]
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
            bad = 0
            if hit:
                t[6] = 0
                t[7] = 0
                t[16] = 0
                hop = t[12]
                if (
                    good
                    and i == end
                    and nh == 3
                    and run == 0
                    and raw_len >= 8
                    and ((w[2] + 1) & 0xFF) == hop
                ):
                    p = raw_len - 2
                    old = w[2]
                    w[2] = hop
                    c = 0xFFFF
                    for k in range(p):
                        c = ((c << 8) & 0xFFFF) ^ tb[((c >> 8) ^ w[k]) & 0xFF]
                    w[2] = old
                    hi = c >> 8
                    lo = c & 0xFF
                    if hi and lo:
                        d[o] = 3
                        d[o + 1] = hi
                        d[o + 2] = lo
                    elif hi:
                        d[o] = 2
                        d[o + 1] = hi
                        d[o + 2] = 1
                    elif lo:
                        d[o] = 1
                        d[o + 1] = 2
                        d[o + 2] = lo
                    else:
                        d[o] = 1
                        d[o + 1] = 1
                        d[o + 2] = 1
                    d[o + 3] = 0
                    o += 4
                    relayed = 1
                    t[14] = t[14] + 1
                else:
                    bad = 1
            elif cnt > 252:  # MAX_ENCODED: longer than any frame
                t[16] = 0
                t[6] = 2
                bad = 1
            if bad:  # end what was sent as invalid COBS
                if run == 0:
                    d[o] = 5
                    o += 1
                d[o] = 0
                o += 1
                t[15] = t[15] + 1
            continue
        b = s[i]
        i += 1
        if b == 0:
            t[6] = 0
            t[7] = 0
            continue
        if t[6] != 0:
            continue  # not relayed: wait for the delimiter
        n = t[7]
        t[8 + n] = b
        t[7] = n + 1
        if n < 3:
            continue
        # the first four wire bytes: relay this frame?
        t[6] = 2
        c0 = t[8]
        flags = t[10]
        if c0 < 3 or t[9] != 2 or flags & 0xFC:  # zero in ver/flags, version, unknown/LOCAL
            continue
        if t[13]:
            if not (flags & 0x01):
                continue
        elif (flags & 0x01) or not (flags & 0x02):
            continue
        if c0 == 3:
            c3 = t[11]
            if c3 > 251:
                continue
            d[o] = c3 + 3
            t[0] = c3 - 1
            t[12] = 1
        else:
            if t[11] == 255:
                continue
            d[o] = c0
            t[0] = c0 - 4
            t[12] = t[11] + 1
        d[o + 1] = t[9]
        d[o + 2] = flags
        d[o + 3] = t[12]
        o += 4
        t[1] = 0
        t[5] = 4
        t[6] = 1
        t[16] = 1
    return o | (relayed << 16)


@micropython.viper
def scan(data, start: int, end: int, buf, st, table) -> int:
    """``protocol.frame.FrameReader``'s byte loop in one call: collect data[start:end] into
    ``buf`` until a delimiter, then decode the COBS in place and check length, pad and CRC; stop
    after the first good frame. The same contract and results as its bytecode twin
    ``protocol.frame._scan_py`` (state ``st``, array 'i', layout in frame.py). Returns the next
    position << 1 | 1 if a frame completed. The caller checks ``0 <= start <= end <= len(data)``
    (``st`` holds len(buf))."""
    s = ptr8(data)
    b = ptr8(buf)
    t = ptr32(st)
    tb = ptr16(table)
    cap = t[9]
    n = t[0]
    i = start
    while i < end:
        c = s[i]
        i += 1
        if c != 0:
            if n < cap:
                b[n] = c
                n += 1
            else:
                t[1] = 1
            continue
        if t[1]:  # the frame overflowed the buffer
            t[6] = t[6] + 1
            t[1] = 0
            n = 0
            continue
        if n == 0:
            continue  # idle padding
        # COBS, in place (the output never overtakes the input)
        q = 0
        m = 0
        while q < n:
            code = b[q]
            q += 1
            stop = q + code - 1
            if stop > n:
                m = -1
                break
            while q < stop:
                b[m] = b[q]
                m += 1
                q += 1
            if code != 0xFF and q < n:
                b[m] = 0
                m += 1
        n = 0
        pe = -1
        if m >= 7 and m <= t[2]:  # HEADER_LEN + CRC_LEN .. max_frame
            if b[0] == 1:  # LEGACY_VERSION: no pad
                pe = m - 2
            elif m >= 8 and b[m - 3] == 0:  # MIN_FRAME, the pad
                pe = m - 3
        if pe < 0:
            t[5] = t[5] + 1
            continue
        p = m - 2
        crc = 0xFFFF
        for k in range(p):
            crc = ((crc << 8) & 0xFFFF) ^ tb[((crc >> 8) ^ b[k]) & 0xFF]
        if crc != ((b[p] << 8) | b[p + 1]):
            t[4] = t[4] + 1
            continue
        t[7] = m
        t[8] = pe
        t[3] = t[3] + 1
        t[0] = 0
        return (i << 1) | 1
    t[0] = n
    return i << 1


@micropython.viper
def scan_relay(rd, rl, data, start: int, end: int, out, table) -> int:
    """``FrameReader.scan`` then ``Relay.feed`` over what it consumed, in one call (a segment's
    receive step, device/segment.py ``_drain``): the same machine-code loops (``scan``,
    ``relay_feed``) and the same attributes set on the reader ``rd`` and the relay ``rl`` as the
    two methods, without their bytecode. Returns the next position | bytes to send << 12 | 1 << 24
    if a frame completed. The caller checks ``0 <= start <= end <= len(data)`` and that ``out``
    holds end - start + 8 bytes; both below 4096."""
    raw = rd.raw
    st = rd.st
    r = int(scan(data, start, end, raw, st, table))
    nxt = r >> 1
    ok = r & 1
    n = 0
    if ok:
        b = ptr8(raw)
        t = ptr32(st)
        rd.ver = b[0]
        rd.flags = b[1]
        rd.hop = b[2]
        rd.mtype = b[3]
        rd.seq = b[4]
        n = t[7]
        rd.raw_len = n
        rd.payload_end = t[8]
        rd.ready = True
    else:
        rd.ready = False
    ls = rl.st
    f = int(relay_feed(data, start, nxt, out, ls, ok, raw, n, table))
    rl.relayed = f & 0x10000
    rl.busy = int(ptr32(ls)[16])
    return nxt | ((f & 0xFFFF) << 12) | (ok << 24)
