"""The emulated board (unix port): a ``machine`` as strict as the board, and its timing model.

Used by hal_unix.py; docs/emulator.md, "Boards" and "Timing model". Kept out of hal_unix so the
firmware's boot compiles it after the board rules (protocol/boards.py) have been freed.
"""

import time


class BoardMachine:
    """The ``machine`` of an emulated board: UARTs and pins as strict as the board's profile.

    ``wires`` maps a UART id to the pty path wired to it (None: nothing plugged in);
    ``open_uart(path_or_None)`` makes the UART object (the HAL's, passed in so this module does
    not import the HAL back). Errors are ValueError, with the port's own text where the port has
    one ("UART(3) does not exist").
    """

    IRQ_RX = 1

    def __init__(self, board, profile, wires, open_uart):
        self.board = board
        self.open_uart = open_uart
        self.profile = profile
        self.wires = wires
        self.claimed = {}  # GPIO -> what uses it
        self.uarts = {}
        self.timers = {}

    def _pin(self, gpio, role, output):
        p = self.profile
        if isinstance(gpio, bool) or not isinstance(gpio, int) or gpio not in p["gpio"]:
            raise ValueError("%s has no GPIO%r (%s)" % (self.board, gpio, role))
        why = p["reserved"].get(gpio)
        if why:
            raise ValueError("GPIO%d is %s on %s (%s)" % (gpio, why, self.board, role))
        if output and gpio in p["input_only"]:
            raise ValueError("GPIO%d is input-only on %s (%s)" % (gpio, self.board, role))
        if gpio in self.claimed:
            raise ValueError("GPIO%d is already %s (%s)" % (gpio, self.claimed[gpio], role))
        self.claimed[gpio] = role

    def UART(self, uid, baudrate=115200, tx=None, rx=None, **kw):
        p = self.profile
        if isinstance(uid, bool) or not isinstance(uid, int) or not 0 <= uid < p["uarts"]:
            raise ValueError("UART(%r) does not exist" % (uid,))
        if uid == p["repl_uart"]:
            raise ValueError(
                "UART(%d) is the REPL's on %s: the chain cannot use it" % (uid, self.board)
            )
        if uid in self.uarts:
            raise ValueError("UART(%d) is already in use" % uid)
        self._pin(tx, "UART%d TX" % uid, True)
        self._pin(rx, "UART%d RX" % uid, False)
        path = self.wires.get(uid)
        u = self.open_uart(path)
        self.uarts[uid] = u
        return u

    def Pin(self, gpio, role="Pin"):
        self._pin(gpio, role, True)
        return gpio

    def Timer(self, tid):
        """``machine.Timer(id)`` of the board: its hardware timers (ids 0..3; 0..1 on a C3,
        SOC_TIMER_GROUP_TOTAL_TIMERS), ValueError as the port words it otherwise."""
        n = 2 if self.profile.get("chip") == "ESP32C3" else 4
        if isinstance(tid, bool) or not isinstance(tid, int) or not 0 <= tid < n:
            raise ValueError("invalid Timer number, max %d" % n)
        t = self.timers.get(tid)
        if t is None:
            from wdt import EmuTimer  # only a segment with a hardware watchdog needs it

            t = self.timers[tid] = EmuTimer(tid)
        return t


class TickPoller:
    """``select.poll`` as the ESP32 port runs it: a wait with a timeout wakes on a FreeRTOS tick.

    extmod/modselect.c polls, then sleeps in ``MICROPY_EVENT_POLL_HOOK`` (``ulTaskNotifyTake(1)``,
    ports/esp32/mpconfigport.h) until the next tick or a notification (a UART rx irq); it returns
    when an object is ready or ``elapsed_ms >= timeout`` (docs/emulator.md has the lines). The
    tick phase is this process's start, as a board's is its boot.
    """

    def __init__(self, poller, uarts, tick_us, t0_us):
        self.poller = poller
        self.uarts = uarts
        self.tick_us = tick_us
        self.t0 = t0_us

    def ipoll(self, timeout_ms):
        if timeout_ms == 0:
            return self.poller.ipoll(0)
        start = time.ticks_ms()
        wakes = False
        for u in self.uarts:
            if u.irq_set:
                wakes = True
        while True:
            ready = self.poller.poll(0)
            if ready or (timeout_ms >= 0 and time.ticks_diff(time.ticks_ms(), start) >= timeout_ms):
                return iter(ready)
            now = time.ticks_us()
            since = time.ticks_diff(now, self.t0)
            nap = self.tick_us - since % self.tick_us  # to the next tick
            if wakes:
                for _ in self.poller.ipoll((nap + 999) // 1000):
                    break
            else:
                time.sleep_us(nap)


def host_spin(poller, deadline):
    """The ESP32 spin's outcome (back at the deadline or on input) with little host CPU: the
    board's ``ipoll(0)`` never sleeps, so the host's poller (not the tick model) waits here."""
    poller = getattr(poller, "poller", poller)
    while True:
        rem = time.ticks_diff(deadline, time.ticks_us())
        if rem <= 0:
            return
        if rem > 1500:
            for _ in poller.ipoll(rem // 1000 - 1):
                return
        else:
            for _ in poller.ipoll(0):
                return
            time.sleep_us(100 if rem > 100 else rem)


class StretchUart:
    """A UART under the timing model: a write first waits out the board's compute time. The
    host's read and write system calls themselves are not the board's compute (its UART calls
    copy into the driver's ring buffers in C): their time is left out of the next stretch."""

    def __init__(self, uart, hal):
        self.uart = uart
        self.hal = hal
        self.f = uart.f
        self.irq_set = uart.irq_set

    def readinto(self, buf):
        t0 = time.ticks_us()
        n = self.uart.readinto(buf)
        self.hal.not_compute(t0)
        return n

    def write(self, buf, n=-1):
        self.hal.stretch()
        t0 = time.ticks_us()
        n = self.uart.write(buf, n)
        self.hal.not_compute(t0)
        return n

    def irq(self, handler=None, trigger=0):
        self.uart.irq(handler, trigger)
        self.irq_set = self.uart.irq_set
