"""HAL of an ESP32 running MicroPython: machine.UART up/down, PWM / bus servos, ticks, unique id.

Pins come from config key ``pins`` (defaults below). The REPL stays on the USB port (UART0 or the
native USB of S2/S3/C3 boards); the chain uses UART1 (upstream) and UART2 (downstream).
A Feetech bus needs a third UART: use a board whose REPL is on native USB (ESP32-S3/C3) and give
the bus UART0 (config ``bus``), or use PWM servos on a classic ESP32.
"""

import select
import time

import machine

_TMASK = 0x3FFFFFFF

PLATFORM = "esp32"
DEFAULT_DRIVER = "pwm"

PINS = {"up_tx": 19, "up_rx": 18, "down_tx": 17, "down_rx": 16, "baud": 921600}


class Hal:
    platform = PLATFORM
    default_driver = DEFAULT_DRIVER

    def __init__(self, cfg_pins=None):
        p = dict(PINS)
        if cfg_pins:
            p.update(cfg_pins)
        # rxbuf holds at least one whole encoded frame (253 bytes) plus slack
        self.up = machine.UART(
            1, baudrate=p["baud"], tx=p["up_tx"], rx=p["up_rx"], rxbuf=1024, timeout=0
        )
        self.down = machine.UART(
            2, baudrate=p["baud"], tx=p["down_tx"], rx=p["down_rx"], rxbuf=1024, timeout=0
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
        return machine.UART(
            b["uart"], baudrate=b["baud"], tx=b["tx"], rx=b["rx"], rxbuf=256, timeout=0
        )

    def pwm(self, pin, freq):
        return machine.PWM(machine.Pin(pin), freq=freq, duty_ns=0)
