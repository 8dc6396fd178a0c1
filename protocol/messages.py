"""Message builders and parsers with SI units (host, tests, emulator, device slow path).

``encode_*`` return complete wire frames (bytes, COBS + delimiter); ``*_payload`` return the
int-keyed payload dict; ``decode_*`` take a payload (bytes-like, CBOR) and return a dict with the
names of docs/architecture.md in SI units. Errors raise ``ProtocolError`` subclasses whose
``code`` is the ERROR code to answer with. Runs on MicroPython too (allocates: not for the
control cycle, see ``protocol.device``).
"""

import math
import struct

from protocol import cbor
from protocol.constants import (
    ANGLE_SCALE,
    DESCRIPTOR_KEYS,
    ERROR_NAMES,
    EVENT_NAMES,
    FLAG_BCAST,
    FLAG_LOCAL,
    FLAG_UP,
    INT_LIMIT,
    KAPPA_SCALE,
    SERVO_SCALE,
    SP_HOLD,
    SP_KAPPA_MAX,
    SP_KAPPA_MIN,
    SP_LEN,
    STATE_FIXED,
    STATUS_NAMES,
    T_ALIVE,
    T_CLEAR_FAULT,
    T_DESCRIPTOR,
    T_DISCOVER,
    T_ERROR,
    T_EVENT,
    T_HEARTBEAT,
    T_HOLD,
    T_PARAM_GET,
    T_PARAM_SET,
    T_PARAM_VALUE,
    T_STATE,
    T_SYNC,
    TYPE_NAMES,
    VERSION,
    VERSION_MAX,
    VERSION_MIN,
)
from protocol.errors import (
    BadValueError,
    MalformedError,
    UnknownTypeError,
    UnsupportedVersionError,
)
from protocol.frame import encode_frame

_PI = math.pi
_TWO_PI = 2.0 * math.pi

# Optional fast encoder on the host: cbor2 in canonical mode gives the same bytes as
# protocol.cbor.dumps (tested for every message). None on MicroPython.
try:
    import cbor2 as _cbor2
except ImportError:
    _cbor2 = None

_use_cbor2 = _cbor2 is not None


def use_cbor2(enabled: bool) -> None:
    """Select cbor2 (True, host only) or the project's own codec (False) for payload encoding."""
    global _use_cbor2
    if enabled and _cbor2 is None:
        raise RuntimeError("cbor2 is not installed")
    _use_cbor2 = bool(enabled)


def dumps(obj) -> bytes:
    """Canonical CBOR bytes of ``obj`` (cbor2 or own codec: identical output)."""
    if _use_cbor2:
        return _cbor2.dumps(obj, canonical=True)
    return cbor.dumps(obj)


# --------------------------------------------------------------------------------------------
# value conversion and validation
# --------------------------------------------------------------------------------------------
def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return (isinstance(v, int) or isinstance(v, float)) and not isinstance(v, bool)


def _finite(x, name: str) -> float:
    """``x`` as a finite float; BadValueError for NaN, inf or a non-number."""
    if not _is_num(x):
        raise BadValueError("%s must be a number, got %r" % (name, x))
    x = float(x)
    if not math.isfinite(x):
        raise BadValueError("%s must be finite, got %r" % (name, x))
    return x


def _check_wire_int(v: int, name: str) -> int:
    if not -INT_LIMIT < v < INT_LIMIT:
        raise BadValueError("%s = %d is outside the wire range +-2**30" % (name, v))
    return v


def to_fixed(x, scale: int, name: str = "value") -> int:
    """SI float -> wire int ``round(x * scale)``; BadValueError if not finite or out of range."""
    return _check_wire_int(int(round(_finite(x, name) * scale)), name)


def wrap_angle(phi: float) -> float:
    """Angle in rad wrapped to (-pi, pi]."""
    phi = math.fmod(phi, _TWO_PI)
    if phi <= -_PI:
        phi += _TWO_PI
    elif phi > _PI:
        phi -= _TWO_PI
    return phi


