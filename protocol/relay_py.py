"""The cut-through step in plain Python, for interpreters without the viper emitter
(``protocol.relay`` uses ``protocol._fast.relay_feed`` where it can)."""


def relay(data, i, end, out, o, st):
    """The hold-back loop of ``feed``: pass data[i:end] to out[o:] through a 3-byte hold-back
    until a 0x00. ``st``: [run, held, h0, h1, h2, count, ...]; ``run`` counts the data bytes left
    in the current COBS run of what was passed on. Leaves the next position in st[17] and the
    output length in st[18] (no tuple: this runs on boards without viper); returns 1 if it
    stopped at a delimiter."""
    run = st[0]
    nh = st[1]
    h0 = st[2]
    h1 = st[3]
    h2 = st[4]
    cnt = st[5]
    hit = 0
    while i < end:
        b = data[i]
        i += 1
        if b == 0:
            hit = 1
            break
        cnt += 1
        if nh == 3:
            out[o] = h0
            o += 1
            run = h0 - 1 if run == 0 else run - 1
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
    st[0] = run
    st[1] = nh
    st[2] = h0
    st[3] = h1
    st[4] = h2
    st[5] = cnt
    st[17] = i
    st[18] = o
    return hit


def feed(data, start, end, out, st, good, raw, raw_len, table):
    """Bytecode twin of ``protocol._fast.relay_feed`` (same contract, same results): the whole
    cut-through step of ``Relay.feed`` over data[start:end], state in ``st`` (relay.py's layout)."""
    o = 0
    i = start
    relayed = 0
    while i < end:
        if st[6] == 1:  # passing the frame on
            hit = relay(data, i, end, out, o, st)
            i = st[17]
            o = st[18]
            if hit:  # the delimiter: the CRC for the new hop if the reader accepted it
                st[6] = 0
                st[7] = 0
                st[16] = 0
                if good and i == end and st[1] == 3 and st[0] == 0 and raw_len >= 8:
                    if (raw[2] + 1) & 0xFF == st[12]:
                        o = _crc_out(raw, raw_len, st[12], out, o, table)
                        relayed = 1
                        st[14] += 1
                        continue
                o = _invalid(out, o, st)
            elif st[5] > 252:  # MAX_ENCODED: longer than any frame
                st[16] = 0
                o = _invalid(out, o, st)
                st[6] = 2
            continue
        b = data[i]
        i += 1
        if b == 0:
            st[6] = 0
            st[7] = 0
            continue
        if st[6] == 0:  # collecting the first four wire bytes
            n = st[7]
            st[8 + n] = b
            st[7] = n + 1
            if n == 3:
                o = _start(out, o, st)
    return o | relayed << 16


def _start(out, o, st):
    c0 = st[8]
    st[6] = 2  # not relayed unless all below holds
    if c0 < 3 or st[9] != 2:  # a zero in ver/flags, or another version
        return o
    flags = st[10]
    if flags & 0xF8 or flags & 0x04:  # unknown bits, LOCAL
        return o
    if st[13]:
        if not flags & 0x01:
            return o
    elif flags & 0x01 or not flags & 0x02:
        return o
    if c0 == 3:  # hop 0: raw 2 is a zero, the fourth byte codes the run after it
        c3 = st[11]
        if c3 > 251:
            return o
        out[o] = c3 + 3
        run = c3 - 1
        st[12] = 1
    else:
        if st[11] == 255:
            return o  # the hop would wrap to 0
        out[o] = c0
        run = c0 - 4
        st[12] = st[11] + 1
    out[o + 1] = st[9]
    out[o + 2] = flags
    out[o + 3] = st[12]
    st[0] = run
    st[1] = 0
    st[5] = 4
    st[6] = 1
    st[16] = 1
    return o + 4


def _crc_out(raw, raw_len, hop, out, o, table):
    p = raw_len - 2
    old = raw[2]
    raw[2] = hop
    c = 0xFFFF
    for k in range(p):
        c = ((c << 8) & 0xFFFF) ^ table[((c >> 8) ^ raw[k]) & 0xFF]
    raw[2] = old
    hi = c >> 8
    lo = c & 0xFF
    if hi and lo:
        out[o] = 3
        out[o + 1] = hi
        out[o + 2] = lo
    elif hi:
        out[o] = 2
        out[o + 1] = hi
        out[o + 2] = 1
    elif lo:
        out[o] = 1
        out[o + 1] = 2
        out[o + 2] = lo
    else:
        out[o] = 1
        out[o + 1] = 1
        out[o + 2] = 1
    out[o + 3] = 0
    return o + 4


def _invalid(out, o, st):
    """End what was sent as invalid COBS (inside a run the delimiter comes too early; at a code
    position a code claiming 4 more bytes goes first)."""
    if st[0] == 0:
        out[o] = 5
        o += 1
    out[o] = 0
    st[15] += 1
    return o + 1
