"""Slow path of a segment: parameters (PARAM_GET / PARAM_SET), the descriptor, FAULT entry and
CLEAR_FAULT.

Functions of the ``Segment`` (passed as ``self``), kept out of segment.py so that each module is
compiled on its own at boot (the compiler's peak heap grows with a module's size). They allocate
(CBOR decoding and replies); the control cycle never calls them. Parameter ids and names:
docs/firmware.md.
"""

try:
    from micropython import const
except ImportError:  # CPython

    def const(x):
        return x


import gc

import config
import sc as scmod

gc.collect()  # sc (and mech_fast) loaded: the codec is loaded on a clean heap
from protocol import cbor  # noqa: E402
from protocol import device as pd  # noqa: E402
from protocol.constants import (  # noqa: E402
    ERR_BAD_VALUE,
    ERR_IDENTITY_MISMATCH,
    ERR_MALFORMED,
    ERR_UNKNOWN_PARAM,
    ERR_UNKNOWN_TYPE,
    EV_FAULT,
    EV_FAULT_CLEARED,
    FAULT_NAMES,
    FLAG_BCAST,
    FLAG_UP,
    HEADER_LEN,
    T_CLEAR_FAULT,
    T_DESCRIPTOR,
    T_DISCOVER,
    T_ERROR,
    T_PARAM_GET,
    T_PARAM_SET,
    T_PARAM_VALUE,
    VERSION,
)
from protocol.frame import frame_into  # noqa: E402

_WIRE_MAX = 0x3FFFFFFF  # the wire's int range: |n| < 2**30 (docs/protocol.md "Integer range")

# parameter ids (PARAM_GET / PARAM_SET); names and units in docs/firmware.md
_P_WATCHDOG_MS = const(0)
_P_KAPPA_MAX = const(1)
_P_KAPPA_RATE_MAX = const(2)
_P_SC = const(3)
_P_SC_GAIN = const(4)
_P_FAULTS = const(5)
_P_FRAMES_OK = const(6)
_P_CRC_ERRORS = const(7)
_P_FRAMING_ERRORS = const(8)
_P_DROPPED = const(9)
_P_UID = const(10)
_P_STATUS = const(11)
_P_SERVO_FAULTS = const(12)
_P_CYCLE_US = const(13)
_P_OVERRUNS = const(14)
_P_POSITION = const(15)
_P_CONFIG_ERROR = const(16)
_P_MEM_FREE = const(17)
_P_EVENTS_LOST = const(18)
_P_SERVO_TARGETS = const(19)
_P_FAULT = const(20)
_P_FAULT_COUNT = const(21)
_P_SERVO_TELEMETRY = const(22)
_P_CPU_LOAD = const(23)
_P_TICK_MS = const(24)

PARAM_NAMES = (
    "watchdog_ms",
    "kappa_max",
    "kappa_rate_max",
    "sc",
    "sc_gain",
    "faults",
    "frames_ok",
    "crc_errors",
    "framing_errors",
    "dropped",
    "uid",
    "status",
    "servo_faults",
    "cycle_us",
    "overruns",
    "position",
    "config_error",
    "mem_free",
    "events_lost",
    "servo_targets",
    "fault",
    "fault_count",
    "servo_telemetry",
    "cpu_load",
    "tick_ms",
)


def reply(self, mtype, seq, obj):
    """CBOR-encode ``obj`` (protocol.cbor) into an UP frame and send it (``Segment._reply``)."""
    try:
        end = cbor.dumps_into(obj, self.raw, HEADER_LEN)
        end = frame_into(self.raw, end, FLAG_UP, 0, mtype, seq, self.wire)
    except (IndexError, ValueError, TypeError):
        # too long for one frame (or not encodable): say so instead of going silent
        end = cbor.dumps_into(
            {0: ERR_BAD_VALUE, 1: mtype, 2: "reply does not fit a frame"}, self.raw, HEADER_LEN
        )
        end = frame_into(self.raw, end, FLAG_UP, 0, T_ERROR, seq, self.wire)
    self._up(end)


