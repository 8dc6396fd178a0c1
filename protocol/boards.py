"""Board profiles: what each ESP32-family board offers a segment, and the rules of a wiring plan.

One source of truth read by the firmware (``device/config.py``, ``hal_esp32.py``, ``hal_unix.py``),
by ``ucr check`` / ``ucr flash`` (``ucrdf/boards.py``) and by the emulator. It lives in
``protocol/`` because that package is the one both runtimes already share and every segment
already carries; it imports nothing, so any layer may use it (docs/architecture.md, "Boards").
Facts and their sources: docs/firmware.md, "Boards".

A plan is ``pins`` (``up_uart``, ``up_tx``, ``up_rx``, ``down_uart``, ``down_tx``, ``down_rx``,
``baud``), ``bus`` (``uart``, ``tx``, ``rx`` of a serial servo bus) and ``pwm`` (``pins``: one
GPIO per hobby servo), the config.json keys of docs/firmware.md. ``resolve`` fills the board's
defaults in; ``problems`` lists every reason the plan cannot work on that board.
"""

DEFAULT_BOARD = "esp32"
BUS_DRIVERS = ("feetech_sts", "feetech_scs")


def _r(a, b):
    return tuple(range(a, b + 1))


def _reserve(*groups):
    d = {}
    for pins, why in groups:
        for p in pins:
            d[p] = why
    return d


_ESP32_RESERVED = _reserve(
    ((1, 3), "UART0 TX/RX, the REPL's"),
    (_r(6, 11), "wired to the SPI flash"),
)
_S3_RESERVED = _reserve(
    ((19, 20), "the native USB D-/D+"),
    (_r(26, 32), "wired to the SPI flash / PSRAM"),
    (_r(33, 37), "wired to the octal PSRAM on R8 modules"),
    ((43, 44), "UART0 TX/RX, the REPL's"),
)
_C3_RESERVED = _reserve(
    (_r(12, 17), "wired to the SPI flash"),
    ((18, 19), "the native USB D-/D+"),
    ((20, 21), "UART0 RX/TX, the REPL's"),
)

# uarts: hardware UART count; repl_uart: the UART stock MicroPython gives the REPL (None: REPL
# on native USB only, a custom build); heap: bytes the firmware must fit in (-X heapsize in the
# emulator; the unix VM's 64-bit objects make that stricter than on the 32-bit board); tick_hz:
# FreeRTOS tick (select.poll timeouts end on it); mhz: the CPU clock the firmware runs the chip at
# (device/hal_esp32.py sets it at boot with machine.freq: the chip's fastest, where stock builds
# start slower); pystones: pystone 1.2 score of stock MicroPython at that clock (the emulator's
# CPU factor, docs/emulator.md "Timing model").
BOARDS = {
    "esp32": {
        "chip": "ESP32",
        "uarts": 3,
        "repl_uart": 0,
        "gpio": _r(0, 19) + _r(21, 23) + _r(25, 27) + _r(32, 39),
        "reserved": _ESP32_RESERVED,
        # GPIO34..39 are inputs only (37/38 exist on some packages): the port refuses an output
        # on every GPIO >= 34 (ports/esp32/machine_pin.c GPIO_FIRST_NON_OUTPUT)
        "input_only": _r(34, 39),
        "strapping": (0, 2, 12),
        "pins": {
            "up_uart": 1,
            "up_tx": 19,
            "up_rx": 18,
            "down_uart": 2,
            "down_tx": 17,
            "down_rx": 16,
            "baud": 921600,
        },
        "bus": None,
        "pwm": [25, 26, 27, 32, 33, 13, 14, 4],
        "heap": 163840,
        "tick_hz": 100,
        "mhz": 240,
        "pystones": 1661,
    },
    "esp32s3": {
        "chip": "ESP32S3",
        "uarts": 3,
        "repl_uart": 0,
        "gpio": _r(0, 21) + _r(26, 48),
        "reserved": _S3_RESERVED,
        "input_only": (),
        "strapping": (0, 3, 45, 46),
        "pins": {
            "up_uart": 1,
            "up_tx": 17,
            "up_rx": 18,
            "down_uart": 2,
            "down_tx": 15,
            "down_rx": 16,
            "baud": 921600,
        },
        "bus": None,
        "pwm": [4, 5, 6, 7, 8, 9, 10, 11],
        "heap": 163840,
        "tick_hz": 100,
        "mhz": 240,
        "pystones": 1916,
    },
    "esp32c3": {
        "chip": "ESP32C3",
        "uarts": 2,
        "repl_uart": 0,
        "gpio": _r(0, 21),
        "reserved": _C3_RESERVED,
        "input_only": (),
        "strapping": (2, 8, 9),
        "pins": {
            "up_uart": 1,
            "up_tx": 5,
            "up_rx": 4,
            "down_uart": None,
            "down_tx": None,
            "down_rx": None,
            "baud": 921600,
        },
        "bus": None,
        "pwm": [6, 7, 10, 0, 1, 3],
        "heap": 163840,
        "tick_hz": 100,
        "mhz": 160,
        "pystones": 1292,
    },
    "unix": {
        "chip": "unix",
        "uarts": 3,
        "repl_uart": None,
        "gpio": _r(0, 63),
        "reserved": {},
        "input_only": (),
        "strapping": (),
        "pins": {
            "up_uart": 1,
            "up_tx": 1,
            "up_rx": 2,
            "down_uart": 2,
            "down_tx": 3,
            "down_rx": 4,
            "baud": 921600,
        },
        "bus": {"uart": 0, "tx": 5, "rx": 6, "baud": 1000000},
        "pwm": [10, 11, 12, 13, 14, 15, 16, 17],
        "heap": 163840,
        "tick_hz": 0,
        "mhz": 0,
        "pystones": 0,
    },
}