def phi_to_wire(phi: float) -> int:
    """phi in rad -> wire int (1e-4 rad), wrapped to (-pi, pi] first."""
    return to_fixed(wrap_angle(_finite(phi, "phi")), ANGLE_SCALE, "phi")


def _uint(v, name: str, limit: int = INT_LIMIT) -> int:
    if not _is_int(v) or not 0 <= v < limit:
        raise BadValueError("%s must be an int 0..%d, got %r" % (name, limit - 1, v))
    return v


def _seq(seq) -> int:
    return _uint(seq, "seq", 256)


def status_bits(status) -> int:
    """Status as an int from an int or an iterable of names ("HOLD", "WATCHDOG", ...)."""
    if _is_int(status):
        return _uint(status, "status")
    bits = 0
    for name in status:
        for bit, n in STATUS_NAMES:
            if n == name:
                bits |= bit
                break
        else:
            raise BadValueError("unknown status name %r" % (name,))
    return bits


def status_names(bits: int) -> set:
    """Set of status names for the bits set in ``bits`` (unknown bits are named "BIT<n>")."""
    names = set()
    for i in range(30):
        b = 1 << i
        if bits & b:
            for bit, n in STATUS_NAMES:
                if bit == b:
                    names.add(n)
                    break
            else:
                names.add("BIT%d" % i)
    return names


def _param_value(v):
    if isinstance(v, bool) or isinstance(v, str):
        return v
    if _is_int(v):
        return _check_wire_int(v, "value")
    if isinstance(v, float):
        return _finite(v, "value")
    raise BadValueError("parameter value must be int, float, bool or str, got %r" % (v,))


# --------------------------------------------------------------------------------------------
# payload decoding helpers
# --------------------------------------------------------------------------------------------
def decode_map(payload) -> dict:
    """Payload bytes -> int-keyed dict (empty payload -> {}); MalformedError if not a map."""
    if len(payload) == 0:
        return {}
    obj = cbor.loads(payload)
    if not isinstance(obj, dict):
        raise MalformedError("payload is not a CBOR map")
    for k in obj:
        if not _is_int(k):
            raise MalformedError("payload map keys must be ints")
    return obj


def _get(d: dict, key: int, name: str, kind: str, required: bool = True):
    """Field ``key`` of kind "int", "uint", "num", "str", "bool", "intlist", "numlist"."""
    if key not in d:
        if required:
            raise MalformedError("missing key %d (%s)" % (key, name))
        return None
    v = d[key]
    ok = False
    if kind == "int":
        ok = _is_int(v)
    elif kind == "uint":
        ok = _is_int(v) and v >= 0
    elif kind == "num":
        ok = _is_num(v)
    elif kind == "str":
        ok = isinstance(v, str)
    elif kind == "bool":
        ok = isinstance(v, bool)
    elif kind == "intlist":
        ok = isinstance(v, list) and all(_is_int(x) for x in v)
    elif kind == "numlist":
        ok = isinstance(v, list) and all(_is_num(x) for x in v)
    if not ok:
        raise MalformedError("key %d (%s) has the wrong type: %r" % (key, name, v))
    if kind == "int" or kind == "uint":
        _check_wire_int(v, name)
    elif kind == "intlist":
        for x in v:
            _check_wire_int(x, name)
    return v


# --------------------------------------------------------------------------------------------
# host -> segments
# --------------------------------------------------------------------------------------------
def encode_discover(seq: int) -> bytes:
    """DISCOVER broadcast (every segment answers DESCRIPTOR)."""
    return encode_frame(FLAG_BCAST, 0, T_DISCOVER, _seq(seq), {})


_I16_MAX = 0x7FFF


def _s24(b, i: int) -> int:
    """The big-endian int24 at ``b[i:i + 3]``."""
    v = (b[i] << 16) | (b[i + 1] << 8) | b[i + 2]
    return v - 0x1000000 if v & 0x800000 else v