def request(self, t, flags, hop, raw, pe, seq):
    """A request other than SYNC, HEARTBEAT, HOLD, ALIVE and CALIBRATE (``Segment._process``):
    DISCOVER, PARAM_GET/SET, CLEAR_FAULT; any other type is answered with ERROR."""
    if t == T_DISCOVER:
        if flags & FLAG_BCAST:
            self.position = hop
        if pd.decode_empty(raw, HEADER_LEN, pe) < 0:
            self.dropped += 1
            self._error(seq, ERR_MALFORMED, t, "malformed DISCOVER")
            return
        self._reply(T_DESCRIPTOR, seq, descriptor_payload(self))
    elif t == T_PARAM_GET or t == T_PARAM_SET:
        param_request(self, t, raw, pe, seq)
    elif t == T_CLEAR_FAULT:
        clear_fault_request(self, raw, pe, seq)
    else:
        self.dropped += 1
        self._error(seq, ERR_UNKNOWN_TYPE, t, "unknown or non-request message type 0x%02x" % t)


def enter_fault(self, code, text):
    """Enter FAULT (``Segment.enter_fault``). Servos hold where they are (config
    ``fault_action`` "release": stop driving them), an EVENT FAULT (detail = code, key 3 =
    ``text``) goes up, STATE carries the FAULT and HOLD bits, ``fault_count`` counts every
    exception. Only CLEAR_FAULT leaves it (for HOLD)."""
    self.fault_count += 1
    if self.fault_code:
        return  # already in FAULT: counted
    self.fault_code = code
    b = text.encode()
    n = len(b)
    room = len(self.fault_msg)
    if n > room:
        n = room
        while n and b[n] & 0xC0 == 0x80:
            n -= 1  # never cut a UTF-8 sequence
    for i in range(n):
        self.fault_msg[i] = b[i]
    self.fault_len = n
    self.hold = True
    try:
        if self.cfg.fault_action == "release":
            self.moving = False
            self.bus.release()
        elif self.moving:
            self._stop_moving()
    except Exception:  # noqa: BLE001 - the bus may be what failed; the fault stands
        self.moving = False
    self.event(EV_FAULT, code)


def clear_fault(self):
    """Leave FAULT for HOLD (``Segment.clear_fault``); False if not in FAULT."""
    code = self.fault_code
    if not code:
        return False
    self.fault_code = 0
    self.fault_len = 0
    self.event(EV_FAULT_CLEARED, code)
    return True


def clear_fault_request(self, raw, pe, seq):
    """CLEAR_FAULT: check the request (uid), then ``Segment.clear_fault``."""
    try:
        req = cbor.loads(raw, HEADER_LEN, pe) if pe > HEADER_LEN else {}
    except ValueError:
        req = None
    ok = isinstance(req, dict)
    if ok:
        for k in req:
            if not isinstance(k, int) or isinstance(k, bool):
                ok = False
        if 15 in req and not isinstance(req[15], str):
            ok = False
    if not ok:
        self.dropped += 1
        self._error(seq, ERR_MALFORMED, T_CLEAR_FAULT, "malformed CLEAR_FAULT")
        return
    uid = req.get(15)
    if uid is not None and uid.lower() != self.uid:
        self._error(
            seq,
            ERR_IDENTITY_MISMATCH,
            T_CLEAR_FAULT,
            "identity mismatch: this segment is %s" % self.uid,
        )
        return
    self.clear_fault()


def descriptor(self):
    """Descriptor dict with the contract's names (SI floats)."""
    si = self.cfg.si
    return {
        "uid": self.uid,
        "fw_version": config.FW_VERSION,
        "protocol_version": VERSION,
        "model": si["model"],
        "length": float(si["length"]),
        "tendon_angles": [float(a) for a in si["tendon_angles"]],
        "tendon_radius": float(si["tendon_radius"]),
        "spool_radius": float(si["spool_radius"]),
        "kappa_max": self.kappa_max_si,
        "kappa_rate_max": self.rate_max_si,
        "mass": float(si["mass"]),
        "backbone_radius": float(si["backbone_radius"]),
        "name": si["name"],
        "servo_driver": si["servo_driver"],
        "watchdog_ms": self.watchdog_ms,
        "downstream_present": self.down_present,
        # why config.json was refused, shortened to fit the frame (full text: PARAM 16): at
        # most 40 bytes, fewer when the name leaves less room (config.descriptor_room)
        "config_error": _cut(self.cfg.error or "", self.cfg.err_room),
        "config_hash": _config_hash(self),
    }


def _cut(text, n):
    """``text`` cut to at most ``n`` bytes of UTF-8, never inside a character."""
    b = text.encode()
    if len(b) > n:
        while b[n] & 0xC0 == 0x80:
            n -= 1
        text = b[:n].decode()
    return text


