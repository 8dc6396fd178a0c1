# ruff: noqa: F821 - ptr32 is a viper built-in, resolved by the MicroPython compiler
"""Viper (machine code) versions of the control cycle's fixed-point maths (device/fxp.py).

``fxp`` imports this module at its end and, where it compiles (MicroPython with a native emitter:
the ESP32's xtensawin, the C3's rv32imc, the unix VM's x64), binds its ``mulq``, ``sin_q20``,
``cos_q20`` and ``atan2_e4`` to these; elsewhere (CPython, a port without an emitter) the plain
versions stay. Same integers out for every input in the documented ranges, checked against the
plain versions on the VM by tests/device/test_device_mapping.py. On a board a bytecode ``mulq``
call costs about as much as an interpreted loop of a dozen steps; the machine-code one, a call.

Viper ints are machine words: 32 bits on the boards, 64 on the emulator's host. Every value here
stays within +-2**30 and every product below 2**31 (fxp.py's argument ranges), so both give the
same results. ``ptr32`` loads zero-extend on a 64-bit host; the tables hold only non-negative
values, so no sign fix is needed. ``//`` and ``%`` are Python's floor operations (viper calls the
small-int helpers), as in the plain code.
"""

import micropython

_SIN = None  # fxp's tables, handed over by init() (fxp imports this module)
_ATAN = None


def init(sin_table, atan_table):
    global _SIN, _ATAN
    _SIN = sin_table
    _ATAN = atan_table


@micropython.viper
def mulq(a: int, c: int, q: int) -> int:
    """fxp.mulq: round(a * c / 2**q) for |a| < 2**24, |c| < 2**21, 12 <= q <= 29."""
    hi = a >> 16
    s = q - 16
    if s > 0:
        t = (hi * c + (1 << (s - 1))) >> s
    elif s == 0:
        t = hi * c
    else:
        t = (hi * c) << (0 - s)
    return (
        t
        + ((((a >> 8) & 255) * c + (1 << (q - 9))) >> (q - 8))
        + (((a & 255) * c + (1 << (q - 1))) >> q)
    )


@micropython.viper
def sin_q20(a: int) -> int:
    """fxp.sin_q20: sin of an angle in 1e-4 rad (within +-2**29), Q20."""
    t = ptr32(_SIN)
    a = a % 62832  # ANGLE_2PI
    quad = a // 15708  # ANGLE_HALF_PI
    rem = a - quad * 15708
    if quad & 1:
        rem = 15708 - rem
    x = rem * 256
    i = x // 15708
    if i >= 256:
        v = int(t[256])
    else:
        v0 = int(t[i])
        f = x - i * 15708
        v = v0 + ((int(t[i + 1]) - v0) * f + 7854) // 15708
    if quad >= 2:
        return 0 - v
    return v


@micropython.viper
def cos_q20(a: int) -> int:
    """fxp.cos_q20: cos of an angle in 1e-4 rad, Q20."""
    return int(sin_q20(a + 15708))


@micropython.viper
def atan2_e4(y: int, x: int) -> int:
    """fxp.atan2_e4: atan2(y, x) in 1e-4 rad in (-pi, pi]; 0 for (0, 0); |x|, |y| < 2**29."""
    ax = x
    if x < 0:
        ax = 0 - x
    ay = y
    if y < 0:
        ay = 0 - y
    if ax == 0 and ay == 0:
        return 0
    while ax >= 32768 or ay >= 32768:
        ax = ax >> 1
        ay = ay >> 1
    swap = 0
    if ay <= ax:
        r = ((ay << 15) + (ax >> 1)) // ax
    else:
        r = ((ax << 15) + (ay >> 1)) // ay
        swap = 1
    tb = ptr32(_ATAN)
    i = r >> 7
    if i >= 256:
        t = int(tb[256])
    else:
        t0 = int(tb[i])
        t = t0 + (((int(tb[i + 1]) - t0) * (r & 127) + 64) >> 7)
    t = (t + 5) // 10
    if swap:
        t = 15708 - t
    if x < 0:
        t = 31416 - t
    if y < 0:
        t = 0 - t
        if t == -31416:
            t = 31416
    return t
