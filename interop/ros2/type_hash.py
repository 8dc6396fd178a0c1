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
from interop.ros2 import actions, services

RIHS01_PREFIX = "RIHS01_"
EVENT_INFO = "service_msgs/ServiceEventInfo"


def _service_types(srvtype: str, parts: tuple[str, str] | None = None) -> dict[str, str]:
    """The messages rosidl generates for one service: ``{name: .msg text}`` (``srvtype`` may be
    an action's ``pkg/action/A_SendGoal`` with its ``parts`` given)."""
    if parts is None:
        pkg, name = services.split_name(srvtype)
        base = f"{pkg}/srv/{name}"
        req, resp = services.service_text(srvtype)
    else:
        base, (req, resp) = srvtype, parts
    return {
        f"{base}_Request": req,
        f"{base}_Response": resp,
        f"{base}_Event": f"{EVENT_INFO} info\n{base}_Request[<=1] request\n"
        f"{base}_Response[<=1] response\n",
        base: f"{base}_Request request_message\n{base}_Response response_message\n"
        f"{base}_Event event_message\n",
    }


def _action_types(action: str) -> dict[str, str]:
    """Every type rosidl generates for one action, with its services and the action type."""
    base = actions.full_name(action)
    gen = actions.generated(base)
    out = dict(gen)
    for svc in ("SendGoal", "GetResult"):
        parts = (gen[f"{base}_{svc}_Request"], gen[f"{base}_{svc}_Response"])
        out.update(_service_types(f"{base}_{svc}", parts))
    out[base] = actions.action_type_text(base)
    return out


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
    generated: dict[str, str] = {}
    for srv in services.shipped_services():
        generated.update(_service_types(srv))
    for action in actions.shipped_actions():
        generated.update(_action_types(action))
    for name, text in generated.items():
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
def action_type_hash(action: str, part: str = "") -> str:
    """``RIHS01_…`` of the action ``pkg/action/A`` or of one of its generated types (``part``:
    ``SendGoal``, ``GetResult``, ``FeedbackMessage``, ``Goal``, ``SendGoal_Request``, …)."""
    base = actions.full_name(action)
    actions.action_text(base)  # UnknownActionType for an action ucr does not ship
    name = f"{base}_{part}" if part else base
    if name not in _action_types(base):
        raise ValueError(f"{base} has no generated type {part!r}")
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
