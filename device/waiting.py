"""How the main loop waits for its next tick: never in whole RTOS ticks when the deadline is near.

On the ESP32 port a ``select.poll`` with a timeout sleeps until the next FreeRTOS tick (10 ms at
the stock 100 Hz) unless an interrupt wakes the main task (docs/firmware.md, "Waiting"), so a
plain ``ipoll(ms)`` turns a 5 ms tick into bursts. ``wait`` sleeps in the poller only while more
than one RTOS tick (+1 ms) remains (a UART rx irq, or the emulator's model of it, ends that early on
input) and covers the rest with ``spin(poller, deadline_us)``, which returns at the deadline or
as soon as input is there. Both HALs use it: the ESP32 one spins on ``ticks_us``; the emulator's
spin has the same outcome without burning the host's CPU.
"""

import time


def wait(poller, ms, tick_us, spin):
    """Wait up to ``ms`` milliseconds; return early when ``poller`` has input."""
    deadline = time.ticks_add(time.ticks_us(), ms * 1000)
    if tick_us:
        rem = ms * 1000
        if rem >= tick_us + 2000:  # ipoll(T) ends within [T, T + one tick): keep a tick spare
            for _ in poller.ipoll((rem - tick_us - 1000) // 1000):
                return
        spin(poller, deadline)
        return
    for _ in poller.ipoll(ms):
        return


def spin(poller, deadline):
    """Busy-wait until ``deadline`` (ticks_us) or input: ``ipoll(0)`` never sleeps."""
    while time.ticks_diff(deadline, time.ticks_us()) > 0:
        for _ in poller.ipoll(0):
            return
