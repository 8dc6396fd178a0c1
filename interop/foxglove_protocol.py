"""The Foxglove WebSocket protocol, server side and read-only: the messages ``ucr foxglove`` sends
and how it reads a client's (https://github.com/foxglove/ws-protocol/blob/main/docs/spec.md;
foxglove-sdk's server speaks the same under the subprotocol name ``foxglove.sdk.v1``).

Pure functions, no I/O; :mod:`interop.guard` serves them. The server advertises no capability,
so a client may only ``subscribe`` and ``unsubscribe``: :func:`parse_client` turns any client
message (any text or bytes) into a :class:`Subscribe`, an :class:`Unsubscribe` or an
:class:`Invalid` (the ``status`` message to answer with) and never raises.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the same protocol, two names
MESSAGE_DATA = 0x01  # server binary opcode: u32 subscription id, u64 log time (ns), payload
U32_MAX = 2**32 - 1  # subscription and channel ids are u32
U64_MAX = 2**64 - 1
INFO, WARNING, ERROR = 0, 1, 2  # status levels

_HEADER = struct.Struct("<BIQ")
# client ops a server without capabilities does not serve -> the capability they need
_UNSUPPORTED = {
    "advertise": "clientPublish",
    "unadvertise": "clientPublish",
    "getParameters": "parameters",
    "setParameters": "parameters",
    "subscribeParameterUpdates": "parametersSubscribe",
    "unsubscribeParameterUpdates": "parametersSubscribe",
    "subscribeConnectionGraph": "connectionGraph",
    "unsubscribeConnectionGraph": "connectionGraph",
    "fetchAsset": "assets",
}
_UNSUPPORTED_BINARY = {1: "clientPublish", 2: "services", 3: "playbackControl"}


@dataclass(frozen=True)
class ChannelInfo:
    """One advertised channel (a topic)."""

    id: int
    topic: str
    encoding: str
    schema_name: str
    schema_encoding: str
    schema: str  # text: every schema encoding ucr sends (ros2msg) is text

    def as_json(self) -> dict:
        return {"id": self.id, "topic": self.topic, "encoding": self.encoding,
                "schemaName": self.schema_name, "schemaEncoding": self.schema_encoding,
                "schema": self.schema}  # fmt: skip


@dataclass(frozen=True)
class Subscribe:
    """A client's ``subscribe``: (subscription id, channel id) pairs, each a u32."""

    subscriptions: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class Unsubscribe:
    """A client's ``unsubscribe``: subscription ids, each a u32."""

    ids: tuple[int, ...]


@dataclass(frozen=True)
class Invalid:
    """A client message the server does not act on; answer with :func:`status`."""

    level: int
    message: str


def _dumps(obj: object) -> str:
    return json.dumps(obj, separators=(",", ":"), ensure_ascii=False)


def server_info(name: str, session_id: str, encodings: list[str]) -> str:
    """The first message on every connection: no capabilities (read-only)."""
    return _dumps({"op": "serverInfo", "name": name, "capabilities": [],
                   "supportedEncodings": encodings, "metadata": {},
                   "sessionId": session_id})  # fmt: skip


def advertise(channels: list[ChannelInfo]) -> str:
    return _dumps({"op": "advertise", "channels": [c.as_json() for c in channels]})


def status(level: int, message: str) -> str:
    return _dumps({"op": "status", "level": level, "message": message})


def message_data(sub_id: int, t_ns: int, data: bytes) -> bytes:
    """A message data frame; ``sub_id`` a u32 and ``t_ns`` a u64 (checked where they enter)."""
    return _HEADER.pack(MESSAGE_DATA, sub_id, t_ns) + data


def _shown(value: object) -> str:
    """A client's value in a status message: short (never the client's whole frame back)."""
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _u32(value: object) -> bool:
    return type(value) is int and 0 <= value <= U32_MAX  # not bool, not float


def parse_client(msg: str | bytes) -> Subscribe | Unsubscribe | Invalid:
    """A client message -> what to do, or the status to answer it with. Never raises."""
    if isinstance(msg, (bytes, bytearray, memoryview)):
        opcode = msg[0] if len(msg) else None
        need = _UNSUPPORTED_BINARY.get(opcode)  # type: ignore[arg-type]
        if need is not None:
            return Invalid(ERROR, f"Server does not support {need} capability")
        return Invalid(ERROR, f"Invalid message: unknown binary opcode {_shown(opcode)}")
    if not isinstance(msg, str):
        return Invalid(ERROR, "Invalid message: neither text nor binary")
    try:
        obj = json.loads(msg)
    except (ValueError, RecursionError):  # bad JSON, a huge integer, nesting too deep
        return Invalid(ERROR, "Invalid message: not JSON")
    if not isinstance(obj, dict):
        return Invalid(ERROR, "Invalid message: not a JSON object")
    op = obj.get("op")
    if op == "subscribe":
        return _subscribe(obj.get("subscriptions"))
    if op == "unsubscribe":
        ids = obj.get("subscriptionIds")
        if not isinstance(ids, list) or not all(_u32(i) for i in ids):
            return Invalid(ERROR, "Invalid message: unsubscribe needs subscriptionIds, a list "
                                  "of u32")  # fmt: skip
        return Unsubscribe(tuple(ids))
    if isinstance(op, str) and op in _UNSUPPORTED:
        return Invalid(ERROR, f"Server does not support {_UNSUPPORTED[op]} capability")
    return Invalid(ERROR, f"Invalid message: unknown op {_shown(op)}")


def _subscribe(subs: object) -> Subscribe | Invalid:
    if not isinstance(subs, list):
        return Invalid(ERROR, "Invalid message: subscribe needs subscriptions, a list")
    out = []
    for s in subs:
        if not isinstance(s, dict):
            return Invalid(ERROR, "Invalid message: a subscription is not an object")
        sid, cid = s.get("id"), s.get("channelId")
        if not _u32(sid) or not _u32(cid):
            return Invalid(ERROR, f"Invalid message: subscription id {_shown(sid)}, channelId "
                                  f"{_shown(cid)}: each must be a u32")  # fmt: skip
        out.append((sid, cid))
    return Subscribe(tuple(out))
