"""Message schemas of the API: request validation, reply/push builders, JSON encoding.

Every request is a JSON object ``{"id": n, "op": "...", ...params}`` (optionally with
``"on_behalf_of"``, for the audit line). :func:`parse_request` turns the raw text into
``(id, op, params, on_behalf_of)`` or raises :class:`RequestError` carrying the error code and
the request id (when one could be read), so the server can always answer. Validation is strict:
unknown ops, unknown fields, wrong types and out-of-range numbers are errors, never ignored.
Units on the wire are SI (s, 1/m, rad); degrees appear only in the CLI.

One piece: the error codes, the shared field validators and every op's parameter table are
together the API's wire contract, and each op's table uses the validators defined beside it.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Callable
from typing import Any

from ucrdf.units import phi_beyond_a_turn

MAX_REQUEST_BYTES = 64 * 1024
MAX_NAME_LEN = 64
MAX_POINTS = 10_000
MAX_TIME_S = 604_800.0  # a waypoint's time_from_start: at most a week (1e15 s broke retiming)
MAX_SEGMENTS = 64
#: shortest time between waypoints (s), and from the start to the first: shorter pieces are
#: numerically unsound (the cJTC refuses them too: host/controllers/waypoints.py)
MIN_POINT_GAP_S = 1e-3
#: float rounding of times written with a few decimals: 1 ms written as 1.000 -> 1.001 counts
TIME_EPS_S = 1e-9
MAX_RATE_HZ = 1000.0
MIN_RATE_HZ = 0.1  # a subscription's max_rate: at least one message per 10 s (1e-300 never sent)
MAX_UPLOADS = 4  # chunked uploads in progress on one connection
MAX_DEFLECTION = 1.0
MAX_INT_MAGNITUDE = 2**53  # JSON integers beyond this are refused (exact in a float up to here)

# Error codes (the "code" of an error reply).
BAD_JSON = "bad_json"  # not valid JSON text (or NaN/Infinity literals)
TOO_LARGE = "too_large"  # request text above MAX_REQUEST_BYTES
BAD_REQUEST = "bad_request"  # not an object, missing/invalid id or op, binary frame
UNKNOWN_OP = "unknown_op"
INVALID_PARAMS = "invalid_params"  # unknown field, wrong type, out of range
NOT_FOUND = "not_found"  # unknown goal, subscription, controller or segment
REJECTED = "rejected"  # the daemon refused (e.g. controller conflict, not active, limits)
UNAVAILABLE = "unavailable"  # the daemon cannot act now (chain lost, rebuilding, stopping)
INTERNAL = "internal"  # unexpected failure inside the daemon (logged on the server)
FORBIDDEN = "forbidden"  # the connection's token lacks the scope this op needs
RATE_LIMITED = "rate_limited"  # the token's share of the server's request budget is used up
ERROR_CODES = (
    BAD_JSON,
    TOO_LARGE,
    BAD_REQUEST,
    UNKNOWN_OP,
    INVALID_PARAMS,
    NOT_FOUND,
    REJECTED,
    UNAVAILABLE,
    INTERNAL,
    FORBIDDEN,
    RATE_LIMITED,
)

# Subscription kinds on the API; the daemon publishes "event" for what the API calls "events".
KINDS = ("joint_states", "transforms", "events", "topology")
KIND_ALIASES = {"event": "events"}
# Kinds whose messages are a periodic stream that max_rate may thin out.
RATE_LIMITED_KINDS = ("joint_states", "transforms")


class RequestError(Exception):
    """A request that cannot be served; becomes an error reply with ``code`` and ``message``."""

    def __init__(self, code: str, message: str, request_id: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.request_id = request_id
        self.upload: int | None = None  # the upload a refused chunk belonged to (it ends)


# --------------------------------------------------------------------------- field checkers
def _bad(field: str, what: str) -> RequestError:
    return RequestError(INVALID_PARAMS, f"{field}: {what}")


def _number(
    value: Any,
    field: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
) -> float:
    """A finite JSON number (bool excluded) within [lo, hi] (lo exclusive if ``lo_open``)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _bad(field, f"expected a number, got {_type_name(value)}")
    if isinstance(value, int) and not -MAX_INT_MAGNITUDE <= value <= MAX_INT_MAGNITUDE:
        raise _bad(field, "number out of range")  # e.g. 10**400: no float holds it
    v = float(value)
    if not math.isfinite(v):
        raise _bad(field, "must be finite")
    if lo is not None and (v <= lo if lo_open else v < lo):
        raise _bad(field, f"must be {'>' if lo_open else '>='} {lo:g}, got {v:g}")
    if hi is not None and v > hi:
        raise _bad(field, f"must be <= {hi:g}, got {v:g}")
    return v


