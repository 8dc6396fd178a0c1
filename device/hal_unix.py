"""HAL of the MicroPython unix port: UARTs are ptys, servos are emulated (the emulator's contract).

Environment (docs/architecture.md, "Running firmware on the unix port"): ``UCR_UP_PORT`` and
``UCR_DOWN_PORT`` (pty paths; a missing one is an unconnected port), ``UCR_UID`` (hex unique id),
``UCR_FAULTS`` (optional fault injection spec for the emulated servos, see servos/emulated.py).
A pty is opened with ``open(path, "r+b")`` and put in raw mode with VMIN = VTIME = 0, so
``readinto`` returns what is there (0 when nothing) instead of blocking.
"""

import os
import select
import termios
import time

_TMASK = 0x3FFFFFFF
_VTIME = 5  # indexes into the c_cc list of tcgetattr (Linux)
_VMIN = 6

PLATFORM = "unix"
DEFAULT_DRIVER = "emulated"


class PtyUart:
    """A pty opened as a UART: ``readinto(buf) -> n or None``, ``write(buf[, n])``."""

    def __init__(self, path):
        self.path = path
        self.f = open(path, "r+b")
        fd = self.f.fileno()
        termios.setraw(fd)
        attrs = termios.tcgetattr(fd)
        attrs[6][_VMIN] = 0
        attrs[6][_VTIME] = 0
        termios.tcsetattr(fd, termios.TCSANOW, attrs)

    def readinto(self, buf):
        try:
            n = self.f.readinto(buf)
        except OSError:
            return None  # peer gone (EIO on a closed pty master): nothing to read
        return n if n else None

    def write(self, buf, n=-1):
        try:
            if n < 0:
                return self.f.write(buf)
            return self.f.write(buf, n)
        except OSError:
            return 0  # unplugged link: the bytes are lost, as on a wire


class NullUart:
    """An unconnected port: never receives, swallows writes."""

    f = None

    def readinto(self, buf):
        return None

    def write(self, buf, n=-1):
        return len(buf) if n < 0 else n


class Hal:
    """Unix-port HAL: pty UARTs, select.poll wait, monotonic ms ticks, emulated servo bus."""

    platform = PLATFORM
    default_driver = DEFAULT_DRIVER

    def __init__(self, cfg_pins=None):
        up = os.getenv("UCR_UP_PORT")
        down = os.getenv("UCR_DOWN_PORT")
        self.up = PtyUart(up) if up else NullUart()
        self.down = PtyUart(down) if down else NullUart()
        self.poller = select.poll()
        for u in (self.up, self.down):
            if u.f is not None:
                self.poller.register(u.f, select.POLLIN)
        self.faults_spec = os.getenv("UCR_FAULTS")
        self._t0 = time.ticks_ms()

    def uid(self):
        u = os.getenv("UCR_UID")
        return u.lower() if u else "0000unix0000"

    def ticks_ms(self):
        """Milliseconds since boot, wrapping at 2**30 (contract's time stamp)."""
        return time.ticks_diff(time.ticks_ms(), self._t0) & _TMASK

    def ticks_us(self):
        return time.ticks_us()

    def ticks_diff(self, a, b):
        return time.ticks_diff(a, b)

    def wait(self, ms):
        """Sleep up to ``ms`` milliseconds, returning early when a UART has input.

        A pty whose other end is closed reports POLLHUP at once and forever; then sleep the full
        time instead of spinning (the link is down until the emulator reconnects it).
        """
        for _, ev in self.poller.ipoll(ms):
            if ev & (select.POLLHUP | select.POLLERR):
                time.sleep_ms(ms)
            break

    def servo_uart(self, bus_cfg):
        raise ValueError("serial bus servos need the ESP32 HAL; use servo_driver 'emulated'")

    def pwm(self, pin, freq):
        raise ValueError("PWM servos need the ESP32 HAL; use servo_driver 'emulated'")
