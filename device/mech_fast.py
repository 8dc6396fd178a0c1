# ruff: noqa: F821 - ptr8/ptr32 are viper built-ins, resolved by the MicroPython compiler
"""Viper (machine code) versions of the Mechanism's cycle work (device/mechanism.py): measure
(positions -> kappa, phi), update (slew and servo targets) and the servo-target loop.

``mechanism`` imports this module where fxp uses ``fxp_fast`` (a native emitter: the ESP32's
xtensawin, the C3's rv32imc, the unix VM's x64) and calls these instead of its bytecode code,
which stays the reference (tests/device/test_fast_paths.py compares both on the VM). A call from
viper to another viper function costs about what a bytecode call does, so the per-servo
products (``fxp_fast.mulq``) are written out in the loops; the trigonometry stays calls.

Every value is within +-2**30 (Mechanism's checks). ``ptr32`` loads zero-extend on a 64-bit host,
so each signed load is sign-fixed (``| NEG`` when bit 30 is set): 32- and 64-bit words agree.
2**30 itself is no small int on a 32-bit port, so ``B30`` is made at run time, never a constant.
"""

import micropython
from fxp_fast import atan2_e4, cos_q20, mulq, sin_q20


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
    # fxp_fast.mulq written out below (a call per product cost more than the loop): its
    # shifts and rounding terms for q = qb and q = qi, computed once
    sb = qb - 16
    rb = 0
    if sb > 0:
        rb = 1 << (sb - 1)
    r8b = 1 << (qb - 9)
    r0b = 1 << (qb - 1)
    si = qi - 16
    ri = 0
    if si > 0:
        ri = 1 << (si - 1)
    r8i = 1 << (qi - 9)
    r0i = 1 << (qi - 1)
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
        # dl = -mulq(rel, back, qb)
        t = (rel >> 16) * back
        if sb > 0:
            t = (t + rb) >> sb
        elif sb < 0:
            t = t << (0 - sb)
        t += ((((rel >> 8) & 255) * back + r8b) >> (qb - 8)) + (((rel & 255) * back + r0b) >> qb)
        dl = 0 - t
        tn[i] = lum + dl
        # sx += mulq(-dl, ix[i], qi); sy += mulq(-dl, iy[i], qi)
        v = px[i]
        if v & B30:
            v |= NEG
        a = 0 - dl
        t = (a >> 16) * v
        if si > 0:
            t = (t + ri) >> si
        elif si < 0:
            t = t << (0 - si)
        sx += t + ((((a >> 8) & 255) * v + r8i) >> (qi - 8)) + (((a & 255) * v + r0i) >> qi)
        v = py[i]
        if v & B30:
            v |= NEG
        t = (a >> 16) * v
        if si > 0:
            t = (t + ri) >> si
        elif si < 0:
            t = t << (0 - si)
        sy += t + ((((a >> 8) & 255) * v + r8i) >> (qi - 8)) + (((a & 255) * v + r0i) >> qi)
    m.mx = sx
    m.my = sy
    # kappa, phi (Mechanism.measure after its loop): phi held while about straight
    if sx > -10 and sx < 10 and sy > -10 and sy < 10:  # _PHI_HOLD_EPS
        if sx < 0:
            sx = 0 - sx
        if sy < 0:
            sy = 0 - sy
        if sx > sy:
            m.kappa = sx
        else:
            m.kappa = sy
        return
    phi = int(atan2_e4(sy, sx))
    m.kappa = int(mulq(sx, int(cos_q20(phi)), 20)) + int(mulq(sy, int(sin_q20(phi)), 20))
    m.phi = phi


@micropython.viper
def update(m) -> int:
    """``Mechanism.update`` for Mechanism ``m`` (same integers, state and clamp bits): the slew
    of the commanded curvature vector towards the target, then ``servo_targets``."""
    tx = int(m.tx)
    ty = int(m.ty)
    cx = int(m.cx)
    cy = int(m.cy)
    dx = tx - cx
    dy = ty - cy
    st = int(m.step_whole)
    acc = int(m.step_acc) + int(m.step_frac)
    if acc >= 1000:
        acc -= 1000
        st += 1
    h = st >> 1
    flags = 0
    if dx >= 0 - h and dx <= h and dy >= 0 - h and dy <= h:
        cx = tx
        cy = ty
        acc = 0
    else:
        psi = int(atan2_e4(dy, dx))
        c = int(cos_q20(psi))
        s = int(sin_q20(psi))
        if int(mulq(dx, c, 20)) + int(mulq(dy, s, 20)) <= st:
            cx = tx
            cy = ty
            acc = 0
        else:
            cx += int(mulq(st, c, 20))
            cy += int(mulq(st, s, 20))
            if m.rate_excess:
                flags = 2  # CLAMP_RATE
    m.step_acc = acc
    m.cx = cx
    m.cy = cy
    if cx == tx and cy == ty:
        m.rate_excess = False
    return flags | int(servo_targets(m))


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
    # fxp_fast.mulq written out below, as in ``measure``: shifts and rounding terms for q = qt
    # and q = qs, and the byte split of cx, cy, computed once
    s_t = qt - 16
    r_t = 0
    if s_t > 0:
        r_t = 1 << (s_t - 1)
    r8t = 1 << (qt - 9)
    r0t = 1 << (qt - 1)
    s_s = qs - 16
    r_s = 0
    if s_s > 0:
        r_s = 1 << (s_s - 1)
    r8s = 1 << (qs - 9)
    r0s = 1 << (qs - 1)
    x2 = cx >> 16
    x1 = (cx >> 8) & 255
    x0 = cx & 255
    y2 = cy >> 16
    y1 = (cy >> 8) & 255
    y0 = cy & 255
    flags = 0
    for i in range(n):
        v = a_[i]
        if v & B30:
            v |= NEG
        w = b_[i]
        if w & B30:
            w |= NEG
        # dl = -(mulq(cx, ta[i], qt) + mulq(cy, tb[i], qt))
        t = x2 * v
        u = y2 * w
        if s_t > 0:
            t = (t + r_t) >> s_t
            u = (u + r_t) >> s_t
        elif s_t < 0:
            t = t << (0 - s_t)
            u = u << (0 - s_t)
        t += ((x1 * v + r8t) >> (qt - 8)) + ((x0 * v + r0t) >> qt)
        u += ((y1 * w + r8t) >> (qt - 8)) + ((y0 * w + r0t) >> qt)
        dl = 0 - (t + u)
        tc[i] = lum + dl
        # rel = mulq(-dl, spool_fwd, qs)
        a = 0 - dl
        t = (a >> 16) * fwd
        if s_s > 0:
            t = (t + r_s) >> s_s
        elif s_s < 0:
            t = t << (0 - s_s)
        rel = t + ((((a >> 8) & 255) * fwd + r8s) >> (qs - 8)) + (((a & 255) * fwd + r0s) >> qs)
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