def sync_payload(cycle: int, setpoints_si, resume: bool = False) -> dict:
    """SYNC payload: ``setpoints_si`` is a list of (kappa 1/m, phi rad) or None (hold).

    Key 1 packs SP_LEN bytes per position: kappa int24 (1e-4 1/m, |kappa| <= 838.8607 1/m),
    phi int16 (1e-4 rad, wrapped to (-pi, pi]), big-endian; a hold is ``80 00 00 00 00``.
    """
    packed = bytearray()
    for i, sp in enumerate(setpoints_si):
        if sp is None:
            packed += struct.pack(">i", SP_HOLD)[1:] + b"\x00\x00"
            continue
        if len(sp) != 2:
            raise BadValueError("setpoint %d must be (kappa, phi), got %r" % (i, sp))
        k = to_fixed(sp[0], KAPPA_SCALE, "kappa")
        if not SP_KAPPA_MIN <= k <= SP_KAPPA_MAX:
            raise BadValueError(
                "setpoint %d: kappa %r 1/m is outside the wire range +-%g 1/m"
                % (i, sp[0], SP_KAPPA_MAX / KAPPA_SCALE)
            )
        packed += struct.pack(">i", k)[1:] + struct.pack(">h", phi_to_wire(sp[1]))
    d = {0: _uint(cycle, "cycle"), 1: bytes(packed)}
    if resume:
        d[2] = True
    return d


def encode_sync(seq: int, cycle: int, setpoints_si, resume: bool = False) -> bytes:
    """SYNC broadcast: one (kappa 1/m, phi rad) or None per position; ``resume`` ends a HOLD."""
    return encode_frame(FLAG_BCAST, 0, T_SYNC, _seq(seq), sync_payload(cycle, setpoints_si, resume))