def _usb_repl(base, reserved_uart0, pins, bus):
    """A custom build of ``base`` with the REPL on native USB only: UART0 and its pins are free."""
    p = dict(BOARDS[base])
    p["repl_uart"] = None
    res = dict(p["reserved"])
    for pin in reserved_uart0:
        res.pop(pin, None)
    p["reserved"] = res
    p["pins"] = pins
    p["bus"] = bus
    return p


BOARDS["esp32s3-usbrepl"] = _usb_repl(
    "esp32s3",
    (43, 44),
    BOARDS["esp32s3"]["pins"],
    {"uart": 0, "tx": 43, "rx": 44, "baud": 1000000},
)
BOARDS["esp32c3-usbrepl"] = _usb_repl(
    "esp32c3",
    (20, 21),
    {
        "up_uart": 1,
        "up_tx": 5,
        "up_rx": 4,
        "down_uart": 0,
        "down_tx": 21,
        "down_rx": 20,
        "baud": 921600,
    },
    None,
)

NAMES = tuple(sorted(BOARDS))
_CHAIN_KEYS = ("up_uart", "up_tx", "up_rx", "down_uart", "down_tx", "down_rx", "baud")


def default_board(driver):
    """The board a configuration that names none runs on: ``esp32``, or ``esp32s3-usbrepl`` for
    a serial servo bus (a stock ESP32 has no UART left for one: UART0 is the REPL's)."""
    return "esp32s3-usbrepl" if driver in BUS_DRIVERS else DEFAULT_BOARD


def profile(name):
    """The profile of board ``name`` (ValueError naming the known boards otherwise)."""
    p = BOARDS.get(name)
    if p is None:
        raise ValueError("unknown board %r (boards: %s)" % (name, ", ".join(NAMES)))
    return p


def resolve(name, pins=None, bus=None, pwm=None):
    """(pins, bus, pwm_pins) of a plan: the board's defaults overridden by what is given."""
    p = profile(name)
    chain = dict(p["pins"])
    if pins:
        for k in pins:
            chain[k] = pins[k]
    b = dict(p["bus"]) if p["bus"] else {}
    if bus:
        for k in bus:
            b[k] = bus[k]
    pw = list(p["pwm"])
    if pwm and pwm.get("pins") is not None:
        pw = list(pwm["pins"])
    return chain, (b or None), pw


def _isint(v):
    return isinstance(v, int) and not isinstance(v, bool)


