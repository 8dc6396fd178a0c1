"""Hardware interface (paper REQ 1): command and state interfaces per bendable, with lifecycle.

Interfaces are named ``<bendable>/kappa`` and ``<bendable>/phi`` as the U(C)RDF ``<ros2_control>``
block declares them (initial values, min/max from its params, see ``host.config.bendable_limits``).

Lifecycle, as ros2_control's hardware components:
``unconfigured`` --configure--> ``inactive`` --activate--> ``active``, and back with
``deactivate`` (active → inactive) and ``cleanup`` (inactive → unconfigured).
- state interfaces are readable from ``inactive`` on (configure reads the segments once);
- command interfaces are written to the segments only while ``active``. While inactive the cycle
  sends HEARTBEAT (feeds the segments' watchdogs, returns states) and never a setpoint.

A segment that reports HOLD ignores setpoints until a SYNC with "resume": activation sets
``resume_pending`` (the first SYNCs resume), and it clears once no segment reports HOLD.

One bus exchange per cycle: ``write()`` sends one SYNC (setpoints of every segment, one frame) or a
HEARTBEAT and stores the STATE replies; ``read()`` at the start of the next cycle copies those
states into the state interfaces. So read → update → write costs one frame down and one round of
STATE frames up.
"""

from __future__ import annotations

import math
from typing import Any

from host.config import BendableLimits

UNCONFIGURED, INACTIVE, ACTIVE = "unconfigured", "inactive", "active"


class LifecycleError(RuntimeError):
    """A lifecycle transition or interface access that the current state does not allow."""


