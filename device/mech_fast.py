# ruff: noqa: F821 - ptr8/ptr32 are viper built-ins, resolved by the MicroPython compiler
"""Viper (machine code) versions of the Mechanism's per-servo loops (device/mechanism.py).

``mechanism`` imports this module where fxp uses ``fxp_fast`` (a native emitter: the ESP32's
xtensawin, the C3's rv32imc, the unix VM's x64) and calls these instead of its bytecode loops,
which stay the reference (tests/device/test_fast_paths.py compares both on the VM).

Every value is within +-2**30 (Mechanism's checks). ``ptr32`` loads zero-extend on a 64-bit host,
so each signed load is sign-fixed (``| NEG`` when bit 30 is set): 32- and 64-bit words agree.
2**30 itself is no small int on a 32-bit port, so ``B30`` is made at run time, never a constant.
"""

import micropython
from fxp_fast import mulq


@micropython.viper
def measure(m, pos):
    """The per-servo loop of ``Mechanism.measure`` for Mechanism ``m`` (same integers): joint
    angles and tendon lengths from the servo positions ``pos`` (array 'i'), and the least-squares
    curvature vector (``m.mx``, ``m.my``). Arrays are the Mechanism's own (``dir``: 'b', +-1)."""
    B30 = 1
    B30 <<= 30
    NEG = 0 - B30
    p = ptr32(pos)
    z = ptr32(m.zero)
    dr = ptr8(m.dir)
    lo = ptr32(m.mlo)
    hi = ptr32(m.mhi)
    jn = ptr32(m.joint)
    tn = ptr32(m.tendon)
    px = ptr32(m.ix)
    py = ptr32(m.iy)
    n = int(m.n)
    back = int(m.spool_back)
    qb = int(m.q_b)
    lum = int(m.length_um)
    qi = int(m.q_i)
    sx = 0
    sy = 0
    for i in range(n):
        rel = p[i]
        if rel & B30:
            rel |= NEG
        v = z[i]
        if v & B30:
            v |= NEG
        rel -= v
        v = lo[i]
        if v & B30:
            v |= NEG
        if rel < v:
            rel = v
        else:
            v = hi[i]
            if v & B30:
                v |= NEG
            if rel > v:
                rel = v
        if dr[i] >= 128:  # -1 as an unsigned byte
            rel = 0 - rel
        jn[i] = rel
        dl = 0 - int(mulq(rel, back, qb))
        tn[i] = lum + dl
        v = px[i]
        if v & B30:
            v |= NEG
        sx += int(mulq(0 - dl, v, qi))
        v = py[i]
        if v & B30:
            v |= NEG
        sy += int(mulq(0 - dl, v, qi))
    m.mx = sx
    m.my = sy


@micropython.viper
def servo_targets(m) -> int:
    """``Mechanism._servo_targets`` for Mechanism ``m`` (same integers and clamp bit): tendon
    lengths and servo targets for its commanded curvature vector (cx, cy). Returns CLAMP_SERVO
    (4) if a target was limited to its range."""
    B30 = 1
    B30 <<= 30
    NEG = 0 - B30
    cx = int(m.cx)
    cy = int(m.cy)
    a_ = ptr32(m.ta)
    b_ = ptr32(m.tb)
    dr = ptr8(m.dir)
    lo = ptr32(m.amin)
    hi = ptr32(m.amax)
    z = ptr32(m.zero)
    tc = ptr32(m.tendon_cmd)
    st = ptr32(m.servo_target)
    n = int(m.n)
    qt = int(m.q_t)
    qs = int(m.q_s)
    fwd = int(m.spool_fwd)
    lum = int(m.length_um)
    flags = 0
    for i in range(n):
        v = a_[i]
        if v & B30:
            v |= NEG
        w = b_[i]
        if w & B30:
            w |= NEG
        dl = 0 - (int(mulq(cx, v, qt)) + int(mulq(cy, w, qt)))
        tc[i] = lum + dl
        rel = int(mulq(0 - dl, fwd, qs))
        if dr[i] >= 128:
            rel = 0 - rel
        v = lo[i]
        if v & B30:
            v |= NEG
        if rel < v:
            rel = v
            flags = 4
        else:
            v = hi[i]
            if v & B30:
                v |= NEG
            if rel > v:
                rel = v
                flags = 4
        v = z[i]
        if v & B30:
            v |= NEG
        st[i] = v + rel
    return flags
