"""RIHS01 type hashes (REP-2011 type descriptions) of the shipped ROS 2 message and service
definitions.

The hash is computed from the type description of each ``.msg`` in :mod:`interop.ros2` and its
dependencies (rosbags' implementation of the REP-2011 algorithm), never written down per type: a
changed definition changes its hash. rmw_zenoh puts this hash into every key expression, so a
wrong one means no ROS 2 node ever matches our topics.

A service ``pkg/srv/S`` (:mod:`interop.ros2.services`) is described, as rosidl generates it, by
the messages ``S_Request``, ``S_Response`` and ``S_Event`` (``service_msgs/ServiceEventInfo info,
S_Request[<=1] request, S_Response[<=1] response``) and the type ``S`` with the fields
``request_message``, ``response_message`` and ``event_message``. rosidl reads a ``.msg`` ``char``
as ``uint8``; so does the type description here.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from interop import ros2
from interop.ros2 import services

RIHS01_PREFIX = "RIHS01_"
EVENT_INFO = "service_msgs/ServiceEventInfo"


def _service_types(srvtype: str) -> dict[str, str]:
    """The messages rosidl generates for one service: ``{name: .msg text}``."""
    pkg, name = services.split_name(srvtype)
    req, resp = services.service_text(srvtype)
    base = f"{pkg}/srv/{name}"
    return {
        f"{base}_Request": req,
        f"{base}_Response": resp,
        f"{base}_Event": f"{EVENT_INFO} info\n{base}_Request[<=1] request\n"
        f"{base}_Response[<=1] response\n",
        base: f"{base}_Request request_message\n{base}_Response response_message\n"
        f"{base}_Event event_message\n",
    }


def _rename(x: Any, fix: dict[str, str]) -> Any:
    """Undo rosbags' normalisation of ``pkg/srv/T`` to ``pkg/srv/msg/T``; ``char`` -> ``uint8``
    (rosidl's reading of a .msg ``char``)."""
    if isinstance(x, str):
        return fix.get(x, "uint8" if x == "char" else x)
    if isinstance(x, tuple | list):
        return type(x)(_rename(i, fix) for i in x)
    return x


@cache
def _store() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: PLC0415

    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for name in ros2.shipped_types():
        types.update(get_types_from_msg(ros2.message_text(name), name))
    fix: dict[str, str] = {}
    for srv in services.shipped_services():
        for name, text in _service_types(srv).items():
            parsed = get_types_from_msg(text, name)
            for key in parsed:
                fix[key] = name
            types.update(parsed)
    store.register({_rename(k, fix): _rename(v, fix) for k, v in types.items()})
    return store


@cache
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex digits>`` of ``pkg/msg/Type`` (or ``pkg/Type``)."""
    name = ros2.full_name(typename)
    ros2.message_text(name)  # UnknownMessageType for a type ucr does not ship
    return str(_store().hash_rihs01(name))


@cache
def service_type_hash(srvtype: str, part: str = "") -> str:
    """``RIHS01_…`` of the service ``pkg/srv/S`` (what rmw_zenoh puts into a service's key
    expression), or of one of its messages (``part``: ``Request``, ``Response``, ``Event``)."""
    name = services.full_name(srvtype)
    services.service_text(name)  # UnknownServiceType for a service ucr does not ship
    if part not in ("", "Request", "Response", "Event"):
        raise ValueError(f"service part {part!r}")
    return str(_store().hash_rihs01(f"{name}_{part}" if part else name))
