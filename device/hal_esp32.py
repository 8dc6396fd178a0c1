"""HAL of an ESP32 running MicroPython: machine.UART up/down, PWM / bus servos, ticks, unique id.

Pins come from config key ``pins`` (defaults below). The REPL stays on the USB port (UART0 or the
native USB of S2/S3/C3 boards); the chain uses UART1 (upstream) and UART2 (downstream).
A Feetech bus needs a third UART: use a board whose REPL is on native USB (ESP32-S3/C3) and give
the bus UART0 (config ``bus``), or use PWM servos on a classic ESP32.

The default pins are a classic ESP32's. On other chips they may be the native USB pins (S3:
GPIO19/20, C3: GPIO18/19) and a C3 has no UART2, so there the chain pins must be configured
(``pins``: up_tx, up_rx, down_tx, down_rx, and up_uart/down_uart where UART2 is missing).
"""

import os
import select
import time

import machine

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


def chip():
    """'ESP32', 'ESP32S3', 'ESP32C3', ... from os.uname().machine ('... with ESP32S3')."""
    m = os.uname().machine
    i = m.rfind("with ")
    return (m[i + 5 :] if i >= 0 else m).strip().upper()


def chain_pins(chip_name, cfg_pins):
    """UART ids, pins and baud of the chain: the defaults on a classic ESP32; elsewhere the
    chain pins must come from the config (the defaults may be that chip's USB pins)."""
    p = dict(PINS)
    if cfg_pins:
        p.update(cfg_pins)
    if chip_name != "ESP32":
        missing = [k for k in _CHAIN_PINS if not cfg_pins or k not in cfg_pins]
        if missing:
            raise ValueError(
                "this board is an %s: the default chain pins are a classic ESP32's and may be "
                "its USB pins; set %s in config.json 'pins' (docs/firmware.md)"
                % (chip_name, ", ".join(missing))
            )
    return p


class Hal:
    platform = PLATFORM
    default_driver = DEFAULT_DRIVER

    def __init__(self, cfg_pins=None):
        p = chain_pins(chip(), cfg_pins)
        self.pins = p
        # rxbuf holds at least one whole encoded frame (253 bytes) plus slack
        self.up = machine.UART(
            p["up_uart"], baudrate=p["baud"], tx=p["up_tx"], rx=p["up_rx"], rxbuf=1024, timeout=0
        )
        self.down = machine.UART(
            p["down_uart"],
            baudrate=p["baud"],
            tx=p["down_tx"],
            rx=p["down_rx"],
            rxbuf=1024,
            timeout=0,
        )
        self.poller = select.poll()
        self.poller.register(self.up, select.POLLIN)
        self.poller.register(self.down, select.POLLIN)
        self.faults_spec = None
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
        for _ in self.poller.ipoll(ms):
            break

    def servo_uart(self, b):
        chain = [self.pins[k] for k in _CHAIN_PINS]
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