def decode_sync(payload) -> dict:
    """SYNC payload -> ``{cycle, setpoints: [(kappa 1/m, phi rad) | None], resume}``."""
    d = decode_map(payload)
    cycle = _get(d, 0, "cycle", "uint")
    packed = d.get(1)
    if not isinstance(packed, bytes) or len(packed) % SP_LEN:
        raise MalformedError("SYNC key 1 must be a byte string of %d-byte entries" % SP_LEN)
    sps = []
    for i in range(0, len(packed), SP_LEN):
        k = _s24(packed, i)
        p = struct.unpack_from(">h", packed, i + 3)[0]
        if k == SP_HOLD:
            if p:
                raise MalformedError(
                    "SYNC entry %d: a hold entry is 80 00 00 00 00" % (i // SP_LEN)
                )
            sps.append(None)
        else:
            sps.append((k / KAPPA_SCALE, p / ANGLE_SCALE))
    resume = d.get(2, False)
    if not (isinstance(resume, bool) or resume in (0, 1)):
        raise MalformedError("SYNC key 2 (resume) must be a bool")
    return {"cycle": cycle, "setpoints": sps, "resume": bool(resume)}


def encode_heartbeat(seq: int, cycle: int) -> bytes:
    """HEARTBEAT broadcast (feeds watchdogs; every segment answers STATE)."""
    return encode_frame(FLAG_BCAST, 0, T_HEARTBEAT, _seq(seq), {0: _uint(cycle, "cycle")})


def decode_heartbeat(payload) -> dict:
    """HEARTBEAT payload -> ``{cycle}``."""
    return {"cycle": _get(decode_map(payload), 0, "cycle", "uint")}


def param_get_payload(param_id: int, uid=None) -> dict:
    """PARAM_GET payload."""
    d = {0: _uint(param_id, "param_id")}
    if uid is not None:
        if not isinstance(uid, str):
            raise BadValueError("uid must be text")
        d[15] = uid
    return d


def encode_param_get(seq: int, position: int, param_id: int, uid=None) -> bytes:
    """PARAM_GET addressed to chain ``position`` (0 = first segment); ``uid`` checks identity."""
    return encode_frame(
        0,
        _uint(position, "position", 256),
        T_PARAM_GET,
        _seq(seq),
        param_get_payload(param_id, uid),
    )


def decode_param_get(payload) -> dict:
    """PARAM_GET payload -> ``{param_id, uid (None if absent)}``."""
    d = decode_map(payload)
    return {
        "param_id": _get(d, 0, "param_id", "uint"),
        "uid": _get(d, 15, "uid", "str", False),
    }


def param_set_payload(param_id: int, value, uid=None) -> dict:
    """PARAM_SET payload (value: int, finite float in SI, bool or text)."""
    d = param_get_payload(param_id, uid)
    d[1] = _param_value(value)
    return d


def encode_param_set(seq: int, position: int, param_id: int, value, uid=None) -> bytes:
    """PARAM_SET addressed to chain ``position``; answered by PARAM_VALUE with the stored value."""
    return encode_frame(
        0,
        _uint(position, "position", 256),
        T_PARAM_SET,
        _seq(seq),
        param_set_payload(param_id, value, uid),
    )


def _value(d: dict):
    if 1 not in d:
        raise MalformedError("missing key 1 (value)")
    v = d[1]
    try:
        return _param_value(v)
    except BadValueError as e:
        raise MalformedError(str(e)) from None


def decode_param_set(payload) -> dict:
    """PARAM_SET payload -> ``{param_id, value, uid (None if absent)}``."""
    d = decode_map(payload)
    out = decode_param_get(payload)
    out["value"] = _value(d)
    return out


def encode_hold(seq: int, position=None) -> bytes:
    """HOLD to every segment (``position`` None: broadcast) or to one position."""
    if position is None:
        return encode_frame(FLAG_BCAST, 0, T_HOLD, _seq(seq), {})
    return encode_frame(0, _uint(position, "position", 256), T_HOLD, _seq(seq), {})


def encode_alive(seq: int) -> bytes:
    """ALIVE (segment -> upstream neighbour only, LOCAL)."""
    return encode_frame(FLAG_UP | FLAG_LOCAL, 0, T_ALIVE, _seq(seq), {})


def encode_clear_fault(seq: int, position=None, uid=None) -> bytes:
    """CLEAR_FAULT to every segment (``position`` None) or to one; ``uid`` checks identity.

    A segment in FAULT leaves it for HOLD (a SYNC with resume then moves it again)."""
    d = {}
    if uid is not None:
        if not isinstance(uid, str):
            raise BadValueError("uid must be text")
        d[15] = uid
    if position is None:
        return encode_frame(FLAG_BCAST, 0, T_CLEAR_FAULT, _seq(seq), d)
    return encode_frame(0, _uint(position, "position", 256), T_CLEAR_FAULT, _seq(seq), d)


def decode_clear_fault(payload) -> dict:
    """CLEAR_FAULT payload -> ``{uid (None if absent)}``."""
    return {"uid": _get(decode_map(payload), 15, "uid", "str", False)}


def decode_empty(payload) -> dict:
    """Payload of DISCOVER / HOLD / ALIVE: ``{}`` (unknown keys ignored) -> {}."""
    decode_map(payload)
    return {}


# --------------------------------------------------------------------------------------------
# segments -> host
# --------------------------------------------------------------------------------------------
_DESC_KINDS = (
    "str",  # uid
    "str",  # fw_version
    "uint",  # protocol_version
    "str",  # model
    "num",  # length
    "numlist",  # tendon_angles
    "num",  # tendon_radius
    "num",  # spool_radius
    "num",  # kappa_max
    "num",  # kappa_rate_max
    "num",  # mass
    "num",  # backbone_radius
    "str",  # name
    "str",  # servo_driver
    "uint",  # watchdog_ms
    "bool",  # downstream_present
    "str",  # config_error
    "uint",  # config_hash
)
_DESC_REQUIRED = 4  # uid, fw_version, protocol_version, model are mandatory


def descriptor_payload(desc: dict) -> dict:
    """DESCRIPTOR payload from a dict with the contract's names (SI floats).

    uid, fw_version, protocol_version and model are required; other names may be absent (then
    not sent). Unknown names raise BadValueError (typo protection).
    """
    for name in desc:
        if name not in DESCRIPTOR_KEYS and name != "position":
            raise BadValueError("unknown descriptor field %r" % (name,))
    d = {}
    for key in range(len(DESCRIPTOR_KEYS)):
        name = DESCRIPTOR_KEYS[key]
        kind = _DESC_KINDS[key]
        if name not in desc or desc[name] is None:
            if key < _DESC_REQUIRED:
                raise BadValueError("descriptor field %r is required" % (name,))
            continue
        v = desc[name]
        if kind == "str":
            if not isinstance(v, str):
                raise BadValueError("%s must be text" % name)
        elif kind == "uint":
            v = _uint(v, name)
        elif kind == "num":
            v = _finite(v, name)
        elif kind == "numlist":
            v = [_finite(x, name) for x in v]
        elif kind == "bool":
            if not isinstance(v, bool):
                raise BadValueError("%s must be a bool" % name)
        d[key] = v
    return d


def encode_descriptor(desc: dict, seq: int = 0) -> bytes:
    """DESCRIPTOR frame (UP, hop 0) answering DISCOVER ``seq``."""
    return encode_frame(FLAG_UP, 0, T_DESCRIPTOR, _seq(seq), descriptor_payload(desc))


def decode_descriptor(payload) -> dict:
    """DESCRIPTOR payload -> dict with every contract name (absent optional fields are None)."""
    d = decode_map(payload)
    out = {}
    for key in range(len(DESCRIPTOR_KEYS)):
        kind = _DESC_KINDS[key]
        v = _get(d, key, DESCRIPTOR_KEYS[key], kind, key < _DESC_REQUIRED)
        if v is not None:
            if kind == "num":
                v = float(v)
            elif kind == "numlist":
                v = [float(x) for x in v]
        out[DESCRIPTOR_KEYS[key]] = v
    return out


def state_payload(
    *,
    cycle: int,
    t_ms: int,
    kappa: float,
    phi: float,
    servo_angles=(),
    status=0,
    applied_position=0,
) -> dict:
    """STATE payload ``{0: packed report}`` from SI values (kappa 1/m, phi rad, servo angles rad).

    ``applied_position`` is the chain position whose SYNC entry the segment applies. Layout and
    units: docs/protocol.md 0x83 (what the host can derive -- kx, ky, tendon lengths -- is not
    sent).
    """
    kappa = to_fixed(_finite(kappa, "kappa"), KAPPA_SCALE, "kappa")
    if not SP_KAPPA_MIN <= kappa <= SP_KAPPA_MAX:
        raise BadValueError("kappa is outside the STATE range (int24, 1e-4 1/m)")
    angles = [to_fixed(x, SERVO_SCALE, "servo angle") for x in servo_angles]
    for a in angles:
        if not -_I16_MAX <= a <= _I16_MAX:
            raise BadValueError("servo angle is outside the STATE range (int16, 1e-3 rad)")
    if STATE_FIXED + 2 * len(angles) > 255:
        raise BadValueError("too many servo angles for one STATE")
    rep = struct.pack(
        ">II",
        _uint(cycle, "cycle"),
        _uint(t_ms, "t_ms"),
    )
    rep += struct.pack(">i", kappa)[1:]
    rep += struct.pack(
        ">hBB",
        phi_to_wire(phi),
        status_bits(status),
        _uint(applied_position, "position", 256),
    )
    rep += b"".join(struct.pack(">h", a) for a in angles)
    return {0: rep}


def encode_state(seq: int, **fields) -> bytes:
    """STATE frame (UP, hop 0) from SI keyword fields, see ``state_payload``."""
    return encode_frame(FLAG_UP, 0, T_STATE, _seq(seq), state_payload(**fields))


def decode_state(payload, position=None) -> dict:
    """STATE payload -> SI dict ``{position, applied_position, cycle, t_ms, kappa, phi, kx, ky,
    servo_angles, status: set of names, raw_status}``.

    kx, ky are derived here (kappa cos phi, kappa sin phi). ``applied_position`` is the chain
    position whose SYNC entry the segment applies; it differs from ``position`` (the hop count of
    the reply) when a SYNC reached the segment with a wrong hop byte: its setpoint was meant for
    another segment.
    """
    d = decode_map(payload)
    rep = d.get(0)
    if not isinstance(rep, bytes) or len(rep) < STATE_FIXED or (len(rep) - STATE_FIXED) % 2:
        raise MalformedError(
            "STATE key 0 must be a byte string of %d + 2 x servos bytes" % STATE_FIXED
        )
    cycle, t_ms = struct.unpack_from(">II", rep, 0)
    if cycle >= INT_LIMIT or t_ms >= INT_LIMIT:
        raise MalformedError("STATE cycle / t_ms outside 0..2**30-1")
    kappa = _s24(rep, 8) / KAPPA_SCALE
    phi_w, raw_status, applied = struct.unpack_from(">hBB", rep, 11)
    phi = phi_w / ANGLE_SCALE
    n = (len(rep) - STATE_FIXED) // 2
    angles = struct.unpack_from(">%dh" % n, rep, STATE_FIXED)
    return {
        "position": position,
        "applied_position": applied,
        "cycle": cycle,
        "t_ms": t_ms,
        "kappa": kappa,
        "phi": phi,
        "kx": kappa * math.cos(phi),
        "ky": kappa * math.sin(phi),
        "servo_angles": [a / SERVO_SCALE for a in angles],
        "status": status_names(raw_status),
        "raw_status": raw_status,
    }


def tendon_lengths(length, spool_radius, servo_angles) -> list:
    """Tendon lengths (m) a STATE implies: ``length - spool_radius x angle`` per servo (what the
    firmware's mechanism measures, device/mechanism.py); [] without the descriptor's geometry."""
    if not (_is_num(length) and _is_num(spool_radius)):
        return []
    return [length - spool_radius * a for a in servo_angles]


def encode_param_value(seq: int, param_id: int, value) -> bytes:
    """PARAM_VALUE frame (UP, hop 0) answering PARAM_GET/PARAM_SET ``seq``."""
    return encode_frame(
        FLAG_UP,
        0,
        T_PARAM_VALUE,
        _seq(seq),
        {0: _uint(param_id, "param_id"), 1: _param_value(value)},
    )


def decode_param_value(payload) -> dict:
    """PARAM_VALUE payload -> ``{param_id, value}``."""
    d = decode_map(payload)
    return {"param_id": _get(d, 0, "param_id", "uint"), "value": _value(d)}


def encode_event(seq: int, code: int, detail: int, t_ms: int, text=None) -> bytes:
    """EVENT frame (UP, hop 0, unsolicited); ``text`` (optional) goes in key 3."""
    payload = {0: _uint(code, "code"), 1: _check_wire_int(detail, "detail"), 2: _uint(t_ms, "t_ms")}
    if text is not None:
        if not isinstance(text, str):
            raise BadValueError("event text must be str")
        payload[3] = text
    return encode_frame(FLAG_UP, 0, T_EVENT, _seq(seq), payload)


def decode_event(payload) -> dict:
    """EVENT payload -> ``{code, name, detail, t_ms}`` (name "UNKNOWN_<n>" for new codes)."""
    d = decode_map(payload)
    code = _get(d, 0, "code", "uint")
    out = {
        "code": code,
        "name": EVENT_NAMES.get(code, "UNKNOWN_%d" % code),
        "detail": _get(d, 1, "detail", "int"),
        "t_ms": _get(d, 2, "t_ms", "uint"),
    }
    text = _get(d, 3, "text", "str", False)
    if text is not None:
        out["text"] = text
    return out


def error_payload(code: int, offending_type: int, text: str = "", versions=None) -> dict:
    """ERROR payload; ``versions`` = (min, max) supported, sent as key 3 (UNSUPPORTED_VERSION)."""
    if not isinstance(text, str):
        raise BadValueError("error text must be str")
    d = {0: _uint(code, "code"), 1: _uint(offending_type, "offending type", 256), 2: text}
    if versions is not None:
        d[3] = [_uint(versions[0], "version", 256), _uint(versions[1], "version", 256)]
    return d


def encode_error(seq: int, code: int, offending_type: int, text: str = "", versions=None) -> bytes:
    """ERROR frame (UP, hop 0) answering the request ``seq`` of type ``offending_type``."""
    return encode_frame(
        FLAG_UP, 0, T_ERROR, _seq(seq), error_payload(code, offending_type, text, versions)
    )


def encode_version_error(seq: int, offending_type: int) -> bytes:
    """ERROR UNSUPPORTED_VERSION naming this implementation's range (text and key 3)."""
    text = "supported protocol versions %d..%d" % (VERSION_MIN, VERSION_MAX)
    return encode_error(seq, 3, offending_type, text, (VERSION_MIN, VERSION_MAX))


def decode_error(payload) -> dict:
    """ERROR payload -> ``{code, name, offending_type, text, versions ((min, max) or None)}``."""
    d = decode_map(payload)
    code = _get(d, 0, "code", "uint")
    versions = d.get(3)
    if versions is not None:
        if not (isinstance(versions, list) and len(versions) == 2 and all(map(_is_int, versions))):
            raise MalformedError("ERROR key 3 must be [min, max]")
        versions = (versions[0], versions[1])
    return {
        "code": code,
        "name": ERROR_NAMES.get(code, "UNKNOWN_%d" % code),
        "offending_type": _get(d, 1, "offending type", "uint"),
        "text": _get(d, 2, "text", "str", False) or "",
        "versions": versions,
    }


# --------------------------------------------------------------------------------------------
# dispatch
# --------------------------------------------------------------------------------------------
def decode_calibrate(payload) -> dict:
    """CALIBRATE payload -> ``{action, zero_offsets, directions, uid}`` (see calibration.py)."""
    from protocol import calibration

    try:
        action, zeros, dirs, uid = calibration.decode_calibrate(decode_map(payload))
    except MalformedError:
        raise
    except ValueError as e:
        raise MalformedError(str(e)) from None
    return {"action": action, "zero_offsets": zeros, "directions": dirs, "uid": uid}


def decode_calibration(payload) -> dict:
    """CALIBRATION payload -> ``{version, zero_offsets, directions, stored, config_hash}``."""
    from protocol import calibration

    try:
        return calibration.decode_calibration(decode_map(payload))
    except MalformedError:
        raise
    except ValueError as e:
        raise MalformedError(str(e)) from None


_DECODERS = {
    T_DISCOVER: decode_empty,
    T_SYNC: decode_sync,
    T_HEARTBEAT: decode_heartbeat,
    T_PARAM_GET: decode_param_get,
    T_PARAM_SET: decode_param_set,
    T_HOLD: decode_empty,
    T_ALIVE: decode_empty,
    T_CLEAR_FAULT: decode_clear_fault,
    T_DESCRIPTOR: decode_descriptor,
    T_STATE: decode_state,
    T_PARAM_VALUE: decode_param_value,
    T_EVENT: decode_event,
    T_ERROR: decode_error,
    0x09: decode_calibrate,  # T_CALIBRATE
    0x89: decode_calibration,  # T_CALIBRATION
}


def decode_message(frame) -> dict:
    """Decode a ``Frame`` into ``{"type": name, "mtype", "seq", "hop", "flags", "ver", **fields}``.

    Raises UnknownTypeError, MalformedError/BadValueError (bad payload) or
    UnsupportedVersionError; all are ProtocolError carrying the ERROR ``code`` to answer.
    """
    if frame.ver != VERSION:
        raise UnsupportedVersionError("unsupported protocol version %d" % frame.ver)
    dec = _DECODERS.get(frame.mtype)
    if dec is None:
        raise UnknownTypeError("unknown message type 0x%02x" % frame.mtype)
    out = dec(frame.payload)
    if frame.flags & FLAG_UP:
        out["position"] = frame.hop  # upstream hop counts forwarders: the source position
    out["type"] = TYPE_NAMES[frame.mtype]
    out["mtype"] = frame.mtype
    out["seq"] = frame.seq
    out["hop"] = frame.hop
    out["flags"] = frame.flags
    out["ver"] = frame.ver
    return out
