"""RIHS01 type hashes (REP-2011 type descriptions) of the shipped ROS 2 message definitions.

The hash is computed from the type description of each ``.msg`` in :mod:`interop.ros2` and its
dependencies (rosbags' implementation of the REP-2011 algorithm), never written down per type: a
changed definition changes its hash. rmw_zenoh puts this hash into every key expression, so a
wrong one means no ROS 2 node ever matches our topics.
"""

from __future__ import annotations

from functools import cache
from typing import Any

from interop import ros2

RIHS01_PREFIX = "RIHS01_"


@cache
def _store() -> Any:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: PLC0415

    store = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for name in ros2.shipped_types():
        types.update(get_types_from_msg(ros2.message_text(name), name))
    store.register(types)
    return store


@cache
def type_hash(typename: str) -> str:
    """``RIHS01_<64 hex digits>`` of ``pkg/msg/Type`` (or ``pkg/Type``)."""
    name = ros2.full_name(typename)
    ros2.message_text(name)  # UnknownMessageType for a type ucr does not ship
    return str(_store().hash_rihs01(name))
