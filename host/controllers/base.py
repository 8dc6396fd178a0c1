"""Controller base class and the data it sees each cycle.

A controller is constructed for one robot (its bendables and their limits, in chain order), claims
command interfaces (``<name>/kappa``, ``<name>/phi``) while active, and in ``update`` returns
desired curvature vectors (kx, ky) in 1/m for the bendables it commands. Broadcasters claim
nothing and publish instead. The controller manager turns (kx, ky) into the (kappa, phi) interface
form, so every controller works in (kx, ky) as the architecture prescribes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from host.limits import BendableLimits


class ControllerError(ValueError):
    """A controller cannot be loaded, configured or given this request (message says why)."""


@dataclass
class RobotState:
    """Measured state of the controlled bendables at time ``t`` (s, monotonic), chain order.

    Curvature vectors (kx, ky) and the interface form (kappa, phi) in SI; ``valid[i]`` is False
    when segment i did not answer this cycle (its values are then the last known ones).
    ``t_ms[i]`` is segment i's own time stamp of the measurement (ms since its boot) or None.
    ``known[i]`` is True when the values are real (measured this cycle or last known); False
    only for a segment never measured (its values are then zeros and must not be commanded).
    """

    t: float
    names: list[str]
    kx: list[float]
    ky: list[float]
    kappa: list[float]
    phi: list[float]
    valid: list[bool]
    t_ms: list[int | None] = field(default_factory=list)
    known: list[bool] = field(default_factory=list)

    def has_value(self, i: int) -> bool:
        """Whether position ``i`` holds a real (fresh or last known) measurement."""
        return self.valid[i] or (i < len(self.known) and self.known[i])

    @classmethod
    def zeros(cls, names: list[str], t: float = 0.0) -> RobotState:
        n = len(names)
        return cls(
            t,
            list(names),
            [0.0] * n,
            [0.0] * n,
            [0.0] * n,
            [0.0] * n,
            [False] * n,
            [None] * n,
            [False] * n,
        )


@dataclass
class ControllerContext:
    """What a controller knows about the robot it runs on. ``limits`` is chain-ordered.

    ``publish(msg)`` hands a message dict to the daemon's subscribers (broadcasters use it);
    ``offload(fn)`` runs ``fn()`` outside the control cycle (the daemon's publisher thread; by
    default at once), for work that only feeds subscribers, such as cRSP's FK;
    ``robot`` is the (possibly truncated) U(C)RDF robot currently controlled.
    """

    limits: dict[str, BendableLimits]
    robot: Any = None
    publish: Callable[[dict], None] = field(default=lambda msg: None)
    offload: Callable[[Callable[[], None]], None] = field(default=lambda fn: fn())

    @property
    def names(self) -> list[str]:
        return list(self.limits)


Commands = dict[str, tuple[float, float]]


class Controller:
    """Base of every controller. Subclasses set ``type_name`` and override the hooks.

    Lifecycle (managed by the controller manager): constructed → ``on_activate`` → ``update`` each
    cycle → ``on_deactivate``. ``params`` come from the daemon config; unknown keys are an error.
    """

    type_name: str = ""
    #: parameter name -> default; subclasses extend. "joints" = bendables to command (None = all).
    defaults: dict[str, Any] = {"joints": None}
    #: broadcasters do not claim command interfaces
    claims_commands: bool = True

    def __init__(self, name: str, params: dict[str, Any], ctx: ControllerContext):
        self.name = name
        self.params = self.parse_params(name, params)
        self.ctx = ctx
        joints = self.params.get("joints")
        if joints is None:
            self.joints = list(ctx.limits)
        else:
            # After a hot-plug some configured bendables may be gone: keep the present ones.
            self.joints = [j for j in ctx.limits if j in joints]
        self.active = False

    @classmethod
    def parse_params(cls, name: str, params: dict[str, Any]) -> dict[str, Any]:
        """The checked parameters, defaults filled in (a subclass's numbers as floats); raises
        :class:`ControllerError` naming the controller and the parameter.

        Needs no robot: the daemon's configuration is checked with it when it is read, before
        the chain port is opened (host/config.py), and :meth:`__init__` runs the very same
        checks, so a file the configuration accepts is one every controller loads. Subclasses
        extend it (``super().parse_params`` first) and read their values from ``self.params``.
        """
        unknown = set(params) - set(cls.defaults)
        if unknown:
            raise ControllerError(
                f"controller {name!r} ({cls.type_name}): unknown parameter(s) "
                f"{', '.join(sorted(unknown))} (known: {', '.join(sorted(cls.defaults))})"
            )
        out = {**cls.defaults, **params}
        joints = out.get("joints")
        if joints is not None and (
            not isinstance(joints, list) or not all(isinstance(j, str) for j in joints)
        ):
            raise ControllerError(f"controller {name!r}: 'joints' must be a list of names")
        return out

    # -- helpers -----------------------------------------------------------------------------
    @staticmethod
    def number_param(
        name: str,
        params: dict[str, Any],
        key: str,
        *,
        lo: float = 0.0,
        hi: float | None = None,
        lo_open: bool = False,
    ) -> float:
        """``params[key]`` as a float within [lo, hi] (``lo_open``: above ``lo``), else a
        :class:`ControllerError` saying the bounds (for :meth:`parse_params`)."""
        v = params[key]
        ok = not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
        if ok:
            ok = (v > lo if lo_open else v >= lo) and (hi is None or v <= hi)
        if not ok:
            bound = f"{'>' if lo_open else '>='} {lo:g}" + ("" if hi is None else f" and <= {hi:g}")
            raise ControllerError(
                f"controller {name!r}: parameter {key!r} must be a number {bound}, got {v!r}"
            )
        return float(v)

    def _float_param(self, key: str, *, lo: float = 0.0) -> float:
        """``self.params[key]`` as a float >= ``lo`` (kept for controllers written before
        :meth:`parse_params`; new ones check there, so the configuration is checked early)."""
        return self.number_param(self.name, self.params, key, lo=lo)

    def command_interfaces(self) -> list[str]:
        """The command interfaces this controller claims while active."""
        if not self.claims_commands:
            return []
        out = []
        for j in self.joints:
            out += [f"{j}/{i}" for i in self.ctx.limits[j].command_interfaces]
        return out

    def describe(self) -> dict[str, Any]:
        """Status for ``Daemon.controllers()``; subclasses add their own fields."""
        return {
            "name": self.name,
            "type": self.type_name,
            "state": "active" if self.active else "inactive",
            "claimed_interfaces": self.command_interfaces() if self.active else [],
            "joints": list(self.joints),
        }

    # -- hooks -------------------------------------------------------------------------------
    def on_activate(self, state: RobotState) -> None:
        """Called when switched on; commanding controllers start by holding ``state``."""

    def adopt_measured(self, names: list[str], state: RobotState) -> None:
        """Bendables ``names`` were just measured for the first time since the HWI activated
        (they got hold entries until now): commanding controllers start holding them there."""

    def on_deactivate(self, reason: str = "") -> None:
        """Called when switched off (``reason`` says why, for goals that end here)."""

    def update(self, state: RobotState, dt: float) -> Commands | None:
        """One cycle: return {bendable: (kx, ky)} desired (1/m), or None for no command."""
        return None


#: what a command's sender may say (cFFC ``input_from``, a goal's ``from``), each a string of at
#: most SENDER_CHARS characters: the API connection's address and program and whom it acts for
SENDER_KEYS = ("peer", "client", "for")
SENDER_CHARS = 80


def sender_of(source: Any) -> dict[str, str] | None:
    """Who sent a command, as the daemon describes it: the SENDER_KEYS whose values are strings
    (longer ones cut to SENDER_CHARS); None for anything else (not said)."""
    if not isinstance(source, dict):
        return None
    out = {k: v[:SENDER_CHARS] for k in SENDER_KEYS if isinstance(v := source.get(k), str)}
    return out or None


def clamp_radial(kx: float, ky: float, kmax: float) -> tuple[float, float, bool]:
    """Scale (kx, ky) back onto the disc |kappa| <= kmax. Returns (kx, ky, clamped)."""
    k = math.hypot(kx, ky)
    if k <= kmax:
        return kx, ky, False
    s = kmax / k
    return kx * s, ky * s, True
