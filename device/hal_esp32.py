"""HAL of an ESP32 running MicroPython: machine.UART up/down, PWM / bus servos, ticks, unique id.

The board and its pin plan come from config.json (``board``, ``pins``, ``bus``, ``pwm``, resolved
and checked against protocol/boards.py by config.py; docs/firmware.md has a wiring table per
board). The REPL keeps UART0 (stock MicroPython) and the USB port; the chain uses two other UARTs.
A configuration without a board on a chip other than a classic ESP32 must name its chain pins
(the classic defaults may be that chip's USB pins).

Clock: the CPU runs at the board profile's ``mhz`` (protocol/boards.py), set at boot with
``machine.freq``: a stock ESP32 build starts at ESP-IDF's default 160 MHz, and the control cycle
needs the chip's 240 MHz (docs/firmware.md "Clock"). The UARTs and PWM run from the 80 MHz APB
clock, so their timing does not change.

Waiting (``wait``): a ``select.poll`` timeout ends on a FreeRTOS tick (10 ms), so the HAL sleeps
in the poller only while more than a tick remains, woken early by a UART rx irq (MicroPython
>= 1.24), and spins on ``ticks_us`` for the rest (device/waiting.py).
"""

import os
import select
import time

import machine
import waiting

_TMASK = 0x3FFFFFFF

PLATFORM = "esp32"
DEFAULT_DRIVER = "pwm"

PINS = {
    "up_uart": 1,
    "up_tx": 19,
    "up_rx": 18,
    "down_uart": 2,
    "down_tx": 17,
    "down_rx": 16,
    "baud": 921600,
}
_CHAIN_PINS = ("up_tx", "up_rx", "down_tx", "down_rx")
TICK_US = 10000  # FreeRTOS tick of stock MicroPython (CONFIG_FREERTOS_HZ = 100)


def _on_rx(uart):
    """UART rx irq: nothing to do, waking the main task is the point."""


def chip():
    """'ESP32', 'ESP32S3', 'ESP32C3', ... from os.uname().machine ('... with ESP32S3')."""
    m = os.uname().machine
    i = m.rfind("with ")
    return (m[i + 5 :] if i >= 0 else m).strip().upper()


def _profile(board):
    """The board's profile: the one config.py kept (the rules module is freed after boot)."""
    import config

    prof = config.PROFILE
    if prof is None or config.PROFILE_NAME != board:
        from protocol import boards

        prof = boards.profile(board)
    return prof


def chain_pins(chip_name, cfg_pins):
    """UART ids, pins and baud of the chain. With a board named (config.py puts it in ``pins``)
    the plan is that board's, and the chip must be that board's chip. Without one: the classic
    defaults on a classic ESP32; elsewhere the chain pins must come from the config (the defaults
    may be that chip's USB pins)."""
    p = dict(PINS)
    if cfg_pins:
        p.update(cfg_pins)
    board = p.get("board")
    if board is not None:
        want = _profile(board)["chip"]
        if want != chip_name:
            raise ValueError(
                "config.json names board %r (chip %s) but this chip is an %s: flash the "
                "configuration made for this board" % (board, want, chip_name)
            )
        return p
    if chip_name != "ESP32":
        missing = [k for k in _CHAIN_PINS if not cfg_pins or k not in cfg_pins]
        if missing:
            raise ValueError(
                "this board is an %s: the default chain pins are a classic ESP32's and may be "
                "its USB pins; set %s in config.json 'pins' (docs/firmware.md)"
                % (chip_name, ", ".join(missing))
            )
    return p


def own_pins(chip_name=None):
    """The chain plan of this chip's own stock board (protocol/boards.py: the profile of that
    chip whose REPL is UART0), for a segment whose configured plan this chip cannot run
    (``main.build``): it holds and says why, upstream at least. Where the stock board has no UART
    left for the downstream (the C3), ``down_uart`` is None and the HAL opens no downstream."""
    import gc

    from protocol import boards

    name = chip_name or chip()
    for b in boards.NAMES:
        prof = boards.BOARDS[b]
        if prof["chip"] == name and prof["repl_uart"] is not None:
            p = dict(prof["pins"])
            p["board"] = b
            del boards
            gc.collect()
            return p
    raise ValueError("no board profile for the chip %s" % name)


def _avoiding(p, avoid):
    """Chain plan ``p`` without a UART on any pin in ``avoid`` (servo signal pins: UART bytes
    on one would drive that servo): a downstream on one is dropped (``down_uart`` None: the
    segment is the tip); an upstream on one is a ValueError (the segment cannot reach the host
    without driving a servo, so it stays silent)."""
    if p["up_tx"] in avoid or p["up_rx"] in avoid:
        raise ValueError(
            "the upstream UART's pins %d/%d are servo pins of config.json: not opened"
            % (p["up_tx"], p["up_rx"])
        )
    if p["down_uart"] is not None and (p["down_tx"] in avoid or p["down_rx"] in avoid):
        p = dict(p)
        p["down_uart"] = None
        p["down_tx"] = p["down_rx"] = None
    return p


