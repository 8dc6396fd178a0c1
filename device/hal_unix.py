"""HAL of the MicroPython unix port: the emulated board. UARTs are ptys, servos are emulated.

Environment (docs/architecture.md, "Running firmware on the unix port"): ``UCR_UP_PORT`` and
``UCR_DOWN_PORT`` (pty paths; a missing one is an unconnected port), ``UCR_UID`` (hex unique id),
``UCR_FAULTS`` (optional fault injection spec for the emulated servos, see servos/emulated.py),
``UCR_BOARD`` (board to emulate, overriding config.json's ``board``), ``UCR_TIMING`` ("1": the
board's timing model), ``UCR_CPU_FACTOR`` (how much slower than this host the board computes) and
``UCR_NAIVE_WAIT`` ("1", benchmarks only: wait as the firmware did before issue 11, one poll);
``UCR_SPIN_HOLD`` ("1", benchmarks only: the model's holds busy-wait instead of sleeping, so the
host stays as hot as a board that is computing; it costs a host core per segment).

The board is as strict as the real one (docs/emulator.md, "Boards"): the emulated ``machine``
(:class:`BoardMachine`) refuses a UART the chip lacks or the REPL owns, a pin it lacks or has
wired to flash/USB/REPL, and a pin or UART used twice. With the timing model, a poll with a
timeout ends only on the board's RTOS tick (unless a UART rx irq is registered and input
arrives), as on the ESP32 port, and the compute between two waits is stretched by the CPU factor.
A pty is opened with ``open(path, "r+b")`` and put in raw mode with VMIN = VTIME = 0, so
``readinto`` returns what is there (0 when nothing) instead of blocking.
"""

import os
import select
import termios
import time

import waiting

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
        self.irq_set = False

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

    def irq(self, handler=None, trigger=0):
        """UART.irq: with the timing model, rx then wakes a tick-granular poll at once."""
        self.irq_set = trigger != 0


class NullUart:
    """An unconnected port: never receives, swallows writes."""

    f = None
    irq_set = False

    def readinto(self, buf):
        return None

    def write(self, buf, n=-1):
        return len(buf) if n < 0 else n

    def irq(self, handler=None, trigger=0):
        pass


def _open_uart(path):
    """The emulated board's UART wired to ``path`` (a pty), or an unconnected one."""
    return PtyUart(path) if path else NullUart()


