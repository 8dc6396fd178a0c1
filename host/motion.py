"""Motion: the controllers that move the robot, the goals they run, and arbitration between
sources (a trajectory, a stick taking over, a hand-back).

Owns the :class:`ControllerManager`, the :class:`Arbitrator`, the goal book (goal id → goal,
kept across rebuilds) and the last :class:`RobotState` the loop measured. Every method takes the
shared daemon lock; the loop calls :meth:`update` once per cycle, the topology follower calls
:meth:`build` / :meth:`abort_goals` on a rebuild, the facade calls the rest for the API.

``ready()`` (given by the daemon) raises :class:`DaemonError` while the chain is not usable.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from host.arbitration import Arbitrator
from host.config import DaemonConfig
from host.controller_manager import ControllerManager, SwitchError
from host.controllers.base import ControllerContext, ControllerError, RobotState, sender_of
from host.controllers.jtc import StaleGoalError
from host.errors import DaemonError, GoalNotFound
from host.hwi import HardwareInterface

log = logging.getLogger("ucr.daemon")

_MAX_GOALS = 500  # goals remembered for trajectory_status (oldest forgotten first)
#: Waypoints one event carries at most: a longer goal's waypoints continue in ``goal_waypoints``
#: events. Small enough that encoding one event (tens of KB of JSON, one C call holding the
#: interpreter lock) stays near a millisecond beside the control loop.
EVENT_MAX_WAYPOINTS = 500


def commanded(goal_id: str, controller: str, joints: list[str], traj: Any) -> list[dict[str, Any]]:
    """The fields of the events that publish a goal's waypoints as requested (before any
    retiming), every bendable of the controller filled in: first ``goal_accepted`` (``goal``,
    ``controller``, ``joints``, ``retimed``, ``waypoint_count``, ``parts``, ``part`` = 1 and
    ``waypoints`` = [[time_from_start s, [[kx, ky] 1/m per joint]], ...], at most
    EVENT_MAX_WAYPOINTS of them), then one ``goal_waypoints`` (``goal``, ``part`` = 2 ..
    ``parts``, ``parts``, ``waypoints``) per further EVENT_MAX_WAYPOINTS waypoints, in order."""
    times = traj.requested_durations.cumsum()
    pos = traj.positions[1:]
    m, n = len(times), EVENT_MAX_WAYPOINTS
    chunks = []
    for lo in range(0, max(m, 1), n):  # piece by piece: no long C call converting the whole goal
        ts = times[lo : lo + n].round(6).tolist()
        ps = pos[lo : lo + n].round(6).tolist()
        chunks.append([[t, p] for t, p in zip(ts, ps, strict=True)])
    head: dict[str, Any] = {"goal": goal_id, "controller": controller, "joints": list(joints),
                            "retimed": bool(traj.retimed), "waypoint_count": m,
                            "parts": len(chunks), "part": 1, "waypoints": chunks[0]}  # fmt: skip
    rest = [
        {"goal": goal_id, "part": k, "parts": len(chunks), "waypoints": c}
        for k, c in enumerate(chunks[1:], start=2)
    ]
    return [head, *rest]


class Motion:
    """Controllers, goals and arbitration; ``emit_event(event, message, **fields)`` reports."""

    def __init__(
        self,
        cfg: DaemonConfig,
        lock: threading.RLock,
        emit_event: Callable[..., None],
        ready: Callable[[], None],
        period: float,
    ):
        self.cfg = cfg
        self.lock = lock
        self._emit = emit_event
        self._ready = ready
        self.period = period
        self.cm: ControllerManager | None = None
        self.arb = Arbitrator()
        # goal id -> (Goal, controller name); kept across rebuilds, which recreate controllers
        self._goals: OrderedDict[str, tuple[Any, str]] = OrderedDict()
        self.state = RobotState.zeros([])
        self._t_last = time.monotonic()

    # -- called by the topology follower and the loop ----------------------------------------
    def build(
        self,
        ctx: ControllerContext,
        state: RobotState,
        reason: str,
        *,
        cause: str = "stopped",
        segment: str | None = None,
        affected: set[str] | None = None,
    ) -> list[str]:
        """Controllers for a new HWI (caller holds the lock): built once, then rebuilt, holding
        the measured ``state``; a manual takeover outlives a rebuild. A goal that moves none of
        the ``affected`` segments runs on (``None``: every goal ends); the others are aborted
        with ``reason``, ``cause`` and ``segment``. Returns the ids of the goals aborted."""
        self.state = state
        if self.cm is None:
            cm = ControllerManager(self.cfg.controllers, ctx)
            try:
                cm.switch(self.cfg.active, [], state, reason)
            except SwitchError as exc:
                raise DaemonError(f"{self.cfg.source}: active: {exc}") from None
            self.cm = cm  # only once it runs: a retried start() builds it afresh
            return []
        self.cm.rebuild(ctx, state, reason, cause=cause, segment=segment, affected=affected)
        self.arb.prune(self.cm)
        return list(self.cm.last_aborted)

    def update(self, hwi: HardwareInterface, state: RobotState, now: float) -> None:
        """One control update: active controllers → the HWI's command interfaces."""
        with self.lock:
            dt = now - self._t_last if self._t_last else self.period
            self._t_last = now
            self.state = state
            # a pause shifts timed motions, then the controllers re-anchor segments measured
            # again after a gap (in that order: a stall must not abort the goal it paused)
            cmds = self.cm.update(state, dt, self.period, remeasured=hwi.first_measured)
            for name, (kx, ky) in cmds.items():
                if name in hwi.limits:
                    hwi.set_curvature(name, kx, ky)

    def rehold(self, state: RobotState, msg: str, segments: list[str] | None = None) -> None:
        """Segments held on their own: abort goals, controllers hold the measured state."""
        with self.lock:
            segment = (segments or [None])[0]
            self.abort_goals(msg, "segment_fault", segment)
            self.cm.rebuild(self.cm.ctx, state, msg, cause="segment_fault", segment=segment)

    def abort_goals(
        self,
        reason: str,
        cause: str | None = None,
        segment: str | None = None,
        only: set[str] | None = None,
    ) -> list[str]:
        """Abort the running goal of every active controller; returns their ids. ``cause``:
        one of ``host.controllers.trajectory.ABORT_CAUSES`` (default: inferred from the reason);
        ``segment``: the segment it concerns, if one; ``only``: abort only the goals that move
        one of these segments (a topology change elsewhere leaves the others running)."""
        out = []
        now = time.monotonic()
        with self.lock:
            if self.cm is None:
                return out
            for c in self.cm.controllers.values():
                abort = getattr(c, "abort_active", None)
                if not c.active or abort is None:
                    continue
                if only is not None:
                    tr = getattr(getattr(c, "current_goal", None), "trajectory", None)
                    if tr is not None and not tr.moving(list(c.joints), now) & set(only):
                        continue
                gid = abort(reason, cause=cause, segment=segment)
                if gid:
                    out.append(gid)
        return out

    # -- read by the facade ------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Active controllers, running goals, manual takeovers (caller holds the lock)."""
        active = self.cm.active_names() if self.cm else []
        goals = []
        if self.cm:
            for c in self.cm.controllers.values():
                g = getattr(c, "current_goal", None)
                if g is not None:
                    goals.append(g.id)
        return {
            "active_controllers": active,
            "running_goals": goals,
            "manual_control": sorted(self.arb.takeovers),
        }

    def controllers(self) -> list[dict[str, Any]]:
        """Every configured controller: type, state, claimed interfaces, goal."""
        with self.lock:
            return self.cm.describe() if self.cm else []

    # -- API actions -------------------------------------------------------------------------
    def switch_controllers(self, start: list[str], stop: list[str]) -> dict[str, Any]:
        with self.lock:
            self._ready()
            res = self.cm.switch(start, stop, self.state)
            self.arb.note_switch(res["started"], res["stopped"])
        self._emit(
            "controllers_switched",
            message=f"started {res['started']}, stopped {res['stopped']}",
            **res,
        )
        return res

    def send_trajectory(
        self, points: list[dict], controller: str | None = None, source: Any = None
    ) -> str:
        """Start a trajectory on a cJTC; see :meth:`host.daemon.Daemon.send_trajectory`."""
        lead = 0.05 + 2e-4 * (len(points) if isinstance(points, list | tuple) else 0)
        accepted = ""
        for attempt in range(2):
            with self.lock:
                self._ready()
                ctrl = self._jtc(controller)
                if not ctrl.active:
                    manual = self.arb.blocking_manual(self.cm, ctrl.name)
                    if manual and manual in self.arb.takeovers:
                        raise ControllerError(
                            f"manual control by {manual!r} is active; hand back first "
                            "(`ucr controllers hand-back`, API controllers.hand_back)"
                        )
                    if manual:
                        raise ControllerError(
                            f"{manual!r} was switched on and holds the interfaces; switch "
                            f"back first (`ucr controllers switch --start {ctrl.name} --stop "
                            f"{manual}`, API controllers.switch)"
                        )
                    raise ControllerError(f"controller {ctrl.name!r} is not active")
                t_build = time.monotonic()
                start = ctrl.goal_snapshot(t_build + lead)
            goal, traj = ctrl.build_goal(points, start)  # the slow part, lock not held
            goal.sender = sender_of(source)
            built_s = time.monotonic() - t_build
            with self.lock:
                self._ready()
                current = self.cm.controllers.get(ctrl.name)
                if current is not ctrl or not ctrl.active:
                    why = f"controller {ctrl.name!r} was switched or rebuilt while it was built"
                else:
                    try:
                        ctrl.install_goal(goal, traj, start, time.monotonic())
                    except StaleGoalError as exc:
                        why = str(exc)
                    else:
                        self._goals[goal.id] = (goal, ctrl.name)
                        while len(self._goals) > _MAX_GOALS:
                            self._goals.popitem(last=False)
                        accepted = goal.id
            if accepted:  # outside the lock: recorders keep what was commanded
                head, *rest = commanded(accepted, ctrl.name, ctrl.joints, traj)
                self._emit(
                    "goal_accepted", message=f"goal {accepted}: {goal.n_points} waypoints", **head
                )
                for part in rest:
                    self._emit(
                        "goal_waypoints",
                        message=f"goal {accepted}: waypoints, part {part['part']} of "
                        f"{part['parts']}",
                        **part,
                    )
                return accepted
            log.info("trajectory goal built again (attempt %d): %s", attempt + 1, why)
            lead = 2.0 * built_s + 0.05
        raise ControllerError(f"trajectory not started: {why}; send it again")

    def _jtc(self, controller: str | None) -> Any:
        if controller is not None:
            c = self.cm.get(controller)
            if not hasattr(c, "send_goal"):
                raise ControllerError(
                    f"controller {controller!r} ({c.type_name}) does not take trajectories"
                )
            return c
        cands = [c for c in self.cm.controllers.values() if hasattr(c, "send_goal")]
        if not cands:
            raise ControllerError("no trajectory controller (type jtc) is configured")
        active = [c for c in cands if c.active]
        return (active or cands)[0]

    def trajectory_status(self, goal_id: str) -> dict[str, Any]:
        with self.lock:
            return self._goal(goal_id)[0].status()

    def cancel_trajectory(self, goal_id: str) -> dict[str, Any]:
        with self.lock:
            goal, name = self._goal(goal_id)
            ctrl = self.cm.controllers.get(name)
            canceled = False
            if ctrl is not None and ctrl.has_goal(goal.id):
                canceled = ctrl.cancel(goal.id, time.monotonic())
            return {**goal.status(), "canceled": canceled}

    def _goal(self, goal_id: str) -> tuple[Any, str]:
        entry = self._goals.get(str(goal_id))
        if entry is None:
            raise GoalNotFound(f"unknown goal id {goal_id!r}")
        return entry

    def ffc_input(self, rates: dict[str, Any], source: Any = None) -> dict[str, Any]:
        with self.lock:
            self._ready()
            ffcs = self.cm.of_type("ffc")
            if not ffcs:
                raise ControllerError("no cFFC (type ffc) is configured")
            ctrl = next((c for c in ffcs if c.active), ffcs[0])
            parsed = ctrl.validate_input(rates)
            deflected = ctrl.has_deflection(parsed, ctrl.deadzone)
            takeover = self.arb.manual_input(self.cm, ctrl.name, deflected, self.state)
            if not ctrl.active:
                return {
                    "accepted": False,
                    "controller": ctrl.name,
                    "takeover": None,
                    "reason": f"{ctrl.name!r} is inactive and the input is in the deadzone",
                }
            ctrl.set_input(parsed, time.monotonic(), source)
            setpoint = ctrl.setpoint()  # where this input starts from (it integrates next cycle)
        if takeover:
            self._emit(
                "manual_takeover",
                message=f"{ctrl.name!r} took over from {takeover['preempted']}",
                **{k: v for k, v in takeover.items() if k not in ("t", "event")},
            )
        return {
            "accepted": True,
            "controller": ctrl.name,
            "takeover": takeover,
            "setpoint": setpoint,
        }

    def hand_back(self, manual: str | None = None) -> dict[str, Any]:
        with self.lock:
            self._ready()
            if manual is None:
                if not self.arb.takeovers:
                    raise ControllerError("no manual takeover to hand back")
                manual = next(iter(self.arb.takeovers))
            elif manual not in self.arb.takeovers:
                # only a takeover is handed back: naming another controller must not stop it
                held = ", ".join(repr(m) for m in self.arb.takeovers) or "none"
                raise ControllerError(
                    f"{manual!r} holds no manual takeover to hand back (takeovers: {held}); "
                    "to stop a controller use `ucr controllers switch --stop NAME`"
                )
            rec = self.arb.hand_back(self.cm, manual, self.state)
        self._emit(
            "hand_back",
            message=f"{manual!r} handed back; restarted {rec['restarted']}",
            **{k: v for k, v in rec.items() if k not in ("t", "event")},
        )
        return rec
