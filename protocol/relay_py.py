"""The cut-through byte loop in plain Python, for interpreters without the viper emitter
(``protocol.relay`` uses ``protocol._fast.relay`` where it can)."""


def relay(data, i, end, out, o, st):
    """Bytecode twin of ``protocol._fast.relay`` (same contract, same results)."""
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
    return (i << 10) | (hit << 9) | o