class Hal:
    """Unix-port HAL: the emulated board's UARTs (ptys), its timing model, emulated servo bus."""

    platform = PLATFORM
    default_driver = DEFAULT_DRIVER

    def __init__(self, cfg_pins=None):
        import gc

        import config

        pins = dict(cfg_pins) if cfg_pins else {}
        board = pins.pop("board", None)
        prof = config.PROFILE if board is not None and config.PROFILE_NAME == board else None
        emulated = os.getenv("UCR_BOARD")
        if emulated and emulated != board:
            # the emulator runs this segment as another board: that board's default wiring
            print(
                "[hal] config.json's board %s emulated as %s (its default pins)" % (board, emulated)
            )
            board, pins, prof = emulated, {}, None
        if prof is None:
            gc.collect()
            from protocol import boards

            board = board or boards.DEFAULT_BOARD
            prof = boards.profile(board)
        gc.collect()
        import emu_board  # the emulated machine and timing model (loaded after the rules left)

        chain = dict(prof["pins"])
        chain.update(pins)
        if chain["down_uart"] is None:
            raise ValueError(
                "board %s has no UART left for the downstream port: UART%s is the REPL's"
                % (board, prof["repl_uart"])
            )
        self.board = board
        self.pins = chain
        up = os.getenv("UCR_UP_PORT")
        down = os.getenv("UCR_DOWN_PORT")
        wires = {chain["up_uart"]: up, chain["down_uart"]: down}
        self.machine = emu_board.BoardMachine(board, prof, wires, _open_uart)
        self._spin = emu_board.host_spin
        m = self.machine
        self.up = m.UART(chain["up_uart"], chain["baud"], tx=chain["up_tx"], rx=chain["up_rx"])
        self.down = m.UART(
            chain["down_uart"], chain["baud"], tx=chain["down_tx"], rx=chain["down_rx"]
        )
        self._host_poller = select.poll()
        for u in (self.up, self.down):
            if u.f is not None:
                self._host_poller.register(u.f, select.POLLIN)
        self._up_f = self.up.f
        self.faults_spec = os.getenv("UCR_FAULTS")
        self._t0 = time.ticks_ms()
        self.timing = os.getenv("UCR_TIMING") == "1" and prof["tick_hz"] > 0
        self.cpu_factor = 1.0
        self.tick_us = 0
        self.poller = self._host_poller
        if self.timing:
            self.tick_us = 1000000 // prof["tick_hz"]
            self.cpu_factor = float(os.getenv("UCR_CPU_FACTOR") or "1")
            self.poller = emu_board.TickPoller(
                self._host_poller, (self.up, self.down), self.tick_us, time.ticks_us()
            )
            # the ESP32 HAL's rx irq (hal_esp32.py): the model wakes on input like the port
            for u in (self.up, self.down):
                u.irq(trigger=emu_board.BoardMachine.IRQ_RX)
            # bytes leave when the board would have computed them
            self.up = emu_board.StretchUart(self.up, self)
            self.down = emu_board.StretchUart(self.down, self)
        self.naive_wait = os.getenv("UCR_NAIVE_WAIT") == "1"
        self.spin_hold = os.getenv("UCR_SPIN_HOLD") == "1"
        self.idle_us = 0  # time spent waiting (the board's, under the timing model): CPU load
        self._busy_from = time.ticks_us()

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

        Without the timing model: one host poll. With it: first the compute since the last wait
        is stretched to the board's speed (the board would still be busy), then the ESP32 HAL's
        wait (device/waiting.py) runs on the tick-granular poller. A pty whose other end is
        closed reports POLLHUP at once and forever; then sleep the full time instead of spinning
        (the link is down until the emulator reconnects it).
        """
        if not self.timing:
            t0 = time.ticks_us()
            for _, ev in self._host_poller.ipoll(ms):
                if ev & (select.POLLHUP | select.POLLERR):
                    time.sleep_ms(ms)
                break
            self.idle_us += time.ticks_diff(time.ticks_us(), t0)
            return
        start = time.ticks_us()
        self.stretch()
        t0 = time.ticks_us()  # the board computed until here; from here on it waits
        ms -= time.ticks_diff(t0, start) // 1000
        if ms > 0:
            for _, ev in self._host_poller.ipoll(0):
                if ev & (select.POLLHUP | select.POLLERR):
                    time.sleep_ms(ms)
                    ms = 0
                break
        if ms > 0:
            if self.naive_wait:  # the pre-fix firmware: one poll, tick-granular on the board
                for _ in self.poller.ipoll(ms):
                    break
            else:
                waiting.wait(self.poller, ms, self.tick_us, self._spin)
        self._busy_from = time.ticks_us()
        self.idle_us += time.ticks_diff(self._busy_from, t0)

    def rx_any(self):
        """Which UARTs have input waiting: bit 0 upstream, bit 1 downstream (a hung-up pty
        counts: its read then finds nothing). With the timing model the board first computes
        what this host did since the last wait or write (a relay point comes that much later)."""
        if self.timing:
            self.stretch()
        t0 = time.ticks_us()
        m = 0
        for f, _ in self._host_poller.ipoll(0):
            if f is self._up_f:
                m |= 1
            else:
                m |= 2
        if self.timing:
            self.not_compute(t0)  # UART.any() on the board: C, not the host's poll(2)
        return m

    def not_compute(self, t0):
        """Timing model: the host time since ``t0`` (a system call standing in for the board's
        C driver call) is left out of the compute the next ``stretch`` holds for."""
        self._busy_from = time.ticks_add(self._busy_from, time.ticks_diff(time.ticks_us(), t0))

    def stretch(self):
        """Timing model: the board is still computing what this host did since the last wait
        or write: hold for that time x (cpu_factor - 1)."""
        now = time.ticks_us()
        extra = int(time.ticks_diff(now, self._busy_from) * (self.cpu_factor - 1.0))
        if extra > 0:
            if self.spin_hold:  # the host stays hot: the code after the hold runs at full speed
                end = time.ticks_add(now, extra)
                while time.ticks_diff(end, time.ticks_us()) > 0:
                    pass
            else:
                time.sleep_us(extra)
        self._busy_from = time.ticks_us()

    def servo_uart(self, bus_cfg):
        raise ValueError("serial bus servos need the ESP32 HAL; use servo_driver 'emulated'")

    def pwm(self, pin, freq):
        raise ValueError("PWM servos need the ESP32 HAL; use servo_driver 'emulated'")