def _name(value: Any, field: str) -> str:
    if not isinstance(value, str):
        raise _bad(field, f"expected a string, got {_type_name(value)}")
    if not value or len(value) > MAX_NAME_LEN:
        raise _bad(field, f"must be 1..{MAX_NAME_LEN} characters")
    return value


def _names(value: Any, field: str) -> list[str]:
    if not isinstance(value, list):
        raise _bad(field, f"expected a list of names, got {_type_name(value)}")
    if len(value) > MAX_SEGMENTS:
        raise _bad(field, f"at most {MAX_SEGMENTS} names")
    return [_name(v, f"{field}[{i}]") for i, v in enumerate(value)]


def _goal_id(value: Any, field: str = "goal") -> str | int:
    if isinstance(value, bool) or not isinstance(value, str | int):
        raise _bad(field, f"expected a goal id (string or integer), got {_type_name(value)}")
    if isinstance(value, str) and not 0 < len(value) <= MAX_NAME_LEN:
        raise _bad(field, f"must be 1..{MAX_NAME_LEN} characters")
    if isinstance(value, int) and not 0 <= value < 2**53:
        raise _bad(field, "integer goal ids are 0 .. 2**53 - 1")
    return value


def _type_name(value: Any) -> str:
    return {
        dict: "object",
        list: "array",
        str: "string",
        bool: "boolean",
        type(None): "null",
        int: "integer",
        float: "number",
    }.get(type(value), type(value).__name__)