class HardwareInterface:
    """The HWI of one chain. ``limits`` is chain-ordered: bendable i is segment position i.

    ``link`` is a :class:`host.link.ChainLink` (or anything with its ``sync``/``heartbeat``).
    """

    def __init__(self, limits: dict[str, BendableLimits], link: Any, reply_timeout: float = 0.02):
        self.limits = limits
        self.names = list(limits)
        self.link = link
        self.reply_timeout = reply_timeout
        self.state = UNCONFIGURED
        self.command: dict[str, float] = {}
        self.state_values: dict[str, float] = {}
        for name, bl in limits.items():
            if "kappa" in bl.command_interfaces:
                self.command[f"{name}/kappa"] = bl.kappa_initial
            if "phi" in bl.command_interfaces:
                self.command[f"{name}/phi"] = bl.phi_initial
        self.raw_states: list[dict | None] = [None] * len(self.names)
        self.missing = [0] * len(self.names)  # consecutive cycles without a STATE, per position
        self.extra_states: list[dict] = []  # STATEs from positions beyond the known chain
        self.exchanges = 0
        self.resume_pending = False  # next SYNCs carry "resume" until no segment reports HOLD
        self._pending: list[dict | None] | None = None

    # -- lifecycle ---------------------------------------------------------------------------
    def configure(self) -> None:
        """unconfigured → inactive: read the segments once so state interfaces hold real values."""
        if self.state != UNCONFIGURED:
            raise LifecycleError(f"configure: HWI is {self.state}, expected {UNCONFIGURED}")
        self._pending = self.link.heartbeat(timeout=max(self.reply_timeout, 0.05))
        self.state = INACTIVE
        self.read()

    def activate(self) -> None:
        """inactive → active. Commands start at the measured state, so activation never jumps."""
        if self.state != INACTIVE:
            raise LifecycleError(f"activate: HWI is {self.state}, expected {INACTIVE}")
        for i, name in enumerate(self.names):
            st = self.raw_states[i]
            if st is not None:
                if f"{name}/kappa" in self.command:
                    self.command[f"{name}/kappa"] = float(st["kappa"])
                if f"{name}/phi" in self.command:
                    self.command[f"{name}/phi"] = float(st["phi"])
        self.resume_pending = True  # segments may be holding (HOLD before a rebuild): resume
        self.state = ACTIVE

    def deactivate(self) -> None:
        """active → inactive: setpoints stop; the segments hold the last one (and heartbeats)."""
        if self.state != ACTIVE:
            raise LifecycleError(f"deactivate: HWI is {self.state}, expected {ACTIVE}")
        self.state = INACTIVE

    def cleanup(self) -> None:
        """inactive → unconfigured: forget the states."""
        if self.state != INACTIVE:
            raise LifecycleError(f"cleanup: HWI is {self.state}, expected {INACTIVE}")
        self.state_values.clear()
        self.raw_states = [None] * len(self.names)
        self.state = UNCONFIGURED

    # -- interfaces --------------------------------------------------------------------------
    def command_interface_names(self) -> list[str]:
        return list(self.command)

    def state_interface_names(self) -> list[str]:
        return [f"{n}/{i}" for n, bl in self.limits.items() for i in bl.state_interfaces]

    def get_state(self, interface: str) -> float:
        if self.state == UNCONFIGURED:
            raise LifecycleError("state interfaces are readable once the HWI is configured")
        if interface not in self.state_values:
            raise KeyError(
                f"no state interface {interface!r} (have: "
                f"{', '.join(self.state_interface_names())})"
            )
        return self.state_values[interface]

    def set_command(self, interface: str, value: float) -> None:
        """Write a command interface (clamped to its declared range). Needs ``active``."""
        if self.state != ACTIVE:
            raise LifecycleError(f"command {interface!r} refused: HWI is {self.state}, not active")
        if interface not in self.command:
            raise KeyError(f"no command interface {interface!r}")
        if not math.isfinite(value):
            raise ValueError(f"command {interface!r}: value must be finite, got {value}")
        name, _, kind = interface.rpartition("/")
        bl = self.limits[name]
        if kind == "kappa":
            value = min(max(value, 0.0), bl.kappa_max)
        elif not bl.full_circle:
            value = min(max(value, bl.phi_min), bl.phi_max)
        self.command[interface] = value

    def set_curvature(self, name: str, kx: float, ky: float) -> None:
        """Write both interfaces of a bendable from a curvature vector (phi held at kappa = 0)."""
        kappa = math.hypot(kx, ky)
        self.set_command(f"{name}/kappa", kappa)
        if f"{name}/phi" in self.command and kappa > 1e-9:
            self.set_command(f"{name}/phi", math.atan2(ky, kx))

    def setpoints(self) -> list[tuple[float, float]]:
        """(kappa, phi) per position from the command interfaces (SI)."""
        out = []
        for name in self.names:
            out.append(
                (self.command.get(f"{name}/kappa", 0.0), self.command.get(f"{name}/phi", 0.0))
            )
        return out

    # -- cycle -------------------------------------------------------------------------------
    def read(self) -> list[dict | None]:
        """Copy the STATEs of the last exchange into the state interfaces; returns them."""
        if self.state == UNCONFIGURED:
            raise LifecycleError("read: HWI is unconfigured")
        states = self._pending
        self._pending = None
        if states is None:
            return self.raw_states
        n = len(self.names)
        self.extra_states = [s for s in states[n:] if s is not None]
        for i in range(n):
            st = states[i] if i < len(states) else None
            if st is None:
                self.missing[i] += 1
                self.raw_states[i] = None
                continue
            self.missing[i] = 0
            self.raw_states[i] = st
            name = self.names[i]
            self.state_values[f"{name}/kappa"] = float(st["kappa"])
            self.state_values[f"{name}/phi"] = float(st["phi"])
        if self.resume_pending and not any(
            st is not None and "HOLD" in st["status"] for st in self.raw_states
        ):
            self.resume_pending = False
        return self.raw_states

    def write(self) -> None:
        """One bus exchange: SYNC with the setpoints when active, else HEARTBEAT."""
        if self.state == UNCONFIGURED:
            raise LifecycleError("write: HWI is unconfigured")
        if self.state == ACTIVE:
            self._pending = self.link.sync(
                self.setpoints(), timeout=self.reply_timeout, resume=self.resume_pending
            )
        else:
            self._pending = self.link.heartbeat(timeout=self.reply_timeout)
        self.exchanges += 1
