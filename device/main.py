"""Segment firmware entry point (ESP32 and the MicroPython unix port).

Picks the HAL by platform, loads config.json (absent or invalid: the segment holds, says why),
builds servo driver, MC, SCs and the segment coordinator, then runs forever (``Runner``):
frames are handled as they arrive, the control tick runs every ``tick_ms`` (config.json,
default 5 ms). An exception in either puts the segment in FAULT (``Segment.enter_fault``) and
the loop goes on, so the chain keeps forwarding; the optional hardware watchdog (``wdt.py``) is
fed only by a healthy pass: one that ran the control tick to its end and raised nothing (once
per clean tick). The loop never reads stdin, so the USB REPL stays free; Ctrl-C
(KeyboardInterrupt) ends it and leaves the board (or ``micropython -i``) at the REPL, the servos
in their safe state (``Segment.stop_for_repl``) and a hardware watchdog fed by a timer
(``wdt.keep_fed``), so a flash over the REPL is not reset.
"""

import os
import sys

_TMASK = 0x3FFFFFFF
FAULT_TICK = 1  # protocol.constants FAULT_* (plain ints: main.py imports nothing heavy at top)
FAULT_FRAME = 2
FAULT_WDT_RESET = 3
# config.json absent: refused like an invalid one (docs/firmware.md "Configuration")
NO_CONFIG = "no config.json: flash one (ucr flash)"


def _hal_module():
    if sys.platform == "esp32":
        import hal_esp32

        return hal_esp32
    import hal_unix

    return hal_unix


def _hash(cfg):
    """cfg.hash: the configuration hash (DESCRIPTOR key 17), computed while the heap is tidy;
    the module is dropped again (compiled later, a fragmented heap might not fit it)."""
    from protocol.confighash import config_hash

    cfg.hash = config_hash(cfg.si)
    if sys.implementation.name == "micropython":
        sys.modules.pop("protocol.confighash", None)
        import protocol

        if hasattr(protocol, "confighash"):
            del protocol.confighash


def _intern_calib():
    """Compile the slow-path calibration modules once at boot and drop them again: the names
    they use stay interned (MicroPython never frees a qstr), so when the first CALIBRATE loads
    them, in a heap the boot left fragmented, the compiler needs no new qstr pool, the one large
    block it could not find then (docs/firmware.md, "Calibration")."""
    try:
        import calib  # noqa: F401
    except MemoryError:
        print("[main] no heap to prepare the calibration module")
    if sys.implementation.name == "micropython":
        for m in ("calib", "calib_store", "protocol.cal_core"):
            sys.modules.pop(m, None)
        import protocol

        if hasattr(protocol, "cal_core"):
            del protocol.cal_core


def build(tick_ms=None):
    """Construct (hal, segment) from config.json and the platform's HAL; the tick's period is
    ``tick_ms`` or else the configuration's (``tick_ms``, config.DEFAULTS).

    Modules are compiled one after the other on the board; a collection between them leaves each
    compilation a tidy heap (the compiler's peak, not the firmware's size, bounds the boot).
    """
    import gc

    halmod = _hal_module()
    gc.collect()
    import config

    gc.collect()
    # the largest module first, while the heap holds least: compiled from source (`ucr flash
    # --source`) its parse tree is the boot's peak, and it did not fit once the configuration
    # was loaded (docs/firmware.md, "Memory")
    from segment import Segment

    gc.collect()
    names = os.listdir()
    if "config.json" not in names:
        # no configuration was given: never move on guessed defaults (pins, zero offsets,
        # ranges); hold and say why, as for an invalid file (config.refused)
        cfg = config.refused(None, halmod.DEFAULT_DRIVER, NO_CONFIG)
    elif "calibration.json" in names or "calibration.tmp" in names:  # a stored calibration wins
        import calib_store

        cfg = calib_store.load_config(config, halmod.DEFAULT_DRIVER)
        del calib_store
    else:
        cfg = config.load("config.json", halmod.DEFAULT_DRIVER)  # board rules come and go here
    gc.collect()
    _hash(cfg)
    gc.collect()
    _intern_calib()
    gc.collect()
    import servos

    gc.collect()
    hal = _open_hal(halmod, cfg)
    driver = cfg.driver
    if halmod.PLATFORM == "unix" and driver != "emulated":
        # the unix port emulates the board: its servos, whatever their family, are simulated
        print("[main] servo_driver %r runs as 'emulated' on the unix port" % driver)
        driver = "emulated"
    try:
        if cfg.error and driver != "emulated":
            # a refused configuration: drive no pin it did not name (config.refused)
            raise ValueError("not started: %s" % cfg.error)
        bus = servos.make(driver, cfg, hal)
    except Exception as e:  # noqa: BLE001 - any driver failure: keep the chain alive
        print("[main] servo driver %r failed: %s" % (cfg.driver, e))
        bus = servos.OfflineBus(cfg.n, str(e))
        if not cfg.error:
            cfg.error = "servo driver %s failed: %s" % (cfg.driver, e)
    if hal.faults_spec:
        try:
            bus.set_faults(hal.faults_spec)
        except ValueError as e:
            print("[main] UCR_FAULTS ignored:", e)
    return hal, Segment(hal, cfg, bus, tick_ms or cfg.tick_ms)


