"""Fixed-point integer maths for the zero-allocation control cycle (MicroPython and CPython).

Every value in the hot path is a small int that stays within +-2**30, so that it is a MicroPython
small int on a 32-bit ESP32 as well (no heap object, no allocation). Units:

* angles: 1e-4 rad (``ANGLE_SCALE``); curvature: 1e-4 1/m; lengths: 1e-6 m (um);
* trigonometric values: Q14 (16384 = 1.0).

Accuracy (checked by tests/device against numpy): ``sin_q14``/``cos_q14`` within 1e-4 of the true
value for every angle; ``atan2_e4`` within 1.2e-4 rad (result resolution 1e-4 rad).
Products go through ``mulq``, which splits the factor so no partial product exceeds 2**28.
"""

try:
    from micropython import const
except ImportError:  # CPython (host-side tests, tooling)

    def const(x):
        return x


from array import array

Q_ONE = const(16384)  # 1.0 in Q14
ANGLE_PI = const(31416)  # pi in 1e-4 rad (rounded)
ANGLE_2PI = const(62832)  # 2 pi in 1e-4 rad (rounded)
ANGLE_HALF_PI = const(15708)
_TN = const(256)


def _build_tables():
    """Quarter-wave sine (Q14) and arctangent (1e-5 rad) tables, 257 entries each."""
    import math

    s = array("h", [0] * (_TN + 1))
    t = array("i", [0] * (_TN + 1))
    for i in range(_TN + 1):
        s[i] = int(math.floor(math.sin(i * (math.pi / 2) / _TN) * Q_ONE + 0.5))
        t[i] = int(math.floor(math.atan(i / _TN) * 100000 + 0.5))
    return s, t


_SIN, _ATAN = _build_tables()


def mulq(a, c, q):
    """Return round(a * c / 2**q) for |a| < 2**24, |c| < 2**16, 12 <= q <= 27 (error <= 1).

    The factor a is split into 12-bit halves so each partial product stays below 2**28.
    """
    hi = a >> 12
    lo = a & 4095
    r = q - 12
    if r:
        return ((hi * c + (1 << (r - 1))) >> r) + ((lo * c + (1 << (q - 1))) >> q)
    return hi * c + ((lo * c + (1 << (q - 1))) >> q)


def sin_q14(a):
    """sin of an angle in 1e-4 rad (any int within +-2**29), Q14."""
    a %= ANGLE_2PI
    quad = a // ANGLE_HALF_PI
    rem = a - quad * ANGLE_HALF_PI
    # position inside the quadrant with 16 bits: 8 table-index bits + 8 fraction bits
    p = ((rem << 16) + 7854) // ANGLE_HALF_PI
    if quad & 1:
        p = 65536 - p
    i = p >> 8
    if i >= _TN:
        v = _SIN[_TN]
    else:
        v0 = _SIN[i]
        v = v0 + (((_SIN[i + 1] - v0) * (p & 255) + 128) >> 8)
    if quad >= 2:
        return -v
    return v


def cos_q14(a):
    """cos of an angle in 1e-4 rad, Q14."""
    return sin_q14(a + ANGLE_HALF_PI)


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


def q_for(coeffs, limit=65535):
    """Largest Q shift in 12..27 so every |c| * 2**q stays below ``limit`` (boot time, floats ok).

    Raises ValueError when a coefficient is too large for the fixed-point scheme.
    """
    m = 0.0
    for c in coeffs:
        c = abs(c)
        if c > m:
            m = c
    q = 27
    while q >= 12:
        if m * (1 << q) < limit:
            return q
        q -= 1
    raise ValueError("coefficient %r too large for the fixed-point scheme" % m)


def to_q(c, q):
    """Float coefficient -> int with Q shift q (rounded)."""
    v = c * (1 << q)
    return int(v + 0.5) if v >= 0 else -int(-v + 0.5)
