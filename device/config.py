"""Segment configuration: load ``config.json`` (SI units), fall back to defaults, convert to ints.

The file is generated from the robot's U(C)RDF by ``tools/segment_config.py``; keys are those of
docs/architecture.md ("Segment configuration"). Device-only optional keys (not generated, see
docs/firmware.md): ``sc`` (simple-controller strategy), ``sc_gain``, ``servo_speed`` (rad/s, SC
slew and emulated servo speed), ``servo_tau`` (s, emulated servo time constant), ``pins`` (ESP32 pin
map), ``pwm`` (hobby servo calibration), ``bus`` (serial bus servo settings); ``board`` and the
pins are generated too and checked against protocol/boards.py, whose defaults fill the gaps.

Device-only safety keys: ``fault_action`` ("hold" | "release": what the servos do in FAULT),
``hw_watchdog_ms`` (0 = off: the hardware watchdog, fed only by a healthy loop), ``tick_ms``
(the control tick's period, 2..50 ms, default 5), per servo
``rest_angle`` (rad from zero: the power-on pose an open-loop servo is assumed at), and for the
emulated driver ``emulated_start`` (raw power-on angles, rad).

Floats are used here, once at boot; the control cycle only sees the ints computed here.
An absent file runs the defaults (UNCONFIGURED); an invalid one leaves the segment unable to move
(``error`` says why): it never runs the defaults in place of a configuration it was given.
"""

import math

FW_VERSION = "0.1.0"

_TWO_PI_3 = 2.0 * math.pi / 3.0
_TICK_MIN = 2  # ms: the control tick's period, 500 Hz ...
_TICK_MAX = 50  # ... to 20 Hz (docs/firmware.md "CPU load": a slower tick for a slow board)

# Defaults: the paper's segment (316 mm, three tendons 120 deg apart, bend up to 60 deg).
DEFAULTS = {
    "name": "segment",
    "length": 0.316,
    "tendon_angles": [0.0, _TWO_PI_3, 2.0 * _TWO_PI_3],
    "tendon_radius": 0.05,
    "spool_radius": 0.02,
    "kappa_max": (math.pi / 3.0) / 0.316,
    "kappa_rate_max": None,  # None: protocol/constants.py's DEFAULT_KAPPA_RATE_MAX (one default)
    "mass": 0.5,
    "backbone_radius": 0.003,
    "model": "pcc",
    "servo_driver": None,  # None: the HAL's default driver ("emulated" on unix, "pwm" on ESP32)
    "servos": None,  # None: one default servo per tendon
    "watchdog_ms": 200,
    "uid_override": None,
    "sc": "direct",
    "sc_gain": 0.5,
    "servo_speed": 6.0,
    "servo_tau": 0.03,
    "pins": None,
    "pwm": None,
    "bus": None,
    "board": None,  # None: protocol/boards.py default_board(servo_driver)
    "fault_action": "hold",
    "hw_watchdog_ms": 0,
    "tick_ms": 5,  # the control tick's period (200 Hz); main.py runs it
    "emulated_start": None,
}

_SERVO_DEFAULT = {
    "zero_offset": 0.0,
    "direction": 1,
    "min_angle": -math.pi,
    "max_angle": math.pi,
    "rest_angle": 0.0,
}

#: profile of the board of the configuration loaded last (protocol/boards.py), for the HAL
PROFILE = None
PROFILE_NAME = None

KAPPA_SCALE = 10000  # 1e-4 1/m (mirrors protocol/constants.py; contract in docs/architecture.md)
ANGLE_SCALE = 10000  # 1e-4 rad
LENGTH_SCALE = 1000000  # 1e-6 m

# Bounds that keep every hot-path intermediate a small int on a 32-bit MCU (see docs/firmware.md)
_MAX_KAPPA = 100.0  # 1/m
_MAX_LENGTH = 2.0  # m
_MAX_ANGLE = 50.0  # rad of servo travel from zero
_MAX_TENDONS = 8