def _check_fields(params: dict, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> None:
    unknown = sorted(set(params) - set(allowed))
    if unknown:
        hint = f" (allowed: {', '.join(allowed)})" if allowed else " (this op takes none)"
        raise RequestError(INVALID_PARAMS, f"unknown field(s) {', '.join(unknown)}{hint}")
    for key in required:
        if key not in params:
            raise RequestError(INVALID_PARAMS, f"missing field {key!r}")


# --------------------------------------------------------------------------- per-op validators
def _no_params(params: dict) -> dict:
    _check_fields(params, ())
    return {}


def _switch(params: dict) -> dict:
    _check_fields(params, ("start", "stop"))
    start = _names(params.get("start", []), "start")
    stop = _names(params.get("stop", []), "stop")
    if not start and not stop:
        raise RequestError(INVALID_PARAMS, "give at least one controller in 'start' or 'stop'")
    return {"start": start, "stop": stop}


def validate_points(
    points: Any, field: str = "points", *, start: int = 0, last_t: float = 0.0
) -> list[dict]:
    """Waypoints ``[{"time_from_start": s, "segments": {name: {"kappa": 1/m, "phi": rad}}}, ...]``.

    ``time_from_start`` (alias ``t``) is seconds from the start of the motion, > 0 and strictly
    increasing. Per segment either ``kappa`` (>= 0, 1/m) with ``phi`` (rad, default 0) or the
    curvature vector ``kx``, ``ky`` (1/m). Segments left out of a waypoint keep their previous
    target. Returns the points in canonical form; raises :class:`RequestError` naming the field.
    Limits (kappa_max, phi range) are checked by the daemon, which knows the robot.

    A chunk of an upload passes ``start`` (waypoints before it) and ``last_t`` (the time of the
    last one): errors then name the waypoint's index in the whole trajectory.
    """
    if not isinstance(points, list):
        raise _bad(field, f"expected a list of waypoints, got {_type_name(points)}")
    if not points:
        raise _bad(field, "needs at least one waypoint")
    if len(points) > MAX_POINTS:
        raise _bad(field, f"at most {MAX_POINTS} waypoints")
    out: list[dict] = []
    for i, p in enumerate(points, start):
        where = f"{field}[{i}]"
        if not isinstance(p, dict):
            raise _bad(where, f"expected an object, got {_type_name(p)}")
        unknown = sorted(set(p) - {"time_from_start", "t", "segments"})
        if unknown:
            raise _bad(
                where, f"unknown field(s) {', '.join(unknown)} (allowed: time_from_start, segments)"
            )
        if "time_from_start" in p and "t" in p:
            raise _bad(where, "give 'time_from_start' or its alias 't', not both")
        t_raw = p.get("time_from_start", p.get("t"))
        if t_raw is None or "segments" not in p:
            raise _bad(where, "needs 'time_from_start' (s) and 'segments'")
        t = _number(t_raw, f"{where}.time_from_start", lo=0.0, lo_open=True, hi=MAX_TIME_S)
        if t <= last_t:
            raise _bad(
                f"{where}.time_from_start",
                f"times must increase strictly ({t:g} s after {last_t:g} s)",
            )
        if t - last_t < MIN_POINT_GAP_S - TIME_EPS_S:  # (1.001 - 1.0 is 0.99999... ms)
            after = "the start" if last_t == 0.0 else f"the point before ({last_t:g} s)"
            raise _bad(
                f"{where}.time_from_start",
                f"{t:g} s is {(t - last_t) * 1e3:.3g} ms after {after}; at least "
                f"{MIN_POINT_GAP_S * 1e3:g} ms between points",
            )
        last_t = t
        segs = p["segments"]
        if not isinstance(segs, dict) or not segs:
            raise _bad(f"{where}.segments", "expected a non-empty object {name: {kappa, phi}}")
        if len(segs) > MAX_SEGMENTS:
            raise _bad(f"{where}.segments", f"at most {MAX_SEGMENTS} segments")
        seg_out: dict[str, dict[str, float]] = {}
        for name, target in segs.items():
            swhere = f"{where}.segments.{_name(name, f'{where}.segments key')}"
            if not isinstance(target, dict):
                raise _bad(swhere, f"expected {{kappa, phi}}, got {_type_name(target)}")
            keys = set(target)
            unknown = sorted(keys - {"kappa", "phi", "kx", "ky"}, key=str)
            if unknown:
                raise _bad(
                    swhere,
                    f"unknown field(s) {', '.join(map(str, unknown))} (allowed: 'kappa' (1/m) "
                    "and 'phi' (rad), or 'kx' and 'ky' (1/m); a `ucr trajectory` file also "
                    "takes 'phi_deg')",
                )
            if keys & {"kx", "ky"}:
                if keys != {"kx", "ky"}:  # never a silent 0 for a component left out
                    raise _bad(
                        swhere, "give both 'kx' and 'ky' (1/m), or 'kappa' and 'phi' instead"
                    )
                seg_out[name] = {
                    "kx": _number(target["kx"], f"{swhere}.kx"),
                    "ky": _number(target["ky"], f"{swhere}.ky"),
                }
                continue
            if "kappa" not in keys:
                raise _bad(swhere, "give 'kappa' (1/m) and 'phi' (rad), or 'kx' and 'ky' (1/m)")
            kappa = _number(target["kappa"], f"{swhere}.kappa", lo=0.0)
            phi = _number(target.get("phi", 0.0), f"{swhere}.phi")
            why = phi_beyond_a_turn(phi)  # more than a turn: degrees in a radian field
            if why is not None:
                raise _bad(f"{swhere}.phi", why)
            seg_out[name] = {"kappa": kappa, "phi": phi}
        out.append({"time_from_start": t, "segments": seg_out})
    return out


def _upload_id(value: Any) -> int | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or not 0 < value < 2**53:
        raise _bad("upload", "expected an upload id (positive integer)")
    return value


#: ``uploaded(upload id)``: ``(waypoints, time of the last one)`` the connection's upload holds
#: (None if it has no such upload), so a chunk's errors name indices of the whole trajectory.
Uploaded = Callable[[int], tuple[int, float] | None]


def _chunk_points(points: Any, upload: int | None, uploaded: Uploaded | None) -> list[dict]:
    """A chunk's waypoints, numbered after what its upload holds; a refused chunk names its
    upload in the error (the server then ends that upload)."""
    held = uploaded(upload) if upload is not None and uploaded is not None else None
    start, last_t = held if held is not None else (0, 0.0)
    try:
        return validate_points(points, start=start, last_t=last_t)
    except RequestError as exc:
        exc.upload = upload
        raise


def _trajectory_send(params: dict, uploaded: Uploaded | None = None) -> dict:
    """Waypoints in ``points``, or appended to a chunked upload named by ``upload``."""
    _check_fields(params, ("points", "controller", "upload"))
    upload = _upload_id(params.get("upload"))
    if upload is None and "points" not in params:
        raise RequestError(INVALID_PARAMS, "missing field 'points'")
    out: dict[str, Any] = {
        "points": _chunk_points(params["points"], upload, uploaded) if "points" in params else [],
        "upload": upload,
    }
    if params.get("controller") is not None:
        out["controller"] = _name(params["controller"], "controller")
    else:
        out["controller"] = None
    return out


def _trajectory_upload(params: dict, uploaded: Uploaded | None = None) -> dict:
    """One chunk of a long trajectory: ``points`` (validated now) and, after the first chunk,
    the ``upload`` id the server returned."""
    _check_fields(params, ("points", "upload"), ("points",))
    upload = _upload_id(params.get("upload"))
    return {"points": _chunk_points(params["points"], upload, uploaded), "upload": upload}


def _upload_cancel(params: dict) -> dict:
    """End an unfinished upload of this connection (its waypoints are forgotten)."""
    _check_fields(params, ("upload",), ("upload",))
    upload = _upload_id(params["upload"])
    if upload is None:
        raise _bad("upload", "expected an upload id (positive integer)")
    return {"upload": upload}


def _hand_back(params: dict) -> dict:
    _check_fields(params, ("manual",))
    manual = params.get("manual")
    return {"manual": None if manual is None else _name(manual, "manual")}


def _clear_fault(params: dict) -> dict:
    _check_fields(params, ("segment",))
    segment = params.get("segment")
    return {"segment": None if segment is None else _name(segment, "segment")}


def _goal_op(params: dict) -> dict:
    _check_fields(params, ("goal",), ("goal",))
    return {"goal": _goal_id(params["goal"])}


def validate_rates(rates: Any, field: str = "rates") -> dict[str, tuple[float, float]]:
    """cFFC input ``{name: [dkx, dky]}``: stick deflections in [-1, 1] per bendable.

    The daemon's cFFC scales a deflection by the segment's ``kappa_rate_max`` (1/m/s) from the
    U(C)RDF, so 1.0 means "as fast as the segment may bend" (paper Fig. 5).
    """
    if not isinstance(rates, dict):
        raise _bad(field, f"expected an object {{name: [dkx, dky]}}, got {_type_name(rates)}")
    if not rates:
        raise _bad(field, "needs at least one segment")
    if len(rates) > MAX_SEGMENTS:
        raise _bad(field, f"at most {MAX_SEGMENTS} segments")
    out: dict[str, tuple[float, float]] = {}
    for name, value in rates.items():
        where = f"{field}.{_name(name, f'{field} key')}"
        if not isinstance(value, list) or len(value) != 2:
            raise _bad(where, "expected [dkx, dky] (two numbers in [-1, 1])")
        x = _number(value[0], f"{where}[0]", lo=-MAX_DEFLECTION, hi=MAX_DEFLECTION)
        y = _number(value[1], f"{where}[1]", lo=-MAX_DEFLECTION, hi=MAX_DEFLECTION)
        out[name] = (x, y)
    return out


def _ffc_input(params: dict) -> dict:
    _check_fields(params, ("rates",), ("rates",))
    return {"rates": validate_rates(params["rates"])}


def normalize_kind(kind: str) -> str:
    return KIND_ALIASES.get(kind, kind)


def _subscribe(params: dict) -> dict:
    _check_fields(params, ("kinds", "max_rate"), ("kinds",))
    kinds = params["kinds"]
    if not isinstance(kinds, list) or not kinds:
        raise _bad("kinds", f"expected a non-empty list of {', '.join(KINDS)}")
    out: list[str] = []
    for i, k in enumerate(kinds):
        if not isinstance(k, str) or normalize_kind(k) not in KINDS:
            raise _bad(f"kinds[{i}]", f"unknown kind {k!r} (known: {', '.join(KINDS)})")
        if normalize_kind(k) not in out:
            out.append(normalize_kind(k))
    rate = params.get("max_rate")
    if rate is not None:
        rate = _number(rate, "max_rate", lo=MIN_RATE_HZ, hi=MAX_RATE_HZ)
    return {"kinds": out, "max_rate": rate}


def _unsubscribe(params: dict) -> dict:
    _check_fields(params, ("sub",), ("sub",))
    sub = params["sub"]
    if isinstance(sub, bool) or not isinstance(sub, int) or sub < 0:
        raise _bad("sub", "expected a subscription id (non-negative integer)")
    return {"sub": sub}


#: ``robot.description``'s text above this many bytes is left out (its sha256 and size stay).
DESCRIPTION_TEXT_MAX = 256 * 1024
_described: list[Any] = [None, None]  # the robot described last and its description


def robot_description(robot: Any, text: bool = True) -> dict[str, Any]:
    """A robot (:class:`ucrdf.model.Robot`) as the API describes it: its name and file, its
    canonical U(C)RDF text (``ucrdf.writer.dumps``: comments, spacing and number spelling
    normalised; parsed back it is an equal robot), the text's sha256 and size in bytes (UTF-8);
    ``text`` None above :data:`DESCRIPTION_TEXT_MAX`. ``text=False``: only the sha256 and size
    (what ``topology`` carries). Written once per robot object (the daemon's changes only with
    ``--adopt``)."""
    robot_then, desc = _described
    if robot_then is not robot:
        from ucrdf.writer import dumps  # noqa: PLC0415 - lxml only where a robot is described

        data = dumps(robot).encode("utf-8")
        desc = {
            "robot": robot.name,
            "file": robot.source or None,
            "sha256": hashlib.sha256(data).hexdigest(),
            "bytes": len(data),
            "text": data.decode("utf-8") if len(data) <= DESCRIPTION_TEXT_MAX else None,
        }
        _described[:] = [robot, desc]
    if not text:
        return {"sha256": desc["sha256"], "bytes": desc["bytes"]}
    return dict(desc)


OPS: dict[str, Callable[[dict], dict]] = {
    "ping": _no_params,
    "session": _no_params,
    "status": _no_params,
    "topology": _no_params,
    "robot.description": _no_params,
    "loop_stats": _no_params,
    "controllers.list": _no_params,
    "controllers.switch": _switch,
    "controllers.hand_back": _hand_back,
    "faults.clear": _clear_fault,
    "trajectory.send": _trajectory_send,
    "trajectory.upload": _trajectory_upload,
    "trajectory.upload_cancel": _upload_cancel,
    "trajectory.status": _goal_op,
    "trajectory.cancel": _goal_op,
    "ffc.input": _ffc_input,
    "subscribe": _subscribe,
    "unsubscribe": _unsubscribe,
}


_CHUNK_OPS = {"trajectory.send": _trajectory_send, "trajectory.upload": _trajectory_upload}


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


_LEADING_ID = re.compile(r'\s*\{\s*"id"\s*:\s*(?:(\d{1,15})|"([^"\\]{1,64})")\s*,')


def _leading_id(data: str) -> Any:
    """The id of a request too large to parse, if it is the first member (so the client can
    match the error reply); None otherwise."""
    m = _LEADING_ID.match(data[:100])
    if m is None:
        return None
    return int(m.group(1)) if m.group(1) is not None else m.group(2)


def unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object whose keys are unique: a repeated key (e.g. two "op") is an error, never
    "the last one wins" (RFC 8259 leaves it to the reader; we refuse to guess)."""
    obj = dict(pairs)
    if len(obj) != len(pairs):
        seen: set[str] = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"duplicate key {key!r} in an object")
            seen.add(key)
    return obj


#: The longest ``on_behalf_of`` label a request may carry (characters).
MAX_ON_BEHALF_LEN = 80


def _on_behalf_of(value: Any, rid: Any) -> str | None:
    """A request's optional ``on_behalf_of``: who a client acting for others (``ucr view`` for its
    pages) says this request is for; written into the audit line as declared, not proven."""
    if value is None:
        return None
    if not isinstance(value, str) or not 0 < len(value) <= MAX_ON_BEHALF_LEN:
        raise RequestError(
            BAD_REQUEST,
            f"'on_behalf_of' must be a string of 1 to {MAX_ON_BEHALF_LEN} characters",
            rid,
        )
    if not value.isprintable():
        raise RequestError(BAD_REQUEST, "'on_behalf_of' must be printable (no control)", rid)
    return value


def parse_request(
    data: str | bytes, max_bytes: int = MAX_REQUEST_BYTES, uploaded: Uploaded | None = None
) -> tuple[Any, str, dict, str | None]:
    """Decode and validate one request frame; returns ``(id, op, params, on_behalf_of)``.

    Raises :class:`RequestError`; its ``request_id`` is set whenever the id could be read, so the
    error reply can be matched by the client. ``uploaded``: the connection's uploads (see
    :data:`Uploaded`), so a later chunk's errors count from the start of the trajectory.
    ``on_behalf_of`` (optional, any op): see :func:`_on_behalf_of`.
    """
    if isinstance(data, bytes | bytearray | memoryview):
        raise RequestError(BAD_REQUEST, "binary frames are not accepted: send JSON text")
    if len(data) > max_bytes:  # characters >= bytes/4, so check the cheap bound first
        raise RequestError(
            TOO_LARGE,
            f"request of {len(data)} chars exceeds {max_bytes} bytes (long trajectories: "
            "trajectory.upload in chunks)",
            _leading_id(data),
        )
    if len(data.encode("utf-8", "surrogatepass")) > max_bytes:
        raise RequestError(TOO_LARGE, f"request exceeds {max_bytes} bytes", _leading_id(data))
    try:
        obj = json.loads(data, parse_constant=_reject_constant, object_pairs_hook=unique_keys)
    except (ValueError, RecursionError) as exc:
        raise RequestError(BAD_JSON, f"invalid JSON: {exc}") from None
    if not isinstance(obj, dict):
        raise RequestError(BAD_REQUEST, f"a request is a JSON object, got {_type_name(obj)}")
    rid = obj.get("id")
    if isinstance(rid, bool) or not (
        isinstance(rid, int) and 0 <= rid < 2**53 or isinstance(rid, str) and 0 < len(rid) <= 64
    ):
        raise RequestError(BAD_REQUEST, "'id' must be a non-negative integer or a short string")
    op = obj.get("op")
    if not isinstance(op, str):
        raise RequestError(BAD_REQUEST, "'op' must be a string", rid)
    if op not in OPS:
        raise RequestError(UNKNOWN_OP, f"unknown op {op[:64]!r} (known: {', '.join(OPS)})", rid)
    behalf = _on_behalf_of(obj.get("on_behalf_of"), rid)
    params = {k: v for k, v in obj.items() if k not in ("id", "op", "on_behalf_of")}
    try:
        if op in _CHUNK_OPS:
            return rid, op, _CHUNK_OPS[op](params, uploaded), behalf
        return rid, op, OPS[op](params), behalf
    except RequestError as exc:
        exc.request_id = rid
        raise


# --------------------------------------------------------------------------- encoding
def _default(obj: Any) -> Any:
    """JSON fallback for what the daemon may publish: numpy scalars/arrays, sets, tuples."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    if isinstance(obj, set | frozenset):
        return sorted(obj, key=str)
    if hasattr(obj, "item"):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _finite(obj: Any) -> Any:
    """Replace NaN/inf by None, recursively (JSON has no such numbers)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite(v) for v in obj]
    if isinstance(obj, set | frozenset):
        return [_finite(v) for v in sorted(obj, key=str)]
    if hasattr(obj, "tolist"):
        return _finite(obj.tolist())
    return obj


def encode(obj: Any) -> str:
    """Strict JSON text (no NaN literals: non-finite numbers become null)."""
    try:
        return json.dumps(obj, allow_nan=False, default=_default, separators=(",", ":"))
    except ValueError:
        return json.dumps(_finite(obj), allow_nan=False, default=_default, separators=(",", ":"))


def ok_reply(rid: Any, result: Any) -> dict:
    return {"id": rid, "ok": True, "result": result}


def error_reply(rid: Any, code: str, message: str) -> dict:
    return {"id": rid, "ok": False, "error": {"code": code, "message": message}}