def _open_hal(halmod, cfg):
    """The HAL on the configuration's board and chain pins. If this chip cannot run that plan
    (config.json made for another board, or a refused configuration whose plan was unusable,
    config.refused), the segment still reaches the host: on an ESP32 the HAL opens the chip's own
    board (``hal_esp32.own_pins``, from the chip's detection) and the segment holds, ``error``
    saying why (DESCRIPTOR key 16, PARAM 16). The emulated board refuses as it is (the
    emulator shows why)."""
    # a refused configuration's servo pins: never a chain UART on them (real boards only: the
    # unix port's "pins" are pseudo-terminals)
    avoid = () if halmod.PLATFORM == "unix" else cfg.si.get("servo_pins") or ()
    try:
        if avoid:
            return halmod.Hal(cfg.si.get("pins"), avoid)
        return halmod.Hal(cfg.si.get("pins"))
    except ValueError as e:
        if halmod.PLATFORM == "unix":
            raise
        print("[main]", e)
        if not cfg.error:
            cfg.error = "config.json refused by this chip: %s" % (e,)
    return halmod.Hal(halmod.own_pins(), avoid)


def _why(where, e):
    """Short reason of an exception for the FAULT event: "tick: ZeroDivisionError: ..."."""
    return "%s: %s: %s" % (where, type(e).__name__, e)


class Runner:
    """The main loop, one pass at a time (``once``), so tests drive the very same code."""

    def __init__(self, hal, seg, tick_ms=None, wdt=None):
        self.hal = hal
        self.seg = seg
        self.tick_ms = tick_ms or seg.tick_ms
        self.wdt = wdt
        self.next_t = hal.ticks_ms()
        self.printed = 0

    def _poll(self):
        """``seg.poll()``; an exception in frame handling is a FAULT (False), the loop goes on."""
        try:
            self.seg.poll()
            return True
        except KeyboardInterrupt:
            raise
        except Exception as e:  # noqa: BLE001 - any exception: FAULT, the loop goes on
            self._fault(FAULT_FRAME, "frame", e)
            return False

    def _fault(self, code, where, e):
        if self.printed < 10:  # the REPL shows the first tracebacks
            self.printed += 1
            sys.print_exception(e)
        self.seg.enter_fault(code, _why(where, e))

    def once(self):
        """Handle frames, run the tick when due, feed the watchdog after a healthy pass (the
        tick ran to its end and nothing in the pass raised); return the ms to wait before the
        next pass (0: none)."""
        hal = self.hal
        seg = self.seg
        tick_ms = self.tick_ms
        healthy = self._poll()
        ticked = False
        now = hal.ticks_ms()
        d = (now - self.next_t) & _TMASK
        if d < 0x20000000:  # the tick is due
            if d >= tick_ms:
                seg.overruns += 1  # started a whole tick period (or more) late: its slot passed
            if d > 4 * tick_ms:  # far behind: the missed ticks are dropped, not caught up
                self.next_t = now
            self.next_t = (self.next_t + tick_ms) & _TMASK
            try:
                seg.tick(now)
                ticked = True
            except KeyboardInterrupt:
                raise
            except Exception as e:  # noqa: BLE001
                healthy = False
                self._fault(FAULT_TICK, "tick", e)
                try:
                    seg.service(now)  # still report (EVENT FAULT) and keep the link alive
                except Exception as e2:  # noqa: BLE001
                    self._fault(FAULT_TICK, "service", e2)
            held = seg.held
            if held[0] or held[1]:
                # a frame completed at a relay point of the tick: handle it now, not after the
                # wait (its bytes were read already, so no input would end the wait early)
                healthy = self._poll() and healthy
        if ticked and healthy and self.wdt is not None:
            # healthy: this pass ran the control tick to its end and nothing in the pass raised;
            # a pass that only handled frames feeds nothing (every tick raising must starve it)
            self.wdt.feed()
        wait = (self.next_t - hal.ticks_ms()) & _TMASK
        return wait if 0 < wait <= tick_ms else 0


def run(tick_ms=None):
    import gc

    import micropython

    if hasattr(micropython, "alloc_emergency_exception_buf"):  # not on the unix port
        micropython.alloc_emergency_exception_buf(128)
    hal, seg = build(tick_ms)
    tick_ms = seg.tick_ms
    dog = None
    if seg.cfg.hw_watchdog_ms:  # (without a watchdog there is no watchdog reset to report)
        import wdt

        wdt.stop_feeding()  # run() again from the REPL: only the loop feeds it now
        if wdt.reset_by_watchdog():
            seg.enter_fault(FAULT_WDT_RESET, "reset by the hardware watchdog")
        dog = wdt.make(seg.cfg.hw_watchdog_ms)
    gc.collect()
    print("[main] segment %s up, %d Hz" % (seg.uid, 1000 // tick_ms))
    r = Runner(hal, seg, tick_ms, dog)
    try:
        while True:
            w = r.once()
            if w:
                hal.wait(w)
    except KeyboardInterrupt as e:
        to_repl(seg, dog, hal)
        raise e


def to_repl(seg, dog, hal):
    """Ctrl-C (mpremote, ucr flash) ended the loop: the REPL takes over. A watchdog that cannot
    be stopped (machine.WDT) is fed by a timer (tiny, so first), or it would reset the board in
    the REPL, mid-flash (docs/flashing.md "Hardware watchdog"); the servos go to their safe
    state. A second Ctrl-C meanwhile (ucr flash sends two; people double-tap) starts it again."""
    for _ in range(3):
        try:
            if dog is not None:
                import wdt

                wdt.keep_fed(dog, seg.cfg.hw_watchdog_ms, hal)
            seg.stop_for_repl()
            return
        except KeyboardInterrupt:
            pass
        except Exception as e:  # noqa: BLE001 - the REPL must still come; say why
            print("[main] safe stop failed:", e)
            return


if __name__ == "__main__":
    run()
