"""cFFC: the continuum feed-forward controller (paper Fig. 5: a hand-held controller bends the
segments, the stick deflection sets the rate of curvature change).

Input: per bendable a deflection (ux, uy), each in [-1, 1] (stick x/y), streamed through
``Daemon.ffc_input``. Output: the commanded curvature vector integrates
    d(kx, ky)/dt = kappa_rate_max * gain * (ux, uy)   (|(ux, uy)| limited to 1, deadzone applied)
clamped radially at kappa_max and, on a bendable whose phi range is restricted, kept inside that
sector (projected onto its nearer edge: it slides along it, never flips across the excluded
part; ``host.limits.clamp_to_sector``). When no input arrives for ``deadman_timeout`` s every
rate drops to zero: the robot stops where it is (deadman). Who sent the latest input
(``input_from``: the API connection's peer, program and ``on_behalf_of``) is kept and described,
so a client can tell its own input from another's; so is the setpoint (:meth:`setpoint`), which the
reply to each input carries too.
"""

from __future__ import annotations

import math
import time
from typing import Any

from host.controllers.base import (
    Commands,
    Controller,
    ControllerContext,
    ControllerError,
    RobotState,
    clamp_radial,
    sender_of,
)
from host.limits import clamp_to_sector

#: the longest ``deadman_timeout`` (s): the deadman is what stops a robot whose input stopped (a
#: client gone, a gamepad unplugged); a longer one lets it bend on, unattended, that long
MAX_DEADMAN_S = 2.0