def _chain_uart(p, side):
    """The chain's ``side`` ("up" or "down") UART of pin plan ``p`` (see Hal: rxbuf and the
    zero timeouts)."""
    return machine.UART(
        p[side + "_uart"],
        baudrate=p["baud"],
        tx=p[side + "_tx"],
        rx=p[side + "_rx"],
        rxbuf=1024,
        timeout=0,
        timeout_char=0,
    )


class NoPort:
    """The downstream of a segment whose board has no UART for it (``own_pins`` on a C3):
    nothing arrives, what is written is dropped."""

    def any(self):
        return 0

    def readinto(self, buf, n=None):
        return None

    def write(self, buf, n=None):
        return len(buf) if n is None else n


def set_clock(chip_name, board):
    """Run the CPU at the board profile's clock (the classic ESP32's without a board named);
    return the clock in MHz, or 0 where the firmware cannot know the chip's and leaves it."""
    name = board or ("esp32" if chip_name == "ESP32" else None)
    if name is None:
        return 0
    mhz = _profile(name)["mhz"]
    if machine.freq() != mhz * 1000000:
        machine.freq(mhz * 1000000)
    return mhz


class Hal:
    platform = PLATFORM
    default_driver = DEFAULT_DRIVER

    def __init__(self, cfg_pins=None, avoid=()):
        name = chip()
        p = chain_pins(name, cfg_pins)
        if avoid:  # a refused configuration's servo pins (config.refused): never a chain UART
            p = _avoiding(p, avoid)
        self.pins = p
        self.tick_us = TICK_US
        if p.get("board"):
            self.tick_us = 1000000 // _profile(p["board"])["tick_hz"]
        self.mhz = set_clock(name, p.get("board"))
        # rxbuf holds at least one whole encoded frame (253 bytes) plus slack. timeout_char=0:
        # the port then sets the RX FIFO threshold and RX timeout to 1 (ports/esp32/machine_uart.c,
        # "rx_timeout < 1"), so bytes are readable as they arrive, which cut-through forwarding
        # needs; with the driver's default threshold (120 bytes) a short frame would be readable
        # only after its end plus an idle time
        self.up = _chain_uart(p, "up")
        ports = [self.up]
        if p["down_uart"] is None:
            self.down = NoPort()  # own_pins on a chip with no UART left for it: upstream only
        else:
            self.down = _chain_uart(p, "down")
            ports.append(self.down)
        self.poller = select.poll()
        for u in ports:
            self.poller.register(u, select.POLLIN)
        # an rx irq wakes the main task out of its RTOS-tick sleep (machine_uart.c, >= 1.24)
        self.rx_irq = False
        for u in ports:
            try:
                u.irq(handler=_on_rx, trigger=machine.UART.IRQ_RX)
                self.rx_irq = True
            except (AttributeError, ValueError):
                pass  # MicroPython < 1.24: no UART.irq; the spin still meets the deadline
        self.faults_spec = None
        self.idle_us = 0  # time spent waiting; Segment reads and resets it (CPU load)
        self._t0 = time.ticks_ms()

    def uid(self):
        return "".join("%02x" % b for b in machine.unique_id())

    def ticks_ms(self):
        return time.ticks_diff(time.ticks_ms(), self._t0) & _TMASK

    def ticks_us(self):
        return time.ticks_us()

    def ticks_diff(self, a, b):
        return time.ticks_diff(a, b)

    def wait(self, ms):
        t0 = time.ticks_us()
        waiting.wait(self.poller, ms, self.tick_us, waiting.spin)
        self.idle_us += time.ticks_diff(time.ticks_us(), t0)  # the segment's CPU load

    def rx_any(self):
        """Which chain UARTs hold bytes not read yet (``UART.any``: the driver's ring buffer,
        ports/esp32/machine_uart.c): bit 0 upstream, bit 1 downstream."""
        m = 0
        if self.up.any():
            m = 1
        if self.down.any():
            m |= 2
        return m

    def servo_uart(self, b):
        chain = [self.pins[k] for k in _CHAIN_PINS if self.pins[k] is not None]
        if (
            b["tx"] in chain
            or b["rx"] in chain
            or b["uart"]
            in (
                self.pins["up_uart"],
                self.pins["down_uart"],
            )
        ):
            raise ValueError(
                "the servo bus (uart %d, tx %d, rx %d) shares a UART or pin with the chain: set "
                "config.json 'bus'" % (b["uart"], b["tx"], b["rx"])
            )
        return machine.UART(
            b["uart"], baudrate=b["baud"], tx=b["tx"], rx=b["rx"], rxbuf=256, timeout=0
        )

    def pwm(self, pin, freq):
        return machine.PWM(machine.Pin(pin), freq=freq, duty_ns=0)
