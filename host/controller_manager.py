"""Controller manager: loads controllers by type from the daemon config, keeps exclusive claims on
command interfaces, activates/deactivates/switches them, and runs the active ones each cycle.

A switch is atomic: it is checked completely (names, claims after the switch) before anything
changes, and a conflict names the interface and the controller holding it. After a topology change
``rebuild`` recreates every controller for the new robot and re-activates the ones that were
active (each commanding controller holds the measured position on activation). A running
trajectory goal that moves none of the segments the change concerns (``affected``) is carried
over to the rebuilt controller and runs on; every other goal is aborted with the cause and
segment the caller gives (never a cause guessed from the reason's words).
"""

from __future__ import annotations

import logging
import math
import time
from typing import Any

from host.controllers import controller_class
from host.controllers.base import (
    Commands,
    Controller,
    ControllerContext,
    ControllerError,
    RobotState,
)
from host.controllers.trajectory import GoalStart

log = logging.getLogger("ucr.controllers")
# a cycle later than this many periods after the last one is a pause: timed motions are shifted
PAUSE_CYCLES = 3.0


class SwitchError(ControllerError):
    """A requested controller switch is impossible (unknown name, conflicting claims, …)."""


class ControllerManager:
    """Owns the controller instances of one robot. Not thread-safe: the daemon holds its lock."""

    def __init__(self, specs: dict[str, dict[str, Any]], ctx: ControllerContext):
        self.specs = specs
        self.ctx = ctx
        self.controllers: dict[str, Controller] = {}
        self.failed: dict[str, str] = {}
        self.last_aborted: list[str] = []  # goals the last rebuild aborted
        #: the time of the last cycle (its state's, s): where the robot's motion stands while
        #: the loop pauses (a rebuild decides at it what a carried goal still has to run)
        self.t_last: float | None = None
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
        self,
        start: list[str],
        stop: list[str],
        state: RobotState,
        reason: str = "",
        *,
        logged: bool = True,
    ) -> dict[str, list[str]]:
        """Deactivate ``stop`` then activate ``start``; all-or-nothing. Returns what changed
        (logged unless ``logged`` is False: a rebuild logs its restarts in one line)."""
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
            why = reason or f"controller {n!r} stopped by switch"
            abort = getattr(self.controllers[n], "abort_active", None)
            if abort is not None:
                abort(why, cause="stopped")  # its goal ends with that cause, not a guessed one
            self.controllers[n].on_deactivate(why)
        started = [n for n in start if not self.controllers[n].active]
        for n in started:
            self.controllers[n].on_activate(state)
        if logged and (started or stopped):
            log.info("controllers switched: started %s, stopped %s", started, stopped)
        return {"started": started, "stopped": stopped}

    def rebuild(
        self,
        ctx: ControllerContext,
        state: RobotState,
        reason: str,
        *,
        cause: str = "stopped",
        segment: str | None = None,
        affected: set[str] | None = None,
    ) -> list[str]:
        """Recreate every controller for a new robot; re-activate those that were active.

        ``affected``: the segments the change concerns (lost, replaced, rebooted). A running
        goal that moves none of them and none that the new robot lacks is carried over to the
        rebuilt controller (its path continues, no jump: the segments it moves were commanded
        along it until now); ``None``: every goal ends. The goals that end are aborted with
        ``reason``, ``cause`` and ``segment``; their ids are in :attr:`last_aborted`."""
        now = time.monotonic()
        was_active = self.active_names()
        carried: dict[str, tuple[Any, Any, list[str], Any]] = {}
        kept: set[str] = set()
        self.last_aborted: list[str] = []
        started: list[str] = []
        try:
            for n in was_active:
                c = self.controllers[n]
                g = getattr(c, "current_goal", None)
                tr = getattr(g, "trajectory", None)
                if g is None:
                    pass
                elif (
                    affected is not None
                    and tr is not None
                    and not tr.moving(list(c.joints), now) & (set(affected) | self._gone(c, ctx))
                ):
                    g.carried = True
                    # at the last cycle's time: a pause that began before the path's start and
                    # ends after it is taken back by the time shift after the rebuild (update)
                    t_ref = now if self.t_last is None else min(now, self.t_last)
                    lead = getattr(c, "lead_in_at", lambda _t: None)(t_ref)
                    carried[n] = (g, tr, list(c.joints), lead)
                elif c.abort_active(reason, cause=cause, segment=segment):
                    self.last_aborted.append(g.id)
            for n in was_active:
                self.controllers[n].on_deactivate(reason)
            self.ctx = ctx
            self._load()
            for n in was_active:
                if n in self.controllers:
                    try:
                        self.switch([n], [], state, reason, logged=False)
                        started.append(n)
                    except SwitchError as exc:
                        log.error("after rebuild, %s stays inactive: %s", n, exc)
            if started:
                log.info("controllers rebuilt and restarted (%s): %s", reason, ", ".join(started))
            for n, (g, tr, joints, lead) in carried.items():
                if self._carry(n, g, tr, joints, state, set(affected or ()), lead):
                    kept.add(n)
        finally:  # whatever was raised, every goal can end again: not carried is aborted
            for n, (g, *_) in carried.items():
                g.carried = False
                if n not in kept:
                    g.finish("aborted", reason, cause=cause, segment=segment)
                    self.last_aborted.append(g.id)
        return started

    @staticmethod
    def _gone(c: Controller, ctx: ControllerContext) -> set[str]:
        """Joints of ``c`` that the new robot (``ctx``) does not have."""
        return {j for j in c.joints if j not in ctx.limits}

    def _carry(
        self,
        name: str,
        goal: Any,
        traj: Any,
        joints: list[str],
        state: RobotState,
        affected: set[str],
        lead_in: Any = None,
    ) -> bool:
        """Install ``goal`` (path ``traj`` over ``joints``) on the rebuilt controller ``name``,
        its path mapped onto that controller's joints. A joint that holds where measured (the
        rebuilt controller's hold, ``snap.p``) for the rest of the goal: one new to the path,
        one the change concerns (``affected``: rebooted, swapped, behind the change — the goal
        only held it still, and its old value is stale: docs/daemon.md "No motion without a
        command"), and one the path holds still that was not measured at the rebuild. False
        when it cannot run there. The path keeps its time base: the first cycle after the
        rebuild shifts it by the pause (:meth:`update`). ``lead_in``: the old motion that runs
        until a path that has not begun yet begins (mapped the same way and carried too: the
        path starts where it ends, so holding meanwhile would end in a jump)."""
        c = self.controllers.get(name)
        if c is None or not c.active or not hasattr(c, "install_goal"):
            return False
        now = time.monotonic()
        try:
            snap = c.goal_snapshot(now)
            moving = traj.moving(joints, now)
            index = {n: i for i, n in enumerate(state.names)}
            unmeasured = {j for j in c.joints if j not in index or not state.valid[index[j]]}
            held = (set(c.joints) & affected) | (unmeasured - moving)
            path = traj.remapped(joints, list(c.joints), snap.p, held)
            if lead_in is not None:  # (the path had not begun at the last cycle)
                c.run_lead_in(lead_in.remapped(joints, list(c.joints), snap.p, held))
                snap = c.goal_snapshot(now)
            accepted = goal.t_accepted
            start = GoalStart(now, snap.p, snap.v, snap.a, snap.generation, at_rest=False)
            c.install_goal(goal, path, start, now)
            goal.t_accepted = accepted
        except ControllerError as exc:
            log.warning("goal %s not carried over the rebuild: %s", goal.id, exc)
            return False
        log.info("goal %s carried over the rebuild (it moves none of the segments concerned)",
                 goal.id)  # fmt: skip
        return True

    # -- cycle -------------------------------------------------------------------------------
    def update(
        self,
        state: RobotState,
        dt: float,
        period: float | None = None,
        remeasured: list[str] | None = None,
    ) -> Commands:
        """Run every active controller; merge commands (claims guarantee no overlap).

        ``period``: the loop's period. A cycle that comes more than ``PAUSE_CYCLES`` periods
        after the last (a rebuild, a rediscovery, a failed rejoin, a stalled host) shifts the
        time base of every timed motion by the excess (``shift_time``): during the pause the
        segments sat at their last setpoint, so the path continues from there, without a step;
        the goal's time tolerance window is shifted with it. The controllers then integrate
        one period for that cycle, not the pause (a cFFC would step by the whole pause's rate).

        ``remeasured``: bendables measured again after a gap (the HWI's ``first_measured``):
        every active controller re-anchors them (``adopt_measured``) after the pause is taken
        out of the time base, so a goal compares them with where its path stands now that the
        loop runs again, not with where it would have run on to during the pause."""
        if period is not None and period > 0 and dt > PAUSE_CYCLES * period:
            for c in self.controllers.values():
                shift = getattr(c, "shift_time", None)
                if c.active and shift is not None:
                    shift(dt - period)
            dt = period  # the pause is out of the time base: no controller integrates over it
        if remeasured:
            for c in self.controllers.values():
                if c.active:
                    c.adopt_measured(list(remeasured), state)
        self.t_last = state.t
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
