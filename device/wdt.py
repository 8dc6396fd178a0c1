"""Hardware watchdog (config ``hw_watchdog_ms``; 0 = off), fed only by a healthy loop.

On an ESP32 it is ``machine.WDT``, fed by ``main.Runner`` once per clean control tick (a pass
that ran the tick to its end and raised nothing; frames alone feed nothing): if the loop stops
completing clean ticks (a hang, or a tick that raises every time) for the timeout, the chip
resets, and the next boot enters FAULT with code WDT_RESET (``machine.reset_cause()``). The unix
port has no hardware watchdog, so the emulation provides the same contract: a thread watches the
feed time and, when it expires, marks the reset in ``WDT_MARK`` (the board's "reset cause") and
kills the process, which the emulator restarts as a board reboots.

A ``machine.WDT`` cannot be stopped, so when the loop ends by Ctrl-C (the REPL takes over, e.g.
for ``ucr flash``) ``keep_fed`` feeds it from a periodic ``machine.Timer`` callback: the REPL and a
flash over it then run without a reset. The ESP32 port runs a timer callback as a scheduled
(soft) callback (ports/esp32/machine_timer.c ``mp_sched_schedule``), i.e. between bytecodes and
while the REPL waits for input; a soft reset deinitialises every timer
(ports/esp32/main.c ``machine_timer_deinit_all``), so after a soft reset only a new ``main.py``
feeds it again. The unix port's emulated board (``emu_board.BoardMachine.Timer``) offers the
same timer (``EmuTimer``, below), run from a thread.
"""

import sys

WDT_MARK = "wdt_reset"  # unix port: file in the segment directory = "the last reset was the WDT"
FEED_TIMER = 0  # machine.Timer id of the feeder (hardware timer 0 exists on every ESP32 chip)
_feeder = []  # the running feeder timer (at most one)


def reset_by_watchdog():
    """True if the last reset was the watchdog's (reads, then forgets, the unix marker)."""
    if sys.platform == "esp32":
        import machine

        return machine.reset_cause() == machine.WDT_RESET
    import os

    try:
        os.stat(WDT_MARK)
    except OSError:
        return False
    os.remove(WDT_MARK)
    return True


def make(timeout_ms):
    """The watchdog for ``timeout_ms`` (object with ``feed()``), or None when 0 (off)."""
    if not timeout_ms:
        return None
    if sys.platform == "esp32":
        import machine

        return machine.WDT(timeout=timeout_ms)
    return EmulatedWdt(timeout_ms)


class EmulatedWdt:
    """machine.WDT for the unix port: a watcher thread resets (kills) the process on expiry."""

    def __init__(self, timeout_ms):
        import _thread
        import time

        self.timeout_ms = timeout_ms
        self._time = time
        self.last = time.ticks_ms()
        _thread.start_new_thread(self._watch, ())

    def feed(self):
        self.last = self._time.ticks_ms()

    def _watch(self):
        t = self._time
        while True:
            t.sleep_ms(10)
            if t.ticks_diff(t.ticks_ms(), self.last) > self.timeout_ms:
                import os

                with open(WDT_MARK, "w") as f:
                    f.write("1")
                print("[wdt] watchdog expired: reset")
                os.system("kill -9 $PPID")  # the shell's parent: this process (a hard reset)


def keep_fed(dog, timeout_ms, hal=None):
    """Feed ``dog`` every third of ``timeout_ms`` from a periodic ``machine.Timer`` (the loop
    has ended: the REPL runs). On the unix port the timer is the emulated board's
    (``hal.machine``). Returns the timer."""
    stop_feeding()
    if sys.platform == "esp32":
        import machine

        m = machine
    else:
        m = hal.machine
    period = timeout_ms // 3
    if period < 10:
        period = 10

    def feed(_t):
        dog.feed()

    dog.feed()
    t = m.Timer(FEED_TIMER)
    t.init(mode=t.PERIODIC, period=period, callback=feed)
    _feeder.append(t)
    return t


def stop_feeding():
    """Stop the timer ``keep_fed`` started (``main.run`` again: only the loop feeds the dog)."""
    while _feeder:
        _feeder.pop().deinit()


class EmuTimer:
    """The emulated board's hardware ``machine.Timer`` (``emu_board.BoardMachine.Timer``; kept
    here, so a boot without a hardware watchdog never compiles it), run from a thread:
    ``init(mode=PERIODIC | ONE_SHOT, period=ms, callback=f)``, ``deinit()``. On the board the
    callback is scheduled (ports/esp32/machine_timer.c ``mp_sched_schedule``) and runs between
    bytecodes or while the REPL waits for input; the unix port's REPL blocks in ``read``, so the
    thread calls it. A soft reset deinitialises the board's timers; the emulated board has no
    soft reset (its process ends and the emulator starts it again), which ends the thread."""

    ONE_SHOT = 0
    PERIODIC = 1

    def __init__(self, tid):
        self.tid = tid
        self.gen = 0  # each init/deinit starts a new generation: an older thread stops

    def init(self, mode=PERIODIC, period=0xFFFFFFFF, callback=None, hard=False, **kw):
        import _thread

        if hard:
            raise ValueError("hard Timers are not implemented")
        self.gen += 1
        _thread.start_new_thread(self._run, (self.gen, mode, period, callback))

    def deinit(self):
        self.gen += 1

    def _run(self, gen, mode, period, callback):
        import time

        while True:
            time.sleep_ms(period)
            if gen != self.gen:
                return
            if callback is not None:
                callback(self)
            if mode != EmuTimer.PERIODIC:
                return