def _config_hash(self):
    """protocol/calibration.py config_hash of what runs (cached; device/calib.py resets it)."""
    h = getattr(self, "cfg_hash", None)
    if h is None:
        h = getattr(self.cfg, "hash", None)  # main.build computes it at boot
        if h is None:
            try:
                from protocol.confighash import config_hash

                h = config_hash(self.cfg.si)
            except MemoryError:
                return None  # not sent (key 17 absent): `ucr doctor` says so
        self.cfg_hash = h
    return h


def descriptor_payload(self):
    """DESCRIPTOR payload: int keys 0..17 of the contract, SI floats."""
    d = descriptor(self)
    p = {
        0: d["uid"],
        1: d["fw_version"],
        2: d["protocol_version"],
        3: d["model"],
        4: d["length"],
        5: d["tendon_angles"],
        6: d["tendon_radius"],
        7: d["spool_radius"],
        8: d["kappa_max"],
        9: d["kappa_rate_max"],
        10: d["mass"],
        11: d["backbone_radius"],
        12: d["name"],
        13: d["servo_driver"],
        14: d["watchdog_ms"],
        15: d["downstream_present"],
        16: d["config_error"],
        17: d["config_hash"],
    }
    if p[17] is None:
        del p[17]  # not computed (no heap for it): absent, the host reports that
    return p


def param_request(self, t, raw, pe, seq):
    """PARAM_GET / PARAM_SET: decode, check keys (ints only), identity and id, answer
    PARAM_VALUE or ERROR."""
    try:
        req = cbor.loads(raw, HEADER_LEN, pe) if pe > HEADER_LEN else {}
    except ValueError as e:
        req = "CBOR: %s" % (e,)
    err = None
    if not isinstance(req, dict):
        err = req if isinstance(req, str) else "payload is not a map"
    elif [k for k in req if type(k) is not int]:  # (bool keys are not ints here)
        err = "map keys must be ints"
    elif not isinstance(req.get(0), int) or isinstance(req.get(0), bool):
        err = "key 0 (param_id) must be an int"
    elif 15 in req and not isinstance(req[15], str):
        err = "key 15 (uid) must be text"
    elif t == T_PARAM_SET and 1 not in req:
        err = "key 1 (value) missing"
    if err is not None:
        self.dropped += 1
        self._error(seq, ERR_MALFORMED, t, err)
        return
    uid = req.get(15)
    if uid is not None and uid.lower() != self.uid:
        self._error(
            seq, ERR_IDENTITY_MISMATCH, t, "identity mismatch: this segment is %s" % self.uid
        )
        return
    pid = req[0]
    if not 0 <= pid < len(PARAM_NAMES):
        self._error(
            seq,
            ERR_UNKNOWN_PARAM,
            t,
            "unknown parameter %d (0..%d)" % (pid, len(PARAM_NAMES) - 1),
        )
        return
    try:
        if t == T_PARAM_SET:
            set_param(self, pid, req[1])
        value = get_param(self, pid)
    except Exception as e:  # noqa: BLE001 - any refused value is answered, never escapes poll()
        self._error(seq, ERR_BAD_VALUE, t, "%s: %s" % (PARAM_NAMES[pid], e))
        return
    if isinstance(value, int) and not -_WIRE_MAX <= value <= _WIRE_MAX:
        # a counter past the wire's int range (frames_ok passes 2**30 after ~12 days at 1000
        # frames/s): reported modulo 2**30, as the host's decoder refuses larger ints
        value &= _WIRE_MAX
    self._reply(T_PARAM_VALUE, seq, {0: pid, 1: value})


