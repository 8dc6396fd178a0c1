"""Fixed-point integer maths for the zero-allocation control cycle (MicroPython and CPython).

Every value in the hot path is a small int that stays within +-2**30, so that it is a MicroPython
small int on a 32-bit ESP32 as well (no heap object, no allocation). Units:

* angles: 1e-4 rad (``ANGLE_SCALE``); curvature: 1e-4 1/m; lengths: 1e-6 m (um);
* trigonometric values: Q20 (``sin_q20``/``cos_q20``, 2**20 = 1.0; the hot path) or Q14.

Accuracy (checked by tests/device against numpy): ``sin_q20``/``cos_q20`` within 1e-5 of the true
value over (-pi, pi] and |(cos, sin)| = 1 within 6e-6 for every angle (a curvature of 100 1/m
keeps its magnitude within 6e-4 1/m), ``sin_q14``/``cos_q14`` within 1e-4 over +-20 rad;
``atan2_e4`` within 1.2e-4 rad (result resolution 1e-4 rad). Products go through ``mulq``,
which splits the int factor into 8-bit pieces so no partial product exceeds 2**29 while the
coefficient keeps 21 bits.
"""

try:
    from micropython import const
except ImportError:  # CPython (host-side tests, tooling)

    def const(x):
        return x


from array import array

Q_ONE = const(16384)  # 1.0 in Q14
Q20_ONE = const(1048576)  # 1.0 in Q20
ANGLE_PI = const(31416)  # pi in 1e-4 rad (rounded)
ANGLE_2PI = const(62832)  # 2 pi in 1e-4 rad (rounded)
ANGLE_HALF_PI = const(15708)
_TN = const(256)


def _build_tables():
    """Quarter-wave sine (Q20) and arctangent (1e-5 rad) tables, 257 entries each."""
    import math

    s = array("i", [0] * (_TN + 1))
    t = array("i", [0] * (_TN + 1))
    for i in range(_TN + 1):
        # entry i at i/256 of the integer quadrant (15708e-4 rad), so sin_q20 interpolates
        # straight from the 1e-4 rad input without a second rounding of the position
        s[i] = int(math.floor(math.sin(i * ANGLE_HALF_PI * 1e-4 / _TN) * Q20_ONE + 0.5))
        t[i] = int(math.floor(math.atan(i / _TN) * 100000 + 0.5))
    return s, t


_SIN, _ATAN = _build_tables()


def mulq(a, c, q):
    """Return round(a * c / 2**q) for |a| < 2**24, |c| < 2**21, 12 <= q <= 29 (error <= 1.5).

    ``a`` is split into a signed top byte and two low bytes, so each partial product stays below
    2**29 (a small int on a 32-bit MCU) while the coefficient keeps 21 significant bits
    (relative precision ~1e-6 instead of the 16 bits a two-way split allows).
    """
    hi = a >> 16
    s = q - 16
    if s > 0:
        t = (hi * c + (1 << (s - 1))) >> s
    elif s == 0:
        t = hi * c
    else:
        t = (hi * c) << -s  # below |a * c| / 2**q + |c|: bounded by the result's own range
    return (
        t
        + ((((a >> 8) & 255) * c + (1 << (q - 9))) >> (q - 8))
        + (((a & 255) * c + (1 << (q - 1))) >> q)
    )


def sin_q20(a):
    """sin of an angle in 1e-4 rad (any int within +-2**29), Q20."""
    a %= ANGLE_2PI
    quad = a // ANGLE_HALF_PI
    rem = a - quad * ANGLE_HALF_PI
    if quad & 1:
        rem = ANGLE_HALF_PI - rem
    x = rem * _TN  # table position = x / ANGLE_HALF_PI, interpolated exactly (x < 2**22)
    i = x // ANGLE_HALF_PI
    if i >= _TN:
        v = _SIN[_TN]
    else:
        v0 = _SIN[i]
        f = x - i * ANGLE_HALF_PI
        v = v0 + ((_SIN[i + 1] - v0) * f + 7854) // ANGLE_HALF_PI
    if quad >= 2:
        return -v
    return v


def cos_q20(a):
    """cos of an angle in 1e-4 rad, Q20."""
    return sin_q20(a + ANGLE_HALF_PI)


def sin_q14(a):
    """sin of an angle in 1e-4 rad, Q14 (rounded from ``sin_q20``)."""
    return (sin_q20(a) + 32) >> 6


def cos_q14(a):
    """cos of an angle in 1e-4 rad, Q14."""
    return (sin_q20(a + ANGLE_HALF_PI) + 32) >> 6


def atan2_e4(y, x):
    """atan2(y, x) in 1e-4 rad in (-pi, pi]; 0 for (0, 0). Inputs |x|, |y| < 2**29."""
    ax = -x if x < 0 else x
    ay = -y if y < 0 else y
    if ax == 0 and ay == 0:
        return 0
    # keep the larger magnitude below 2**15 so (small << 15) stays below 2**30
    while ax >= 32768 or ay >= 32768:
        ax >>= 1
        ay >>= 1
    if ay <= ax:
        r = ((ay << 15) + (ax >> 1)) // ax
        swap = False
    else:
        r = ((ax << 15) + (ay >> 1)) // ay
        swap = True
    # r = small/large in Q15 [0, 1]: 8 table-index bits + 7 fraction bits, linear interpolation
    i = r >> 7
    if i >= _TN:
        t = _ATAN[_TN]
    else:
        t0 = _ATAN[i]
        t = t0 + (((_ATAN[i + 1] - t0) * (r & 127) + 64) >> 7)
    t = (t + 5) // 10  # 1e-5 rad -> 1e-4 rad
    if swap:
        t = ANGLE_HALF_PI - t
    if x < 0:
        t = ANGLE_PI - t
    if y < 0:
        t = -t
        if t == -ANGLE_PI:
            t = ANGLE_PI
    return t


def wrap_angle(a):
    """Wrap an angle in 1e-4 rad into (-pi, pi]."""
    a %= ANGLE_2PI
    if a > ANGLE_PI:
        a -= ANGLE_2PI
    return a


def q_for(coeffs, limit=(1 << 21) - 1):
    """Largest Q shift in 12..29 so every |c| * 2**q stays below ``limit`` (boot time, floats ok).

    Raises ValueError when a coefficient is too large for the fixed-point scheme.
    """
    m = 0.0
    for c in coeffs:
        c = abs(c)
        if c > m:
            m = c
    q = 29
    while q >= 12:
        if m * (1 << q) < limit:
            return q
        q -= 1
    raise ValueError("coefficient %r too large for the fixed-point scheme" % m)


def to_q(c, q):
    """Float coefficient -> int with Q shift q (rounded)."""
    v = c * (1 << q)
    return int(v + 0.5) if v >= 0 else -int(-v + 0.5)


# machine-code versions where the VM has a native emitter (device/fxp_fast.py); the plain ones
# above stay the reference, and the only ones on CPython or a port without an emitter
_plain = (mulq, sin_q20, cos_q20, atan2_e4)
try:
    import gc

    gc.collect()  # compiled from source (tests on the VM), it needs contiguous heap: start clean
    import fxp_fast

    fxp_fast.init(_SIN, _ATAN)
    mulq = fxp_fast.mulq
    sin_q20 = fxp_fast.sin_q20
    cos_q20 = fxp_fast.cos_q20
    atan2_e4 = fxp_fast.atan2_e4
except Exception:  # ImportError on CPython; a compile error on a port without viper
    pass