class FeedForwardController(Controller):
    """cFFC. Parameters: joints, deadman_timeout (s, 0.3; 0.01 to MAX_DEADMAN_S), deadzone
    (0.05 of full deflection, below 1), gain (fraction of kappa_rate_max at full deflection,
    1.0; above 0: at 0 a deflected stick takes over and aborts a goal while nothing moves)."""

    type_name = "ffc"
    defaults = {**Controller.defaults, "deadman_timeout": 0.3, "deadzone": 0.05, "gain": 1.0}

    @classmethod
    def parse_params(cls, name: str, params: dict[str, Any]) -> dict[str, Any]:
        p = super().parse_params(name, params)
        num = cls.number_param
        p["deadman_timeout"] = num(name, p, "deadman_timeout", lo=0.01, hi=MAX_DEADMAN_S)
        p["deadzone"] = num(name, p, "deadzone")
        p["gain"] = num(name, p, "gain", lo=0.0, lo_open=True, hi=1.0)
        if p["deadzone"] >= 1.0:
            raise ControllerError(
                f"controller {name!r}: parameter 'deadzone' must be < 1 (of full deflection), "
                f"got {p['deadzone']!r}"
            )
        return p

    def __init__(self, name: str, params: dict[str, Any], ctx: ControllerContext):
        super().__init__(name, params, ctx)
        self.deadman_timeout = self.params["deadman_timeout"]
        self.deadzone = self.params["deadzone"]
        self.gain = self.params["gain"]
        self._cmd: dict[str, list[float]] = {j: [0.0, 0.0] for j in self.joints}
        self._input: dict[str, tuple[float, float]] = {}
        self._t_input = -math.inf
        self.deadman_tripped = False
        self.clamped = False
        #: who sent the latest input (:func:`host.controllers.base.sender_of`), None: not said
        self.input_from: dict[str, str] | None = None

    # -- input (called under the daemon lock, from any thread) ---------------------------------
    @staticmethod
    def _pair(name: str, val: Any) -> tuple[float, float]:
        if isinstance(val, dict):
            val = (val.get("x", 0.0), val.get("y", 0.0))
        if not isinstance(val, list | tuple) or len(val) != 2:
            raise ControllerError(f"ffc input {name!r}: expected [x, y] deflection in [-1, 1]")
        out = []
        for v in val:
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise ControllerError(f"ffc input {name!r}: deflection must be finite numbers")
            if abs(v) > 1.0 + 1e-9:
                raise ControllerError(f"ffc input {name!r}: deflection {v} outside [-1, 1]")
            out.append(float(v))
        return out[0], out[1]

    def validate_input(self, rates: Any) -> dict[str, tuple[float, float]]:
        """Check a stick input {bendable: (ux, uy)}; raises ControllerError naming the problem."""
        if not isinstance(rates, dict):
            raise ControllerError("ffc input: expected a mapping bendable -> [x, y]")
        new: dict[str, tuple[float, float]] = {}
        for name, val in rates.items():
            if name not in self._cmd:
                raise ControllerError(
                    f"ffc input: bendable {name!r} is not commanded by {self.name!r} "
                    f"(commanded: {', '.join(self.joints) or 'none'})"
                )
            new[name] = self._pair(name, val)
        return new

    def set_input(
        self, rates: dict[str, Any], now: float | None = None, source: Any = None
    ) -> None:
        """Replace the stick input: {bendable: (ux, uy)}; bendables not named get zero rate.
        ``source``: who sent it (:func:`host.controllers.base.sender_of`)."""
        self._input = self.validate_input(rates)
        self._t_input = time.monotonic() if now is None else now
        self.deadman_tripped = False
        self.input_from = sender_of(source)

    @staticmethod
    def has_deflection(rates: dict[str, Any], deadzone: float = 0.05) -> bool:
        """True when any stick leaves the deadzone (used by arbitration to take over)."""
        for val in rates.values():
            if isinstance(val, dict):
                val = (val.get("x", 0.0), val.get("y", 0.0))
            try:
                if math.hypot(float(val[0]), float(val[1])) > deadzone:
                    return True
            except (TypeError, ValueError, IndexError):
                return True  # malformed: let set_input report it
        return False

    # -- lifecycle / cycle ---------------------------------------------------------------------
    def on_activate(self, state: RobotState) -> None:
        for j in self.joints:
            si = state.names.index(j)
            if state.has_value(si):  # fresh or last known; never-measured ones get hold entries
                self._cmd[j] = [state.kx[si], state.ky[si]]
        self._input = {}
        self.active = True

    def adopt_measured(self, names: list[str], state: RobotState) -> None:
        for j in names:
            if j in self._cmd:
                si = state.names.index(j)
                self._cmd[j] = [state.kx[si], state.ky[si]]

    def on_deactivate(self, reason: str = "") -> None:
        self._input = {}
        self.active = False

    def rate_of(self, ux: float, uy: float, rate_max: float) -> tuple[float, float]:
        """Curvature-vector rate (1/m/s) for one deflection, with deadzone and unit-disc limit."""
        mag = math.hypot(ux, uy)
        if mag <= self.deadzone:
            return 0.0, 0.0
        scale = (min(mag, 1.0) - self.deadzone) / (1.0 - self.deadzone) / mag
        k = rate_max * self.gain * scale
        return ux * k, uy * k

    def update(self, state: RobotState, dt: float) -> Commands | None:
        if self._input and state.t - self._t_input > self.deadman_timeout:
            self._input = {}
            self.deadman_tripped = True
        self.clamped = False
        out: Commands = {}
        for j in self.joints:
            c = self._cmd[j]
            u = self._input.get(j)
            if u is not None:
                lim = self.ctx.limits[j]
                rx, ry = self.rate_of(u[0], u[1], lim.kappa_rate_max)
                kx, ky, clamped = clamp_radial(c[0] + rx * dt, c[1] + ry * dt, lim.kappa_max)
                if not lim.full_circle:  # inside the sector: slide along its edge, never across
                    sx, sy = clamp_to_sector(kx, ky, lim.phi_min, lim.phi_max, (c[0], c[1]))
                    clamped = clamped or (sx, sy) != (kx, ky)
                    kx, ky = sx, sy
                c[0], c[1] = kx, ky
                self.clamped |= clamped
            out[j] = (c[0], c[1])
        return out

    def setpoint(self) -> dict[str, list[float]]:
        """The commanded curvature vector per bendable, ``[kx, ky]`` in 1/m: what the inputs
        integrated so far (a client steering it reads this instead of modelling it)."""
        return {j: [round(c[0], 6), round(c[1], 6)] for j, c in self._cmd.items()}

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["setpoint"] = self.setpoint() if self.active else None  # inactive: a stale one
        d["input_age_s"] = None if not self._input else round(time.monotonic() - self._t_input, 3)
        d["input_from"] = self.input_from  # who sent the latest input (kept after it ends)
        d["deadman_tripped"] = self.deadman_tripped
        # what a client steering the setpoint needs to know (ucr view's slider drive)
        d["deadzone"] = self.deadzone
        d["gain"] = self.gain
        d["deadman_timeout_s"] = self.deadman_timeout
        return d