RATE_MIN = 1e-3  # 1/m/s: the slowest kappa_rate_max (config.json and PARAM_SET)


def kappa_limit_problem(v):
    """Why ``v`` cannot be a kappa_max (1/m), or None: it must be > 0 and not round to 0 units
    of 1e-4 1/m (KAPPA_SCALE), which the fixed-point path would run as 0 (config.json, PARAM_SET
    and ``ucr check`` apply the same rule)."""
    if not v > 0.0:
        return "must be > 0 1/m, got %r" % (v,)
    if v * KAPPA_SCALE < 0.5:  # int(v * KAPPA_SCALE + 0.5), _derive's rounding, would be 0
        return "%r 1/m rounds to 0 units of 1e-4 1/m (at least 5e-05)" % (v,)
    return None


def _num(cfg, key, lo, hi):
    v = cfg[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError("%s must be a number, got %r" % (key, v))
    v = float(v)
    if not (lo <= v <= hi):
        raise ValueError("%s = %r outside [%r, %r]" % (key, v, lo, hi))
    return v


class Config:
    """Validated configuration: SI floats (``si``) plus the fixed-point ints of the hot path.

    Attributes (ints unless said): ``length_um``, ``kappa_max`` (1e-4 1/m), ``rate_max`` (1e-4 1/m
    per s), ``watchdog_ms``, ``n`` tendons, ``tendon_angles`` (1e-4 rad), ``zero`` / ``direction``
    / ``min_angle`` / ``max_angle`` per servo (1e-4 rad), ``servo_ids``; ``unconfigured`` (bool),
    ``error`` (text or None), ``si`` (dict of the SI values as loaded).
    """

    def __init__(self, data=None, default_driver="emulated"):
        self.unconfigured = data is None
        self.error = None
        cfg = dict(DEFAULTS)
        if data is not None:
            if not isinstance(data, dict):
                raise ValueError("config must be a JSON object")
            for k in data:
                cfg[k] = data[k]
        if cfg["servo_driver"] is None:
            cfg["servo_driver"] = default_driver
        self._validate(cfg)
        if cfg["kappa_rate_max"] is None:  # loaded after the board rules left (heap peak)
            import gc

            gc.collect()
            from protocol.constants import DEFAULT_KAPPA_RATE_MAX

            cfg["kappa_rate_max"] = DEFAULT_KAPPA_RATE_MAX
        self.si = cfg
        self._derive(cfg)

    def _validate(self, cfg):
        if not isinstance(cfg["name"], str) or not cfg["name"]:
            raise ValueError("name must be a non-empty string")
        _num(cfg, "length", 1e-3, _MAX_LENGTH)
        _num(cfg, "tendon_radius", 1e-4, 0.5)
        _num(cfg, "spool_radius", 1e-4, 0.15)
        _num(cfg, "kappa_max", 0.0, _MAX_KAPPA)
        why = kappa_limit_problem(cfg["kappa_max"])
        if why:
            raise ValueError("kappa_max %s" % why)
        if cfg["kappa_rate_max"] is not None:
            _num(cfg, "kappa_rate_max", RATE_MIN, 10 * _MAX_KAPPA)
        _num(cfg, "mass", 0.0, 1e3)
        _num(cfg, "backbone_radius", 0.0, 0.5)
        _num(cfg, "watchdog_ms", 10, 60000)
        _num(cfg, "sc_gain", 0.01, 1.0)
        _num(cfg, "servo_speed", 0.01, 100.0)
        _num(cfg, "servo_tau", 0.0, 10.0)
        ang = cfg["tendon_angles"]
        if not isinstance(ang, list) or not (2 <= len(ang) <= _MAX_TENDONS):
            raise ValueError("tendon_angles must be a list of 2..%d angles (rad)" % _MAX_TENDONS)
        for a in ang:
            if isinstance(a, bool) or not isinstance(a, (int, float)) or abs(a) > 10.0:
                raise ValueError("tendon_angles: bad angle %r" % (a,))
        if not isinstance(cfg["model"], str):
            raise ValueError("model must be a string")
        if cfg["sc"] not in ("direct", "p_slew"):
            raise ValueError("sc must be 'direct' or 'p_slew', got %r" % (cfg["sc"],))
        if cfg["servo_driver"] not in _DRIVERS:
            raise ValueError("unknown servo_driver %r" % (cfg["servo_driver"],))
        if cfg["fault_action"] not in ("hold", "release"):
            raise ValueError(
                "fault_action must be 'hold' or 'release', got %r" % (cfg["fault_action"],)
            )
        hw = cfg["hw_watchdog_ms"]
        if isinstance(hw, bool) or not isinstance(hw, int) or not (hw == 0 or 50 <= hw <= 60000):
            raise ValueError("hw_watchdog_ms must be 0 (off) or an int 50..60000, got %r" % (hw,))
        tk = cfg["tick_ms"]
        if isinstance(tk, bool) or not isinstance(tk, int) or not (_TICK_MIN <= tk <= _TICK_MAX):
            raise ValueError(
                "tick_ms must be an int %d..%d (ms), got %r" % (_TICK_MIN, _TICK_MAX, tk)
            )
        if hw and hw < 4 * tk:
            raise ValueError(
                "hw_watchdog_ms %r is shorter than four ticks (tick_ms %d): it is fed once per "
                "clean tick" % (hw, tk)
            )
        if cfg["watchdog_ms"] < 2 * tk:
            raise ValueError(
                "watchdog_ms %r is shorter than two ticks (tick_ms %d): the tick checks it"
                % (cfg["watchdog_ms"], tk)
            )
        if cfg["servo_speed"] * 10.0 * tk < 1.0:
            raise ValueError(
                "servo_speed %r rad/s is below one step (1e-4 rad) per tick of %d ms: the servo "
                "commands could not move that slowly (at least %.3g rad/s)"
                % (cfg["servo_speed"], tk, 0.1 / tk)
            )
        servos = cfg["servos"]
        if servos is None:
            servos = [{"id": i} for i in range(len(ang))]
        if not isinstance(servos, list) or len(servos) != len(ang):
            raise ValueError("servos must list one servo per tendon (%d)" % len(ang))
        full = []
        for i, s in enumerate(servos):
            if not isinstance(s, dict):
                raise ValueError("servos[%d] must be an object" % i)
            d = dict(_SERVO_DEFAULT)
            d["id"] = i
            for k in s:
                d[k] = s[k]
            if isinstance(d["id"], bool) or not isinstance(d["id"], int) or not 0 <= d["id"] < 254:
                raise ValueError("servos[%d].id must be an int 0..253" % i)
            if d["direction"] not in (1, -1):
                raise ValueError("servos[%d].direction must be 1 or -1" % i)
            for k in ("zero_offset", "min_angle", "max_angle", "rest_angle"):
                try:
                    _num(d, k, -_MAX_ANGLE, _MAX_ANGLE)
                except ValueError as e:
                    raise ValueError("servos[%d].%s" % (i, e)) from None
            if d["min_angle"] >= d["max_angle"]:
                raise ValueError("servos[%d]: min_angle must be below max_angle" % i)
            # the rest pose is where an open-loop (PWM) servo is assumed at power-on: its first
            # pulse goes there, so it must lie inside the range (docs/firmware.md, First motion)
            if (cfg["servo_driver"] == "pwm" or "rest_angle" in s) and not (
                d["min_angle"] <= d["rest_angle"] <= d["max_angle"]
            ):
                raise ValueError(
                    "servos[%d]: rest pose %r rad (rest_angle, from zero) outside its range "
                    "[%r, %r]: the first PWM pulse would drive it there"
                    % (i, d["rest_angle"], d["min_angle"], d["max_angle"])
                )
            full.append(d)
        cfg["servos"] = full
        _wiring(cfg, len(ang))
        start = cfg["emulated_start"]
        if start is not None:
            if not isinstance(start, list) or len(start) != len(ang):
                raise ValueError("emulated_start must list one raw angle (rad) per servo")
            for a in start:
                if (
                    isinstance(a, bool)
                    or not isinstance(a, (int, float))
                    or not abs(a) <= 2 * _MAX_ANGLE
                ):
                    raise ValueError("emulated_start: bad angle %r" % (a,))
        if cfg["uid_override"] is not None and not isinstance(cfg["uid_override"], str):
            raise ValueError("uid_override must be a string")
        # the DESCRIPTOR must fit one frame (protocol/desc_room.py, loaded for this only)
        from protocol import desc_room

        why = desc_room.problem(cfg, FW_VERSION)
        self.err_room = min(40, desc_room.room(cfg, FW_VERSION))  # config_error bytes sent
        _drop("desc_room")
        if why:
            raise ValueError(why)

    def _derive(self, cfg):
        self.name = cfg["name"]
        self.n = len(cfg["tendon_angles"])
        self.length_um = int(cfg["length"] * LENGTH_SCALE + 0.5)
        self.kappa_max = int(cfg["kappa_max"] * KAPPA_SCALE + 0.5)
        self.rate_max = int(cfg["kappa_rate_max"] * KAPPA_SCALE + 0.5)
        self.watchdog_ms = int(cfg["watchdog_ms"])
        self.tendon_angles = [_e4(a) for a in cfg["tendon_angles"]]
        s = cfg["servos"]
        self.servo_ids = [d["id"] for d in s]
        self.zero = [_e4(d["zero_offset"]) for d in s]
        self.direction = [d["direction"] for d in s]
        self.min_angle = [_e4(d["min_angle"]) for d in s]
        self.max_angle = [_e4(d["max_angle"]) for d in s]
        self.rest = [_e4(d["rest_angle"]) for d in s]
        self.fault_action = cfg["fault_action"]
        self.hw_watchdog_ms = cfg["hw_watchdog_ms"]
        self.tick_ms = cfg["tick_ms"]
        self.driver = cfg["servo_driver"]
        self.sc = cfg["sc"]
        self.uid_override = cfg["uid_override"]


def _wiring(cfg, n):
    """Board and pin plan (protocol/boards.py, the rules ``ucr check`` applies too): refuse an
    impossible plan; fill the board's default pins into ``pins``, ``bus`` and ``pwm``."""
    import gc

    gc.collect()
    from protocol import boards

    board = cfg["board"]
    if board is None:
        board = boards.default_board(cfg["servo_driver"])
    if not isinstance(board, str):
        raise ValueError("board must be a board name, got %r" % (board,))
    for k in ("pins", "bus", "pwm"):
        if cfg[k] is not None and not isinstance(cfg[k], dict):
            raise ValueError("%s must be an object" % k)
    ids = [d["id"] for d in cfg["servos"]]
    found = boards.problems(board, cfg["pins"], cfg["bus"], cfg["pwm"], cfg["servo_driver"], ids, n)
    if found:
        raise ValueError("board %s: %s" % (board, found[0][1]))
    chain, bus, pw = boards.resolve(board, cfg["pins"], cfg["bus"], cfg["pwm"])
    chain["board"] = board  # the HAL reads the board with its pins (main.py passes ``pins``)
    cfg["board"] = board
    cfg["pins"] = chain
    cfg["bus"] = bus
    pwm = dict(cfg["pwm"]) if cfg["pwm"] else {}
    pwm["pins"] = pw
    cfg["pwm"] = pwm
    global PROFILE, PROFILE_NAME
    PROFILE = boards.profile(board)
    PROFILE_NAME = board
    del boards
    _drop()


def _e4(x):
    v = x * 10000.0
    return int(v + 0.5) if v >= 0 else -int(-v + 0.5)


def load(path="config.json", default_driver="emulated"):
    """Read ``path``; absent -> defaults (unconfigured); invalid -> defaults with ``error`` set."""
    import json

    try:
        with open(path) as f:
            text = f.read()
    except OSError:
        return Config(None, default_driver)
    data = None
    try:
        data = json.loads(text)
        cfg = Config(data, default_driver)
        import mechanism

        mechanism.Mechanism(cfg, 5)  # geometry must fit the fixed-point scheme too
        return cfg
    except (ValueError, TypeError, KeyError) as e:
        return refused(data, default_driver, "config.json rejected: %s" % (e,))


def refused(data, default_driver, why):
    """The configuration of a segment that refuses the one it was given (``data``, the parsed
    config.json, or None): it never moves and ``error`` says ``why`` (DESCRIPTOR key 16, PARAM
    16). It substitutes no defaults for what the configuration named: the chain keeps the
    configured board and chain pins when they form a usable chain on that board (the board a
    configuration without ``board`` means, ``protocol.boards.default_board``); otherwise no board
    is named (``pins`` and ``board`` None) and the HAL uses the chip's own board, from its own
    detection (``hal_esp32.own_pins``), never another chip's. ``main.build`` gives it no servo
    driver that drives pins (``servos.OfflineBus``)."""
    global PROFILE, PROFILE_NAME
    c = Config(None, default_driver)
    c.error = why
    c.si["board"] = None
    c.si["pins"] = None
    if not isinstance(data, dict):
        return c
    import gc

    gc.collect()
    try:
        from protocol import boards

        board = data.get("board")
        if board is None:
            board = boards.default_board(data.get("servo_driver") or default_driver)
        pins = data.get("pins")
        servo = []
        if isinstance(board, str):
            servo = _servo_pins(boards, board, data, default_driver)
            c.si["servo_pins"] = servo  # never a chain UART on them (hal_esp32.Hal avoid)
        if isinstance(board, str) and (pins is None or isinstance(pins, dict)):
            # the chain only: "emulated" servos make problems() check no bus and no PWM pins
            found = boards.problems(board, pins, None, None, "emulated", [], 0)
            if not found:
                chain = boards.resolve(board, pins)[0]
                if not [k for k in _CHAIN_KEYS if chain.get(k) in servo]:
                    chain["board"] = board
                    c.si["board"] = board
                    c.si["pins"] = chain
                    PROFILE = boards.profile(board)
                    PROFILE_NAME = board
    except (ValueError, TypeError, KeyError, AttributeError):
        pass  # a plan too broken to read: the chip's own board
    _drop()
    return c


_CHAIN_KEYS = ("up_tx", "up_rx", "down_tx", "down_rx")
_DRIVERS = ("emulated", "pwm", "feetech_sts", "feetech_scs")


def _servo_pins(boards, board, data, default_driver):
    """The pins a refused configuration's servos are wired to (its ``pwm``/``bus`` over the
    board's defaults, for its ``servo_driver``; both kinds when the driver is unknown): UART
    bytes on one would drive that servo."""
    drv = data.get("servo_driver") or default_driver
    bus, pwm = data.get("bus"), data.get("pwm")
    _, b, pw = boards.resolve(
        board, None, bus if isinstance(bus, dict) else None, pwm if isinstance(pwm, dict) else None
    )
    out = []
    if drv == "emulated":
        return out
    if drv != "pwm" or drv not in _DRIVERS:  # a serial bus (or unknown: both kinds)
        if b:
            out += [b.get("tx"), b.get("rx")]
    if drv == "pwm" or drv not in _DRIVERS:
        servos = data.get("servos")
        # one PWM pin per servo, the first of the list (all of it when the count is unknown)
        out += list(pw)[: len(servos)] if isinstance(servos, list) and servos else list(pw)
    return [x for x in out if isinstance(x, int) and not isinstance(x, bool)]


def _drop(name="boards"):
    """Free module protocol.``name`` on the board: the board rules (~15 KB) and the DESCRIPTOR
    rule are needed once, at boot (the HAL reads PROFILE)."""
    import gc
    import sys

    if sys.implementation.name == "micropython":
        sys.modules.pop("protocol." + name, None)
        import protocol

        if hasattr(protocol, name):
            delattr(protocol, name)
        gc.collect()