def problems(name, pins=None, bus=None, pwm=None, driver="pwm", servo_ids=None, n=3):
    """Every reason the plan cannot work on board ``name``: a list of (field, message).

    ``field`` is "board", "up", "down", "bus", "pwm" or "servos" (tools map it to a source line).
    Refused: an unknown board, a UART the chip lacks or the REPL's, one UART or one pin used
    twice, pins the board lacks or has wired to flash/PSRAM/USB/REPL, strapping pins, outputs on
    input-only pins, a serial servo bus where no UART is left, too few PWM pins, duplicate servo
    ids on a bus.
    """
    out = []
    p = BOARDS.get(name)
    if p is None:
        return [("board", "unknown board %r (boards: %s)" % (name, ", ".join(NAMES)))]
    chain, b, pw = resolve(name, pins, bus, pwm)
    uarts = []  # (field, role, uart id)
    used = {}  # pin -> role
    repl = p["repl_uart"]

    def uart(field, role, uid):
        if uid is None:
            if repl is not None and p["uarts"] <= 2:
                out.append(
                    (
                        field,
                        "%s has %d UARTs and UART%d is the REPL's on stock "
                        "MicroPython: no UART is left for the %s (a segment needs two: "
                        "upstream and downstream); use board '%s-usbrepl' (a build with the "
                        "REPL on native USB only)" % (name, p["uarts"], repl, role, name),
                    )
                )
            else:
                out.append((field, "no UART given for the %s" % role))
            return False
        if not _isint(uid) or not 0 <= uid < p["uarts"]:
            out.append(
                (
                    field,
                    "%s has UART0..UART%d: UART%s for the %s does not exist"
                    % (name, p["uarts"] - 1, uid, role),
                )
            )
            return False
        if uid == repl:
            out.append(
                (
                    field,
                    "UART%d is the REPL's on %s (stock MicroPython): the %s cannot "
                    "use it (bytes would reach the REPL, and mpremote could no longer "
                    "reach the board)" % (uid, name, role),
                )
            )
            return False
        for _f2, r2, u2 in uarts:
            if u2 == uid:
                out.append((field, "UART%d is used twice: %s and %s" % (uid, r2, role)))
                return False
        uarts.append((field, role, uid))
        return True

    def pin(field, role, gpio, output):
        if not _isint(gpio):
            out.append((field, "%s pin must be a GPIO number, got %r" % (role, gpio)))
            return
        if gpio not in p["gpio"]:
            out.append((field, "%s: %s has no GPIO%d" % (role, name, gpio)))
            return
        why = p["reserved"].get(gpio)
        if why:
            out.append((field, "%s: GPIO%d is %s on %s" % (role, gpio, why, name)))
            return
        if gpio in p["strapping"]:
            out.append(
                (
                    field,
                    "%s: GPIO%d is a strapping pin of %s (sampled at reset: a wire "
                    "there can stop the board booting)" % (role, gpio, name),
                )
            )
            return
        if output and gpio in p["input_only"]:
            out.append((field, "%s: GPIO%d is input-only on %s" % (role, gpio, name)))
            return
        if gpio in used:
            out.append((field, "GPIO%d is used twice: %s and %s" % (gpio, used[gpio], role)))
            return
        used[gpio] = role

    for side, field, role in (("up", "up", "upstream UART"), ("down", "down", "downstream UART")):
        if uart(field, role, chain.get(side + "_uart")):
            pin(field, role + " TX", chain.get(side + "_tx"), True)
            pin(field, role + " RX", chain.get(side + "_rx"), False)
    baud = chain.get("baud")
    if not _isint(baud) or not 9600 <= baud <= 5000000:
        out.append(("up", "chain baud must be an int 9600..5000000, got %r" % (baud,)))
    if driver in BUS_DRIVERS:
        if not b:
            out.append(
                (
                    "bus",
                    "%s has no UART left for a serial servo bus: UART%s is the "
                    "REPL's and the chain needs two; use PWM servos, or a board whose REPL "
                    "is on native USB only (%s)"
                    % (name, repl, ", ".join(k for k in NAMES if k.endswith("-usbrepl"))),
                )
            )
        elif uart("bus", "servo bus", b.get("uart")):
            pin("bus", "servo bus TX", b.get("tx"), True)
            pin("bus", "servo bus RX", b.get("rx"), False)
        ids = servo_ids or []
        seen = {}
        for i, sid in enumerate(ids):
            if sid in seen:
                out.append(
                    ("servos", "servo %d has the same bus id %r as servo %d" % (i, sid, seen[sid]))
                )
            seen[sid] = i
    elif driver == "pwm":
        if len(pw) < n:
            out.append(("pwm", "%d PWM pins for %d servos" % (len(pw), n)))
        for i, g in enumerate(pw[:n]):
            pin("pwm", "PWM servo %d" % i, g, True)
    return out
