"""CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no xorout), table driven.

Chosen over CRC-32 because its value stays a small int on a 32-bit MicroPython build (no heap
allocation in the frame path); see docs/protocol.md "CRC" for the error-detection argument.
Check value: crc16(b"123456789") == 0x29B1.
"""

from array import array

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


_POLY = const(0x1021)
CRC_INIT = const(0xFFFF)


def _make_table():
    t = array("H", bytes(512))
    for i in range(256):
        c = i << 8
        for _ in range(8):
            c = ((c << 1) ^ _POLY) if c & 0x8000 else (c << 1)
        t[i] = c & 0xFFFF
    return t


_TABLE = _make_table()


def crc16(buf, start=0, end=-1, crc=CRC_INIT):
    """CRC of ``buf[start:end]`` (end -1: to the end), continuing from ``crc``. No allocation."""
    if end < 0:
        end = len(buf)
    if start < 0 or start > end or end > len(buf):
        raise IndexError("crc16 range outside the buffer")
    t = _TABLE
    if _fast_crc is not None:
        return _fast_crc(buf, start, end, crc, t)
    for i in range(start, end):
        crc = ((crc << 8) & 0xFFFF) ^ t[((crc >> 8) ^ buf[i]) & 0xFF]
    return crc


# Machine-code loop on MicroPython ports with the viper emitter (protocol/_fast.py); the check
# value guards against a miscompiled emitter. Set to None to force the pure-Python loop.
try:
    from protocol import _fast

    _fast_crc = _fast.crc16 if _fast.crc16(b"123456789", 0, 9, CRC_INIT, _TABLE) == 0x29B1 else None
except Exception:  # ImportError on CPython; SyntaxError/ValueError where viper is unavailable
    _fast_crc = None
