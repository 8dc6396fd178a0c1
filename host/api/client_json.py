"""Turning a request's parameters into JSON for the client (:mod:`host.api.client`): numpy values
a script computes pass as plain numbers, and a value JSON cannot carry is named by where it is
in the request, before anything is sent."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from host.api.client_errors import ApiError

__all__ = ["as_pair", "name_list", "plain_json", "unencodable", "waypoint_list"]


def plain_json(value: Any) -> Any:
    """JSON for what a script computes with numpy: its scalars and arrays (``tolist``); a
    :class:`TypeError` for anything else (the client then says where it is in the request)."""
    tolist = getattr(value, "tolist", None)
    if callable(tolist):
        return tolist()
    raise TypeError(type(value).__name__)


def as_pair(value: Any) -> Any:
    """A deflection ``(dkx, dky)`` as the JSON array the API takes; anything else is sent as it
    is, for the server to say what is wrong with it (``rates.segment_1: expected …``)."""
    if isinstance(value, list | tuple):
        return list(value)
    tolist = getattr(value, "tolist", None)  # a numpy array (a numpy scalar: the server says)
    return tolist() if callable(tolist) else value


def name_list(value: Any) -> Any:
    """Controller names as the API takes them (a JSON array): one name alone (a ``str``) is a
    list of one — ``switch(start="jtc")`` was sent as ``["j", "t", "c"]`` — None is none, any
    other iterable (a tuple, a generator) a list; anything else is sent as it is, for the
    server to say what is wrong with it."""
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    if isinstance(value, Iterable) and not isinstance(value, bytes | bytearray | dict):
        return list(value)
    return value


def waypoint_list(points: Any) -> list:
    """Waypoints as a list: any iterable of them (a generator, a tuple) is read once; a single
    waypoint (a dict), a string or a non-iterable is an :class:`ApiError` (``invalid_params``)
    before anything is sent."""
    if isinstance(points, list):
        return points
    if isinstance(points, Iterable) and not isinstance(points, str | bytes | bytearray | dict):
        return list(points)
    raise ApiError(
        "invalid_params",
        f"points: expected a list of waypoints, got {type(points).__name__}"
        + (" (one waypoint: put it in a list)" if isinstance(points, dict) else ""),
    )


def unencodable(value: Any, path: str = "") -> str:
    """Where in a request's parameters the first value JSON cannot carry is, and what it is:
    ``points[0].segments.segment_1.kappa: nan is not a finite number``."""
    if isinstance(value, dict):
        for k, v in value.items():
            if not isinstance(k, str | int | float | bool) and k is not None:
                return f"{path or 'parameters'}: key {k!r} is not a string"
            found = unencodable(v, f"{path}.{k}" if path else str(k))
            if found:
                return found
        return ""
    if isinstance(value, list | tuple):
        for i, v in enumerate(value):
            found = unencodable(v, f"{path}[{i}]")
            if found:
                return found
        return ""
    if isinstance(value, str | bool | int) or value is None:
        return ""
    if isinstance(value, float):
        return "" if math.isfinite(value) else f"{path}: {value} is not a finite number"
    try:
        plain = plain_json(value)
    except TypeError:
        return f"{path}: a {type(value).__name__} is not a JSON value"
    return unencodable(plain, path)
