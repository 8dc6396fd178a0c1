"""ROS 2 message definitions and their CDR encoding: the one place every ROS 2 consumer of ucr
uses (MCAP recording, the live Foxglove server, later ROS 2 over Zenoh).

``msg/<package>/<Type>.msg`` hold the published ROS 2 (Jazzy) interface definitions (field and
constant lines as published; comments left out). :func:`definition` concatenates a type with its
dependencies in the rosbag2 / MCAP ``ros2msg`` layout (``====`` separators, ``MSG: pkg/Type``).
:class:`Codec` encodes and decodes CDR with mcap-ros2-support (no hand-written CDR here).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from functools import cache
from pathlib import Path
from typing import Any

MSG_DIR = Path(__file__).resolve().parent / "msg"
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
_SEPARATOR = "=" * 80

PRIMITIVES = frozenset(
    "bool byte char float32 float64 int8 uint8 int16 uint16 int32 uint32 int64 uint64 "
    "string wstring".split()
)
_ARRAY = re.compile(r"\[[^\]]*\]$")
_BOUND = re.compile(r"<=\d+$")


class UnknownMessageType(LookupError):
    """A message type for which ucr ships no definition."""


def short_name(typename: str) -> str:
    """``sensor_msgs/msg/JointState`` -> ``sensor_msgs/JointState``."""
    parts = typename.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return f"{parts[0]}/{parts[2]}"
    if len(parts) == 2:
        return typename
    raise UnknownMessageType(f"not a ROS 2 message type name: {typename!r}")


def full_name(typename: str) -> str:
    """``sensor_msgs/JointState`` -> ``sensor_msgs/msg/JointState`` (the name rosbag2 uses)."""
    pkg, name = short_name(typename).split("/")
    return f"{pkg}/msg/{name}"


@cache
def message_text(typename: str) -> str:
    """The ``.msg`` text of one type (without its dependencies)."""
    pkg, name = short_name(typename).split("/")
    path = MSG_DIR / pkg / f"{name}.msg"
    if not path.is_file():
        raise UnknownMessageType(f"no ROS 2 definition shipped for {typename!r}")
    return path.read_text(encoding="utf-8")


def dependencies(typename: str) -> list[str]:
    """Direct non-primitive field types of ``typename`` as ``pkg/Type``, in field order."""
    pkg = short_name(typename).split("/")[0]
    out: list[str] = []
    for raw in message_text(typename).splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        ftype = line.split()[0]
        if "=" in line.split(None, 1)[1]:
            continue  # a constant: always a primitive
        base = _BOUND.sub("", _ARRAY.sub("", ftype))
        if base in PRIMITIVES:
            continue
        dep = base if "/" in base else f"{pkg}/{base}"
        dep = short_name(dep)
        if dep not in out:
            out.append(dep)
    return out


@cache
def definition(typename: str) -> str:
    """Concatenated definition of ``typename`` and every type it uses (depth first, each once),
    as rosbag2 writes it into MCAP schema records."""
    root = short_name(typename)
    order: list[str] = []

    def visit(name: str) -> None:
        for dep in dependencies(name):
            if dep not in order and dep != root:
                order.append(dep)
                visit(dep)

    visit(root)
    parts = [message_text(root).rstrip("\n")]
    for dep in order:
        parts.append(f"{_SEPARATOR}\nMSG: {dep}\n{message_text(dep).rstrip(chr(10))}")
    return "\n".join(parts) + "\n"


def shipped_types() -> list[str]:
    """Every type with a definition here, as ``pkg/msg/Type``."""
    return sorted(f"{p.parent.name}/msg/{p.stem}" for p in MSG_DIR.glob("*/*.msg") if p.is_file())


class Codec:
    """CDR encoder and decoder of one message type (mcap-ros2-support's dynamic codec).

    ``encode`` takes nested dicts (missing fields take their defaults; arrays are lists),
    ``decode`` returns objects with attribute access."""

    def __init__(self, typename: str) -> None:
        # mcap-ros2-support's dynamic codec (what its own Writer and Decoder use; version pinned)
        from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic  # noqa: PLC0415

        self.name = full_name(typename)
        self.schema_text = definition(typename)
        self._encode: Callable[[Any], bytes] = serialize_dynamic(self.name, self.schema_text)[
            self.name
        ]
        self._decode: Callable[[bytes], Any] = generate_dynamic(self.name, self.schema_text)[
            self.name
        ]

    def encode(self, msg: Any) -> bytes:
        return bytes(self._encode(msg))

    def decode(self, data: bytes) -> Any:
        return self._decode(data)


@cache
def codec(typename: str) -> Codec:
    """The shared :class:`Codec` of ``typename``."""
    return Codec(typename)


def stamp(t_ns: int) -> dict[str, int]:
    """builtin_interfaces/Time from integer nanoseconds."""
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}
