"""Segment firmware entry point (ESP32 and the MicroPython unix port).

Picks the HAL by platform, loads config.json (defaults when absent), builds servo driver, MC, SCs
and the segment coordinator, then runs forever: frames are handled as they arrive, the control
tick runs every TICK_MS. The loop never reads stdin, so the USB REPL stays free; Ctrl-C
(KeyboardInterrupt) ends it and leaves the board (or ``micropython -i``) at the REPL.
"""

import sys

TICK_MS = 5  # 200 Hz control tick
_TMASK = 0x3FFFFFFF


def _hal_module():
    if sys.platform == "esp32":
        import hal_esp32

        return hal_esp32
    import hal_unix

    return hal_unix


def build(tick_ms=TICK_MS):
    """Construct (hal, segment) from config.json and the platform's HAL."""
    import config
    import servos
    from segment import Segment

    halmod = _hal_module()
    cfg = config.load("config.json", halmod.DEFAULT_DRIVER)
    hal = halmod.Hal(cfg.si.get("pins"))
    driver = cfg.driver
    if halmod.PLATFORM == "unix" and driver != "emulated":
        # the unix port emulates the board: its servos, whatever their family, are simulated
        print("[main] servo_driver %r runs as 'emulated' on the unix port" % driver)
        driver = "emulated"
    try:
        bus = servos.make(driver, cfg, hal)
    except Exception as e:  # noqa: BLE001 - any driver failure: keep the chain alive
        print("[main] servo driver %r failed: %s" % (cfg.driver, e))
        bus = servos.OfflineBus(cfg.n, str(e))
        cfg.error = "servo driver %s failed: %s" % (cfg.driver, e)
    if hal.faults_spec:
        try:
            bus.set_faults(hal.faults_spec)
        except ValueError as e:
            print("[main] UCR_FAULTS ignored:", e)
    return hal, Segment(hal, cfg, bus, tick_ms)


def run(tick_ms=TICK_MS):
    import gc

    import micropython

    if hasattr(micropython, "alloc_emergency_exception_buf"):  # not on the unix port
        micropython.alloc_emergency_exception_buf(128)
    hal, seg = build(tick_ms)
    gc.collect()
    print("[main] segment %s up, %d Hz" % (seg.uid, 1000 // tick_ms))
    next_t = hal.ticks_ms()
    errors = 0
    while True:
        try:
            seg.poll()
            now = hal.ticks_ms()
            d = (now - next_t) & _TMASK
            if d < 0x20000000:  # the tick is due
                if d > 4 * tick_ms:
                    seg.overruns += 1
                    next_t = now
                seg.tick(now)
                next_t = (next_t + tick_ms) & _TMASK
            wait = (next_t - hal.ticks_ms()) & _TMASK
            if 0 < wait <= tick_ms:
                hal.wait(wait)
        except KeyboardInterrupt:
            raise
        except Exception as e:  # noqa: BLE001 - report and keep the segment alive
            errors += 1
            if errors <= 10:
                sys.print_exception(e)
            hal.wait(10)


if __name__ == "__main__":
    run()
