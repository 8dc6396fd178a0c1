"""Kinematic model plugins (PCC, PPC, …), found by name and through entry points.

Built-in models sit in a small name -> "module:Class" table and are imported only when first
requested. Third-party packages add models through the entry-point group ``ucrdf.models``::

    [project.entry-points."ucrdf.models"]
    mymodel = "mypkg.kinematics:MyModel"

A plugin that fails to import never breaks the others: the failure is reported (as ModelError)
only when its type is requested.
"""

from __future__ import annotations

import importlib
import warnings
from importlib import metadata

from ucrdf.model import ModelSpec
from ucrdf.models.base import CurvatureModel, ModelError, Variable

__all__ = [
    "ENTRY_POINT_GROUP",
    "CurvatureModel",
    "ModelError",
    "Variable",
    "available",
    "create",
    "get_model",
]

ENTRY_POINT_GROUP = "ucrdf.models"

_BUILTIN: dict[str, str] = {
    "pcc": "ucrdf.models.pcc:PCCModel",
    "ppc": "ucrdf.models.ppc:PPCModel",
}

_loaded: dict[str, type[CurvatureModel]] = {}


def _entry_points() -> dict[str, metadata.EntryPoint]:
    """Entry points of the group, read afresh (packages may be installed while we run)."""
    found: dict[str, metadata.EntryPoint] = {}
    try:
        eps = metadata.entry_points(group=ENTRY_POINT_GROUP)
    except Exception as exc:  # a corrupt dist-info must not break the built-in models
        warnings.warn(f"could not read entry points of {ENTRY_POINT_GROUP!r}: {exc}", stacklevel=2)
        return found
    for ep in eps:
        if ep.name in _BUILTIN:
            warnings.warn(
                f"entry point {ep.name} = {ep.value} ignored: {ep.name!r} is a built-in model",
                stacklevel=2,
            )
            continue
        found.setdefault(ep.name, ep)
    return found


def available() -> list[str]:
    """Names of every model type that can be requested (built-in first, then plugins, sorted).

    Plugins are listed without importing them; a broken one fails only in :func:`get_model`."""
    return list(_BUILTIN) + sorted(set(_entry_points()) - set(_BUILTIN))


def _check_class(name: str, origin: str, obj: object) -> type[CurvatureModel]:
    if not (isinstance(obj, type) and issubclass(obj, CurvatureModel)):
        raise ModelError(
            f"model type {name!r} ({origin}) is not a CurvatureModel subclass: {obj!r}"
        )
    return obj


def get_model(name: str) -> type[CurvatureModel]:
    """The model class registered as ``name``; ModelError (listing what exists) otherwise."""
    if name in _loaded:
        return _loaded[name]
    if name in _BUILTIN:
        module_name, _, attr = _BUILTIN[name].partition(":")
        cls = _check_class(
            name, _BUILTIN[name], getattr(importlib.import_module(module_name), attr)
        )
        _loaded[name] = cls
        return cls
    ep = _entry_points().get(name)
    if ep is None:
        raise ModelError(f"unknown model type {name!r}; available: {', '.join(available())}")
    origin = f"entry point {ep.name} = {ep.value}"
    try:
        obj = ep.load()
    except Exception as exc:  # report the plugin's own failure, whatever it is
        raise ModelError(
            f"model type {name!r} could not be loaded from {origin}: {type(exc).__name__}: {exc}"
        ) from exc
    return _check_class(name, origin, obj)


def create(spec: ModelSpec) -> CurvatureModel:
    """An instance of the model named by ``spec.type``, built (and validated) from ``spec``."""
    cls = get_model(spec.type)
    try:
        return cls(spec)
    except ModelError:
        raise
    except Exception as exc:  # a plugin's constructor failing must not look like a crash
        raise ModelError(f"model {spec.type!r} rejected its parameters: {exc}") from exc
