"""Controller manager: loads controllers by type from the daemon config, keeps exclusive claims on
command interfaces, activates/deactivates/switches them, and runs the active ones each cycle.

A switch is atomic: it is checked completely (names, claims after the switch) before anything
changes, and a conflict names the interface and the controller holding it. After a topology change
``rebuild`` recreates every controller for the new robot and re-activates the ones that were
active (each commanding controller holds the measured position on activation).
"""

from __future__ import annotations

import logging
import math
from typing import Any

from host.controllers import controller_class
from host.controllers.base import (
    Commands,
    Controller,
    ControllerContext,
    ControllerError,
    RobotState,
)

log = logging.getLogger("ucr.controllers")


class SwitchError(ControllerError):
    """A requested controller switch is impossible (unknown name, conflicting claims, …)."""


class ControllerManager:
    """Owns the controller instances of one robot. Not thread-safe: the daemon holds its lock."""

    def __init__(self, specs: dict[str, dict[str, Any]], ctx: ControllerContext):
        self.specs = specs
        self.ctx = ctx
        self.controllers: dict[str, Controller] = {}
        self.failed: dict[str, str] = {}
        self._load()

    def _load(self) -> None:
        self.controllers, self.failed = {}, {}
        for name, spec in self.specs.items():
            try:
                cls = controller_class(spec["type"])
                self.controllers[name] = cls(name, dict(spec.get("params") or {}), self.ctx)
            except ControllerError as exc:
                # One broken controller never breaks the others: report it, keep going.
                self.failed[name] = str(exc)
                log.error("controller %s not loaded: %s", name, exc)

    # -- queries -----------------------------------------------------------------------------
    def active_names(self) -> list[str]:
        return [n for n, c in self.controllers.items() if c.active]

    def claims(self) -> dict[str, str]:
        """Claimed command interface -> controller name."""
        out: dict[str, str] = {}
        for n, c in self.controllers.items():
            if c.active:
                for itf in c.command_interfaces():
                    out[itf] = n
        return out

    def describe(self) -> list[dict[str, Any]]:
        out = [c.describe() for c in self.controllers.values()]
        for n, err in self.failed.items():
            out.append(
                {
                    "name": n,
                    "type": self.specs[n]["type"],
                    "state": "failed",
                    "error": err,
                    "claimed_interfaces": [],
                    "joints": [],
                }
            )
        return out

    def of_type(self, type_name: str) -> list[Controller]:
        return [c for c in self.controllers.values() if c.type_name == type_name]

    def get(self, name: str) -> Controller:
        if name in self.failed:
            raise SwitchError(f"controller {name!r} failed to load: {self.failed[name]}")
        c = self.controllers.get(name)
        if c is None:
            raise SwitchError(
                f"unknown controller {name!r} (configured: {', '.join(self.specs) or 'none'})"
            )
        return c

    # -- switching ---------------------------------------------------------------------------
    def switch(
        self, start: list[str], stop: list[str], state: RobotState, reason: str = ""
    ) -> dict[str, list[str]]:
        """Deactivate ``stop`` then activate ``start``; all-or-nothing. Returns what changed."""
        start, stop = list(dict.fromkeys(start or [])), list(dict.fromkeys(stop or []))
        for n in start + stop:
            self.get(n)
        both = set(start) & set(stop)
        if both:
            raise SwitchError(f"controller(s) {', '.join(sorted(both))} both started and stopped")
        remaining = {n for n in self.active_names() if n not in stop}
        holder = {itf: n for itf, n in self.claims().items() if n in remaining}
        for n in start:
            if n in remaining:
                continue  # already active: nothing to do for it
            for itf in self.controllers[n].command_interfaces():
                if itf in holder:
                    raise SwitchError(
                        f"cannot start {n!r}: command interface {itf!r} is claimed by "
                        f"{holder[itf]!r} (stop it in the same switch)"
                    )
                holder[itf] = n
        stopped = [n for n in stop if self.controllers[n].active]
        for n in stopped:
            self.controllers[n].on_deactivate(reason or f"controller {n!r} stopped by switch")
        started = [n for n in start if not self.controllers[n].active]
        for n in started:
            self.controllers[n].on_activate(state)
        if started or stopped:
            log.info("controllers switched: started %s, stopped %s", started, stopped)
        return {"started": started, "stopped": stopped}

    def rebuild(self, ctx: ControllerContext, state: RobotState, reason: str) -> list[str]:
        """Recreate every controller for a new robot; re-activate those that were active."""
        was_active = self.active_names()
        for n in was_active:
            self.controllers[n].on_deactivate(reason)
        self.ctx = ctx
        self._load()
        started = []
        for n in was_active:
            if n in self.controllers:
                try:
                    self.switch([n], [], state, reason)
                    started.append(n)
                except SwitchError as exc:
                    log.error("after rebuild, %s stays inactive: %s", n, exc)
        return started

    # -- cycle -------------------------------------------------------------------------------
    def update(self, state: RobotState, dt: float) -> Commands:
        """Run every active controller; merge commands (claims guarantee no overlap)."""
        out: Commands = {}
        for c in self.controllers.values():
            if not c.active:
                continue
            cmd = c.update(state, dt)
            if cmd:
                for j, (kx, ky) in cmd.items():
                    if math.isfinite(kx) and math.isfinite(ky):
                        out[j] = (kx, ky)
                    else:
                        log.error(
                            "controller %s produced a non-finite command for %s; ignored "
                            "this cycle (segment keeps its last setpoint)",
                            c.name,
                            j,
                        )
        return out
