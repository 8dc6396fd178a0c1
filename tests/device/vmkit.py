"""VM-side test kit (runs on MicroPython): a loopback HAL and helpers to drive a Segment in-process.

Bytes are fed into the upstream/downstream port buffers, time is advanced by hand, and what the
segment writes to each port is collected, so the tests see exactly the wire traffic.
"""

import binascii
import time

import config

try:  # a board's UART copies in C: the kit copies in machine code where it can, so the
    # firmware benchmark does not charge the test port's byte loop to the firmware
    from protocol._fast import move as _move
except Exception:

    def _move(src, s0, dst, d0, n):
        for k in range(n):
            dst[d0 + k] = src[s0 + k]


_CAP = 2048


class BufUart:
    """A UART backed by preallocated buffers (no allocation on read or write)."""

    def __init__(self):
        self.inbuf = bytearray(_CAP)
        self.r = 0
        self.w = 0
        self.out = bytearray(_CAP)
        self.ow = 0
        self.lost = 0
        self.gate = -1  # >= 0: only bytes before this input offset are readable (allow())
        self.total = 0  # bytes written so far

    def feed(self, data):
        if self.r == self.w and self.gate < 0:
            self.r = self.w = 0
        n = len(data)
        self.inbuf[self.w : self.w + n] = data
        self.w += n

    def allow(self, n):
        """Make ``n`` more fed bytes readable (gated mode, no allocation)."""
        if self.gate < 0:
            self.gate = self.r
        self.gate += n

    def readinto(self, buf):
        n = (self.w if self.gate < 0 else self.gate) - self.r
        if n <= 0:
            return None
        m = len(buf)
        if n > m:
            n = m
        r = self.r
        _move(self.inbuf, r, buf, 0, n)
        self.r = r + n
        return n

    def write(self, buf, n=-1):
        if n < 0 or n > len(buf):  # as a board's stream write: MIN(len(buf), n) (py/stream.c)
            n = len(buf)
        self.total += n
        o = self.ow
        if o + n > _CAP:
            self.lost += n  # tests take() or discard() often enough; take() reports a loss
            return n
        _move(buf, 0, self.out, o, n)
        self.ow = o + n
        return n

    def any(self):
        """Bytes readable now (machine.UART.any)."""
        n = (self.w if self.gate < 0 else self.gate) - self.r
        return n if n > 0 else 0

    def take(self):
        if self.lost:
            raise RuntimeError("test UART buffer overflowed: " + str(self.lost) + " bytes lost")
        b = bytes(self.out[: self.ow])
        self.ow = 0
        return b

    def discard(self):
        self.ow = 0
        self.lost = 0


class LoopHal:
    platform = "loop"
    default_driver = "emulated"

    def __init__(self, uid="00aa11bb22cc"):
        self.up = BufUart()
        self.down = BufUart()
        self.t = 0
        self._uid = uid
        self.faults_spec = None
        self.idle_us = 0

    def uid(self):
        return self._uid

    def ticks_ms(self):
        return self.t & 0x3FFFFFFF

    def ticks_us(self):
        return time.ticks_us()

    def ticks_diff(self, a, b):
        return time.ticks_diff(a, b)

    def wait(self, ms):
        pass

    def rx_any(self):
        return (1 if self.up.any() else 0) | (2 if self.down.any() else 0)

    def servo_uart(self, b):
        raise ValueError("no servo uart on the loopback HAL")

    def pwm(self, pin, freq):
        return LoopPwm(pin, freq)


class LoopPwm:
    """A PWM output as ``machine.PWM`` (``duty_ns`` is a C call on the board): keeps the pulse."""

    def __init__(self, pin, freq):
        self.pin = pin
        self.freq = freq
        self.ns = 0

    def duty_ns(self, ns):
        self.ns = ns


def make(data=None, faults=None, tick_ms=5, unconfigured=False):
    """(hal, seg) for a config dict (None: defaults) with the emulated servo bus."""
    import gc

    hal = LoopHal()
    cfg = config.Config(None if unconfigured else (data or {}), "emulated")
    gc.collect()
    # the servo drivers and the segment are compiled after the configuration, in main.build's
    # order: the board rules (protocol/boards.py) come and go before them
    import servos
    from segment import Segment

    gc.collect()
    bus = servos.make(cfg.driver, cfg, hal)
    if faults:
        bus.set_faults(faults)
    seg = Segment(hal, cfg, bus, tick_ms)
    return hal, seg


def run(hal, seg, ms):
    """Advance ``ms`` milliseconds in ticks, polling the ports before every tick."""
    end = hal.t + ms
    while hal.t < end:
        hal.t += seg.tick_ms
        seg.poll()
        seg.tick(hal.ticks_ms())


def hexs(b):
    return binascii.hexlify(b).decode()