def get_param(self, pid):
    if pid == _P_WATCHDOG_MS:
        return self.watchdog_ms
    if pid == _P_KAPPA_MAX:
        return self.kappa_max_si
    if pid == _P_KAPPA_RATE_MAX:
        return self.rate_max_si
    if pid == _P_SC:
        return self.sc.name
    if pid == _P_SC_GAIN:
        return float(self.sc.gain)
    if pid == _P_FAULTS:
        f = getattr(self.bus, "faults_text", None)
        return f() if f else "none"
    if pid == _P_FRAMES_OK:
        return self.rd_up.stats()["ok"] + self.rd_dn.stats()["ok"]
    if pid == _P_CRC_ERRORS:
        return self.rd_up.stats()["crc_error"] + self.rd_dn.stats()["crc_error"]
    if pid == _P_FRAMING_ERRORS:
        u = self.rd_up.stats()
        d = self.rd_dn.stats()
        return u["framing_error"] + u["oversize"] + d["framing_error"] + d["oversize"]
    if pid == _P_DROPPED:
        return self.dropped
    if pid == _P_UID:
        return self.uid
    if pid == _P_STATUS:
        return self.status()
    if pid == _P_SERVO_FAULTS:
        return [self.prev_fault[i] for i in range(self.n)]  # incl. stalls found here
    if pid == _P_CYCLE_US:
        return self.cycle_us_max
    if pid == _P_OVERRUNS:
        return self.overruns
    if pid == _P_POSITION:
        return self.position
    if pid == _P_CONFIG_ERROR:
        return self.cfg.error or ""
    if pid == _P_MEM_FREE:
        import gc

        return gc.mem_free() if hasattr(gc, "mem_free") else -1
    if pid == _P_EVENTS_LOST:
        return self.events_lost
    if pid == _P_SERVO_TARGETS:
        return [self.mc.servo_target[i] for i in range(self.n)]
    if pid == _P_FAULT:
        if not self.fault_code:
            return ""
        return "%s: %s" % (
            FAULT_NAMES.get(self.fault_code, str(self.fault_code)),
            bytes(self.fault_msg[: self.fault_len]).decode(),
        )
    if pid == _P_FAULT_COUNT:
        return self.fault_count
    if pid == _P_SERVO_TELEMETRY:
        tel = getattr(self.bus, "telemetry", None)
        out = []
        for i in range(self.n):
            t = tel(i) if tel else None
            out.append(None if t is None else [float(t[0]), float(t[1]), float(t[2])])
        return out
    if pid == _P_CPU_LOAD:
        return [self.cpu_load, self.cpu_load_peak]
    if pid == _P_TICK_MS:
        return self.tick_ms
    raise ValueError("unknown parameter")


def set_param(self, pid, v):
    """Change a run-time parameter (SI units); ValueError with the reason if refused."""
    num = not isinstance(v, bool) and isinstance(v, (int, float))
    if pid == _P_WATCHDOG_MS:
        if not num or not 10 <= v <= 60000 or int(v) != v:  # range first: int(inf) raises
            raise ValueError("must be an int 10..60000 (ms)")
        if v < 2 * self.tick_ms:  # the rule config.json has (config.Config)
            raise ValueError(
                "must be at least two ticks (%d ms): the tick checks it" % (2 * self.tick_ms)
            )
        self.watchdog_ms = int(v)
    elif pid == _P_KAPPA_MAX:
        top = float(self.cfg.si["kappa_max"])
        if not num or not 0.0 < v <= top:
            raise ValueError("must be in (0, %g] 1/m (the flashed limit)" % top)
        why = config.kappa_limit_problem(v)  # the rule config.json has: not 0 units
        if why:
            raise ValueError(why)
        self.kappa_max_si = float(v)
        self.mc.set_kappa_max(int(v * config.KAPPA_SCALE + 0.5))
    elif pid == _P_KAPPA_RATE_MAX:
        top = float(self.cfg.si["kappa_rate_max"])
        if not num or not config.RATE_MIN <= v <= top:  # the rule config.json has
            raise ValueError(
                "must be in [%g, %g] 1/m/s (the flashed limit)" % (config.RATE_MIN, top)
            )
        self.rate_max_si = float(v)
        self.mc.set_rate_max(int(v * config.KAPPA_SCALE + 0.5))
    elif pid == _P_SC:
        if not isinstance(v, str):
            raise ValueError("must be text: one of %s" % ", ".join(scmod.STRATEGIES))
        self.sc.set_strategy(v)
        self.sc.reset(self.bus.pos if not self.moving else self.sc.cmd)
    elif pid == _P_SC_GAIN:
        if not num or not 0.01 <= v <= 1.0:
            raise ValueError("must be 0.01..1.0")
        self.sc.gain = float(v)
        self.sc.set_strategy(self.sc.name)
    elif pid == _P_FAULTS:
        if not isinstance(v, str):
            raise ValueError("must be text 'IDX:KIND,...' or 'none'")
        self.bus.set_faults(v)
    else:
        raise ValueError("read-only")
