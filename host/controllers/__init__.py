"""Controller registry: type name -> "module:Class", imported lazily (a broken plugin never
breaks the others), plus the entry-point group ``ucr.controllers`` for third-party controllers."""

from __future__ import annotations

import importlib
from importlib import metadata

from host.controllers.base import Controller, ControllerError

REGISTRY: dict[str, str] = {
    "jtc": "host.controllers.jtc:JointTrajectoryController",
    "ffc": "host.controllers.ffc:FeedForwardController",
    "jsb": "host.controllers.jsb:JointStateBroadcaster",
    "rsp": "host.controllers.rsp:RobotStatePublisher",
}
# Long names as the paper spells them.
ALIASES: dict[str, str] = {"cJTC": "jtc", "cFFC": "ffc", "cJSB": "jsb", "cRSP": "rsp"}

ENTRY_POINT_GROUP = "ucr.controllers"


def _entry_points() -> dict[str, metadata.EntryPoint]:
    try:
        return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}
    except Exception:  # noqa: BLE001 - broken metadata must not break the built-in controllers
        return {}


def known_types() -> list[str]:
    """All controller type names usable in a daemon config."""
    return sorted(set(REGISTRY) | set(ALIASES) | set(_entry_points()))


def controller_class(type_name: str) -> type[Controller]:
    """Import and return the class registered for ``type_name`` (raises ControllerError)."""
    type_name = ALIASES.get(type_name, type_name)
    target = REGISTRY.get(type_name)
    try:
        if target is not None:
            mod_name, cls_name = target.split(":")
            cls = getattr(importlib.import_module(mod_name), cls_name)
        else:
            ep = _entry_points().get(type_name)
            if ep is None:
                raise ControllerError(
                    f"unknown controller type {type_name!r} (known: {', '.join(known_types())})"
                )
            cls = ep.load()
    except ControllerError:
        raise
    except Exception as exc:  # noqa: BLE001 - report which plugin failed and why
        raise ControllerError(f"controller type {type_name!r} failed to load: {exc}") from exc
    if not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise ControllerError(f"controller type {type_name!r} is not a Controller subclass")
    return cls


__all__ = [
    "REGISTRY",
    "ALIASES",
    "Controller",
    "ControllerError",
    "controller_class",
    "known_types",
]
