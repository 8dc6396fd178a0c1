"""Arbitration between command sources (ACROSET's arbitrator in the User Interface Subsystem).

Policy: a manual source (a cFFC fed by a gamepad or keyboard) takes over from an automatic one (a
cJTC running an application's trajectory) as soon as its stick leaves the deadzone. The automatic
controller's running goal is aborted with a reason naming the manual source, and the controller is
switched off. Control goes back only explicitly (``hand_back`` / ``switch_controllers``); until
then new trajectories are rejected with a reason telling how to hand back. Safety and topology
handling (SMCS) sit beside this path and are never arbitrated.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from host.controller_manager import ControllerManager, SwitchError
from host.controllers.base import RobotState

log = logging.getLogger("ucr.arbitration")

MANUAL_TYPES = ("ffc",)


@dataclass
class Takeover:
    """One manual takeover: who took control, from whom, which goals it aborted."""

    manual: str
    preempted: list[str]
    aborted_goals: list[str] = field(default_factory=list)


class Arbitrator:
    """Decides which source commands the bendables. Called under the daemon lock."""

    def __init__(self, manual_takeover: bool = True):
        self.manual_takeover = manual_takeover
        self.takeovers: dict[str, Takeover] = {}
        self.log: list[dict[str, Any]] = []

    def _record(self, t: float, **kw: Any) -> dict[str, Any]:
        entry = {"t": t, **kw}
        self.log.append(entry)
        del self.log[:-50]
        return entry

    def manual_input(
        self, cm: ControllerManager, manual: str, deflected: bool, state: RobotState
    ) -> dict[str, Any] | None:
        """A manual source sent input. Takes over if it is inactive and the stick is deflected.

        Returns the takeover record (also logged) or None when nothing changed. Raises SwitchError
        when the takeover is not allowed.
        """
        ctrl = cm.get(manual)
        if ctrl.active or not deflected:
            return None
        if not self.manual_takeover:
            raise SwitchError(f"manual controller {manual!r} is inactive and takeover is disabled")
        wanted = set(ctrl.command_interfaces())
        claims = cm.claims()
        victims = sorted({claims[i] for i in wanted if i in claims})
        aborted = []
        reason = f"preempted by manual control ({manual!r})"
        for v in victims:
            abort = getattr(cm.controllers[v], "abort_active", None)
            if abort is not None:
                gid = abort(reason, state.t)
                if gid:
                    aborted.append(gid)
        cm.switch([manual], victims, state, reason)
        self.takeovers[manual] = Takeover(manual, victims, aborted)
        log.info("manual takeover by %s from %s (aborted goals %s)", manual, victims, aborted)
        return self._record(
            state.t, event="takeover", manual=manual, preempted=victims, aborted_goals=aborted
        )

    def hand_back(self, cm: ControllerManager, manual: str, state: RobotState) -> dict[str, Any]:
        """Explicit hand-back: stop the manual controller, restart the ones it preempted."""
        tk = self.takeovers.pop(manual, None)
        restart = [n for n in (tk.preempted if tk else []) if n in cm.controllers]
        cm.switch(restart, [manual], state, f"manual control ({manual!r}) handed back")
        return self._record(state.t, event="hand_back", manual=manual, restarted=restart)

    def note_switch(self, started: list[str], stopped: list[str]) -> None:
        """A switch made through the API ends the takeovers it resolves."""
        for m in list(self.takeovers):
            if m in stopped:
                self.takeovers.pop(m)

    def prune(self, cm: ControllerManager) -> list[str]:
        """After a rebuild: forget the takeovers whose manual controller is no longer active
        (those still active keep control, and hand-back still restarts what they preempted)."""
        gone = [
            m for m in self.takeovers if m not in cm.controllers or not cm.controllers[m].active
        ]
        for m in gone:
            self.takeovers.pop(m)
        return gone

    def blocking_manual(self, cm: ControllerManager, controller: str) -> str | None:
        """Name of an active manual controller holding interfaces ``controller`` needs."""
        need = set(cm.get(controller).command_interfaces())
        for itf, holder in cm.claims().items():
            if itf in need and cm.controllers[holder].type_name in MANUAL_TYPES:
                return holder
        return None
