"""Hardware watchdog (config ``hw_watchdog_ms``; 0 = off), fed only by a healthy loop.

On an ESP32 it is ``machine.WDT``, fed by ``main.Runner`` once per clean control tick (a pass
that ran the tick to its end and raised nothing; frames alone feed nothing): if the loop stops
completing clean ticks (a hang, or a tick that raises every time) for the timeout, the chip
resets, and the next boot enters FAULT with code WDT_RESET (``machine.reset_cause()``). The unix
port has no hardware watchdog, so the emulation provides the same contract: a thread watches the
feed time and, when it expires, marks the reset in ``WDT_MARK`` (the board's "reset cause") and
kills the process, which the emulator restarts as a board reboots.
"""

import sys

WDT_MARK = "wdt_reset"  # unix port: file in the segment directory = "the last reset was the WDT"


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
