"""cJTC: the continuum joint trajectory controller.

Takes segment-wise waypoints (kappa, phi per bendable at a time from start), and up-samples them
into a smooth motion in the curvature-vector plane (kx, ky) — never in phi, so a path through
straight does not whip the bending plane around.

Path: piecewise quintic Hermite per bendable and axis. Waypoint velocities are the mean of the
neighbouring chord slopes (zero where a component reverses, and zero at the goal), accelerations at
waypoints are zero, so position, velocity and acceleration are continuous. The first piece starts
from the controller's current desired position, velocity and acceleration: a replacement goal
continues without a jump. A bendable no point names holds; one that was moving stops as a cancel
stops it (``_stop_ramp``), never runs on and comes back.

Limits (decided here, documented in docs/controllers.md):
- a waypoint with kappa > kappa_max (or phi outside a restricted phi range) rejects the whole goal
  with a reason naming the waypoint and the bendable; between waypoints the sampled command is
  clamped radially onto |kappa| <= kappa_max (the spline may bulge slightly near the boundary),
  and a path whose samples leave a restricted phi range rejects the goal (bendable, time, phi).
- the rate |d(kx, ky)/dt| is kept <= ``rate_margin`` * kappa_rate_max by stretching the time of the
  pieces that would exceed it (retiming); the status reports the new duration.
Tolerances (1/m, Euclidean in (kx, ky)): ``path_tolerance`` while moving (0 disables), and
``goal_tolerance`` within ``goal_time_tolerance`` s after the end; a segment measured again after a
gap is judged by the one that applies to it there (``adopt_measured``). A violation aborts the goal
with a reason and holds the measured position. A pause of the loop (a rebuild, a rediscovery)
shifts the time base of the running motion by the pause (``shift_time``), so a path continues
where the segments sat, and the goal's time tolerance window is not spent during the pause.

One piece: the desired motion (path, lead-in, hold, generation) and the goal's lifecycle and
tolerance checks change together under one invariant, no jump in the command, so they stay in
one class.
"""

from __future__ import annotations

import itertools
import math
import time
import uuid
from collections import OrderedDict
from typing import Any

import numpy as np

from host.controllers.base import (
    Commands,
    Controller,
    ControllerContext,
    ControllerError,
    RobotState,
    clamp_radial,
)
from host.controllers.trajectory import (
    TERMINAL_STATES,
    CurvatureTrajectory,
    Goal,
    GoalStart,
    StaleGoalError,
    quintic_coeffs,
)
from host.controllers.waypoints import Knots, distinct, parse_waypoints

__all__ = [
    "CurvatureTrajectory",
    "Goal",
    "GoalStart",
    "JointTrajectoryController",
    "StaleGoalError",
    "quintic_coeffs",
]


class JointTrajectoryController(Controller):
    """cJTC. Parameters (daemon config ``params``), SI units:

    joints (list, default all bendables), path_tolerance (1/m, 0.5; 0 = off), goal_tolerance (1/m,
    0.05), goal_time_tolerance (s, 2.0), rate_margin (fraction of kappa_rate_max used, 0.95),
    stop_time (s, 0.3: deceleration on cancel/preemption).
    """

    type_name = "jtc"
    defaults = {
        **Controller.defaults,
        "path_tolerance": 0.5,
        "goal_tolerance": 0.05,
        "goal_time_tolerance": 2.0,
        "rate_margin": 0.95,
        "stop_time": 0.3,
    }

    @classmethod
    def parse_params(cls, name: str, params: dict[str, Any]) -> dict[str, Any]:
        p = super().parse_params(name, params)
        num = cls.number_param
        p["path_tolerance"] = num(name, p, "path_tolerance")
        p["goal_tolerance"] = num(name, p, "goal_tolerance", lo=1e-6)
        p["goal_time_tolerance"] = num(name, p, "goal_time_tolerance")
        p["rate_margin"] = num(name, p, "rate_margin", lo=0.05, hi=1.0)
        p["stop_time"] = num(name, p, "stop_time", lo=0.01)
        return p

    def __init__(self, name: str, params: dict[str, Any], ctx: ControllerContext):
        super().__init__(name, params, ctx)
        self.path_tolerance = self.params["path_tolerance"]
        self.goal_tolerance = self.params["goal_tolerance"]
        self.goal_time_tolerance = self.params["goal_time_tolerance"]
        self.rate_margin = self.params["rate_margin"]
        self.stop_time = self.params["stop_time"]
        lim = [ctx.limits[j] for j in self.joints]
        self._kmax = np.array([b.kappa_max for b in lim])
        self._kmax_list = self._kmax.tolist()
        self._rate = np.array([b.kappa_rate_max for b in lim]) * self.rate_margin
        self._index = {j: i for i, j in enumerate(self.joints)}
        self._state_index: list[int] = [ctx.names.index(j) for j in self.joints]
        J = len(self.joints)
        self._traj: CurvatureTrajectory | None = None
        # the motion that runs until ``_traj.t0`` (a goal installed ahead of its start); None = hold
        self._lead_in: CurvatureTrajectory | None = None
        self._generation = 0  # bumped whenever the desired motion changes (stale-goal check)
        self._hold = np.zeros((J, 2))
        self._goal: Goal | None = None
        self._goals: OrderedDict[str, Goal] = OrderedDict()
        self._last_state: RobotState | None = None
        self._clamped = 0
        self._counter = itertools.count(1)

    # -- lifecycle ---------------------------------------------------------------------------
    def on_activate(self, state: RobotState) -> None:
        """Hold the measured position: activation never moves the robot."""
        self._hold = self._measured(state, fallback=self._hold)
        self._set_motion(None)
        self._last_state = state
        self.active = True

    def adopt_measured(self, names: list[str], state: RobotState) -> None:
        """Bendables measured again after a gap in their states (or for the first time): their
        command restarts from where they are measured. A running goal keeps them only if its
        path is near every such measurement now (taking them back is then no jump): within
        ``path_tolerance`` of a segment the path still moves (the tracking error it allows
        anyway; a stall pauses a goal mid-motion), within ``goal_tolerance`` of one it holds
        still or after its end (and when ``path_tolerance`` is 0). Otherwise it is aborted
        (cause ``link_loss``) and they hold where measured. The caller takes a loop pause out
        of the time base first (``ControllerManager.update``).
        """
        idx = [self._index[n] for n in names if n in self._index]
        if not idx:
            return
        hold = self._desired_now(state.t)[0]
        dev, tols = {}, {}
        moving = self._moving_now(state.t)
        for i in idx:
            si = self._state_index[i]
            j = self.joints[i]
            dev[j] = math.hypot(state.kx[si] - hold[i][0], state.ky[si] - hold[i][1])
            path_tol = self.path_tolerance > 0 and j in moving
            tols[j] = self.path_tolerance if path_tol else self.goal_tolerance
        if self._goal is not None:
            over = {j: d for j, d in dev.items() if d > tols[j]}
            if not over:
                return  # the path passes near where they are: the goal takes them on
            worst = max(over, key=over.get)
            tol = tols[worst]
            err_txt, tol_txt = distinct(dev[worst], tol)  # never "0.050 > 0.050"
            self._goal.finish(
                "aborted",
                f"link loss: {worst} measured again after a gap in its states, "
                f"{err_txt} 1/m from the goal's path (> tolerance {tol_txt} 1/m); "
                "held where measured",
                cause="link_loss",
                segment=worst,
                error=dev[worst],
                tolerance=tol,
            )
            self._goal = None
        for i in idx:
            si = self._state_index[i]
            hold[i] = (state.kx[si], state.ky[si])
        self._hold = hold
        self._set_motion(None)

    def _moving_now(self, t: float) -> set[str]:
        """The joints the running goal's path still moves at ``t`` (none after its end)."""
        tr = self._goal.trajectory if self._goal is not None else None
        if tr is None or t - tr.t0 >= tr.duration:
            return set()
        return tr.moving(list(self.joints), t)

    def on_deactivate(self, reason: str = "") -> None:
        if self._goal is not None:
            self._goal.finish("aborted", reason or f"controller {self.name!r} deactivated")
            self._goal = None
        self._set_motion(None)
        self.active = False

    # -- requests (called under the daemon lock) ----------------------------------------------
    def parse_points(
        self, points: Any, current: np.ndarray | None = None
    ) -> list[tuple[float, np.ndarray]]:
        """Validate waypoints and turn them into knots (time, (J, 2) curvature vectors).

        Each point: ``{"time_from_start": s, "segments": {name: {"kappa": 1/m, "phi": rad}}}``
        (``kx``/``ky`` instead of kappa/phi also accepted). A bendable absent from a point keeps
        its value from the previous point (or ``current``, default its current desired value).
        Raises ControllerError. Reads only immutable configuration when ``current`` is given, so
        it may run outside the daemon lock.
        """
        if current is None:
            current = self._desired_now()[0]
        return parse_waypoints(points, current, self.joints, self.ctx.limits, self.name)

    def send_goal(self, points: Any, now: float | None = None) -> Goal:
        """Accept (or reject with ControllerError) a trajectory; it replaces a running one.

        The new path starts at ``now`` from the current desired position/velocity/acceleration.
        (The daemon uses the three steps below instead, so that the build runs outside its lock.)
        """
        now = time.monotonic() if now is None else now
        start = self.goal_snapshot(now)
        goal, traj = self.build_goal(points, start)
        return self.install_goal(goal, traj, start, now)

    def goal_snapshot(self, t_start: float) -> GoalStart:
        """Step 1, under the daemon lock: the desired motion a new goal starts from at
        ``t_start`` (s, monotonic; may lie in the future: the old motion runs until then)."""
        if not self.active:
            raise ControllerError(f"controller {self.name!r} is not active")
        if not self.joints:
            raise ControllerError(f"controller {self.name!r} commands no bendable")
        p, v, a = self._desired_now(t_start)
        at_rest = not np.any(v) and not np.any(a)
        return GoalStart(t_start, p, v, a, self._generation, at_rest)

    def build_goal(self, points: Any, start: GoalStart) -> tuple[Goal, CurvatureTrajectory]:
        """Step 2, outside the lock: parse and retime (the slow part). Touches no mutable state
        of the controller. Raises ControllerError with the reason for a bad goal."""
        knots = self.parse_points(points, current=start.p)
        p0, v0, a0 = start.p, start.v, start.a
        # a bendable no point names that is moving stops as a cancel stops it (``_stop``), and
        # holds there: the pieces would carry it on and bring it back to where it was
        stopping = [
            i
            for i in range(len(self.joints))
            if i not in knots.named and (np.any(v0[i]) or np.any(a0[i]))
        ]
        ramp = None
        if stopping:
            ramp, end = self._stop_ramp(0.0, p0, v0, a0, stopping)
            p0, v0, a0 = p0.copy(), v0.copy(), a0.copy()
            positions = np.array(knots.positions, dtype=float, copy=True)
            for i in stopping:
                p0[i], v0[i], a0[i] = end[i], 0.0, 0.0
                positions[:, i] = end[i]
            knots = Knots(knots.times, positions, knots.named)
        traj = CurvatureTrajectory(start.t_start, p0, v0, a0, knots, self._rate)
        if ramp is not None:
            traj.with_stops(ramp, stopping)
        self._check_phi_range(traj, set(stopping))
        goal = Goal(
            f"{self.name}-{next(self._counter)}-{uuid.uuid4().hex[:6]}", self.name, len(knots)
        )
        return goal, traj

    def _check_phi_range(self, traj: CurvatureTrajectory, skip: set[int]) -> None:
        """Reject a path that leaves a restricted phi range between its waypoints (the waypoints
        alone are checked by ``parse_waypoints``): from phi = 120 deg to -120 deg in a range
        [-135, 135] deg the straight chord in (kx, ky) crosses phi = 180 deg, and the bending
        plane would flip from one bound to the other in one cycle. ``skip``: columns that only
        stop (a bendable the goal does not name)."""
        ranges = {
            i: (b.phi_min, b.phi_max)
            for i, b in enumerate(self.ctx.limits[j] for j in self.joints)
            if not b.full_circle and i not in skip
        }
        hit = traj.phi_leaves(ranges)
        if hit is None:
            return
        i, t, phi = hit
        lo, hi = ranges[i]
        raise ControllerError(
            f"trajectory: the path of {self.joints[i]} leaves its phi range "
            f"[{lo:.4g}, {hi:.4g}] rad ([{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg) "
            f"between waypoints: phi {phi:.4g} rad ({math.degrees(phi):.1f} deg) at t = "
            f"{t:.3f} s (goal rejected; nothing moved). Add a waypoint that goes round "
            "inside the range, or through straight (kappa 0)"
        )

    def install_goal(
        self, goal: Goal, traj: CurvatureTrajectory, start: GoalStart, now: float
    ) -> Goal:
        """Step 3, under the lock: make the goal run. Raises StaleGoalError when the motion it
        was built from changed meanwhile, or when ``now`` is past its planned start while the
        old motion was moving (the new path would begin with a jump)."""
        if not self.active:
            raise ControllerError(f"controller {self.name!r} is not active")
        if start.generation != self._generation:
            raise StaleGoalError(
                f"controller {self.name!r} changed its motion while the goal was being built"
            )
        lead_in = self._traj  # the old motion runs until the new path begins
        if start.at_rest:
            p, v, a = self._desired_now(now)
            if not np.any(v) and not np.any(a) and np.allclose(p, start.p, rtol=0.0, atol=1e-12):
                # Holding still from now on: the new path may begin at once.
                traj.t0 = now
                lead_in = None
                self._hold = p
        if lead_in is not None and now > start.t_start:
            raise StaleGoalError(
                f"building the goal took {now - start.t_start:.3f} s longer than planned"
            )
        goal.trajectory = traj
        goal.t_accepted = now
        goal.state = "executing"
        if self._goal is not None:
            self._goal.finish("aborted", f"replaced by goal {goal.id}", cause="replaced")
        self._goal = goal
        self._set_motion(traj, lead_in=lead_in)
        self._remember(goal)
        return goal

    def cancel(
        self,
        goal_id: str,
        now: float | None = None,
        reason: str = "canceled by caller",
        state: str = "canceled",
        cause: str | None = None,
        segment: str | None = None,
    ) -> bool:
        """Stop the goal (decelerating over ``stop_time``); False if it was not running."""
        g = self._goals.get(goal_id)
        if g is None:
            raise ControllerError(f"unknown goal id {goal_id!r}")
        if g is not self._goal or g.state in TERMINAL_STATES:
            return False
        g.finish(state, reason, cause=cause, segment=segment)
        self._goal = None
        self._stop(time.monotonic() if now is None else now)
        return True

    def abort_active(
        self,
        reason: str,
        now: float | None = None,
        cause: str | None = None,
        segment: str | None = None,
    ) -> str | None:
        """Abort the running goal (e.g. arbitration or topology change); returns its id.
        ``cause``: one of ``ABORT_CAUSES`` (default: inferred from ``reason``)."""
        if self._goal is None:
            return None
        gid = self._goal.id
        self.cancel(gid, now, reason, state="aborted", cause=cause, segment=segment)
        return gid

    def status_of(self, goal_id: str) -> dict[str, Any]:
        g = self._goals.get(goal_id)
        if g is None:
            raise ControllerError(f"unknown goal id {goal_id!r}")
        return g.status()

    def has_goal(self, goal_id: str) -> bool:
        return goal_id in self._goals

    @property
    def current_goal(self) -> Goal | None:
        return self._goal

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d["goal"] = self._goal.id if self._goal else None
        d["clamped_samples"] = self._clamped
        return d

    # -- cycle -------------------------------------------------------------------------------
    def update(self, state: RobotState, dt: float) -> Commands | None:
        self._last_state = state
        t = state.t
        tr = self._traj_at(t)
        p = tr.position(t) if tr is not None else self._hold.tolist()
        g = self._goal
        if g is not None:
            self._check_goal(g, state, p, t)
            if self._goal is None and g.state == "aborted":
                p = self._hold.tolist()  # held at the measured position by _check_goal
        out: Commands = {}
        kmax = self._kmax_list
        for i, j in enumerate(self.joints):
            kx, ky, clamped = clamp_radial(p[i][0], p[i][1], kmax[i])
            self._clamped += clamped
            out[j] = (kx, ky)
        return out

    def shift_time(self, pause: float) -> None:
        """The loop paused ``pause`` s beyond its period (the segments sat at their last
        setpoint): the running motion (path, lead-in, stop ramp) continues from where it was,
        its time base and the goal's time tolerance window shifted by the pause."""
        if pause <= 0.0 or (self._traj is None and self._lead_in is None):
            return
        for tr in {id(t): t for t in (self._traj, self._lead_in) if t is not None}.values():
            tr.t0 += pause
        self._generation += 1  # a goal built from the unshifted motion would begin with a jump

    # -- internals ---------------------------------------------------------------------------
    def _check_goal(self, g: Goal, state: RobotState, desired: list[list[float]], t: float) -> None:
        tr = g.trajectory
        assert tr is not None
        tau = t - tr.t0
        g.progress = min(1.0, max(0.0, tau / tr.duration))
        errs: dict[str, float] = {}
        for i, j in enumerate(self.joints):
            si = self._state_index[i]
            if state.valid[si]:
                errs[j] = math.hypot(state.kx[si] - desired[i][0], state.ky[si] - desired[i][1])
        if tau < tr.duration:
            if errs:
                worst = max(errs, key=errs.get)
                g.max_error = max(g.max_error, errs[worst])
                if self.path_tolerance > 0 and errs[worst] > self.path_tolerance:
                    err_txt, tol_txt = distinct(errs[worst], self.path_tolerance)
                    self._abort_holding(
                        g,
                        state,
                        desired,
                        f"path tolerance violated on {worst}: error {err_txt} 1/m > "
                        f"tolerance {tol_txt} 1/m at t = {tau:.2f} s",
                        cause="path_tolerance",
                        segment=worst,
                        error=errs[worst],
                        tolerance=self.path_tolerance,
                    )
            return
        g.final_error = {k: round(v, 5) for k, v in errs.items()}
        if len(errs) == len(self.joints) and all(e <= self.goal_tolerance for e in errs.values()):
            g.finish("succeeded")
            self._goal = None
            return
        if tau <= tr.duration + self.goal_time_tolerance:
            return
        over = {k: e for k, e in errs.items() if e > self.goal_tolerance}
        unseen = [j for j in self.joints if j not in errs]
        if over:
            worst = max(over, key=over.get)
            err_txt, tol_txt = distinct(over[worst], self.goal_tolerance)
            self._abort_holding(
                g,
                state,
                desired,
                f"goal tolerance not reached {self.goal_time_tolerance:.2f} s after the end: "
                f"{worst} error {err_txt} 1/m > tolerance {tol_txt} 1/m",
                cause="goal_tolerance",
                segment=worst,
                error=over[worst],
                tolerance=self.goal_tolerance,
            )
        else:  # every measured segment is within tolerance: the others sent no valid state
            self._abort_holding(
                g,
                state,
                desired,
                f"link loss: no valid state from {', '.join(unseen)} "
                f"{self.goal_time_tolerance:.2f} s after the end, so the goal tolerance "
                f"({self.goal_tolerance:g} 1/m) could not be checked",
                cause="link_loss",
                segment=unseen[0],
                tolerance=self.goal_tolerance,
            )

    def _abort_holding(
        self, g: Goal, state: RobotState, desired: Any, reason: str, **detail: Any
    ) -> None:
        """Abort ``g`` and hold the measured position (the desired one where unmeasured)."""
        g.finish("aborted", reason, **detail)
        self._goal = None
        # held where measured now; a segment whose state is stale holds its desired position
        # (never a target computed from a measurement the host no longer sees)
        self._hold = self._measured(state, fallback=desired, fresh_only=True)
        self._set_motion(None)

    def _set_motion(
        self, traj: CurvatureTrajectory | None, lead_in: CurvatureTrajectory | None = None
    ) -> None:
        """Replace the desired motion (None = hold ``_hold``); goals built before are stale."""
        self._traj = traj
        self._lead_in = lead_in
        self._generation += 1

    def lead_in_at(self, t: float) -> CurvatureTrajectory | None:
        """The old motion that still runs at ``t`` because the current path begins later (a
        goal built outside the lock, installed ahead of its start); None once it began."""
        tr = self._traj
        if tr is not None and t < tr.t0 and self._lead_in is not tr:
            return self._lead_in
        return None

    def run_lead_in(self, lead_in: CurvatureTrajectory) -> None:
        """Run ``lead_in`` (a carried goal's old motion, mapped onto these joints) as the
        desired motion; the goal installed next begins where it ends (``install_goal``)."""
        if not self.active:
            raise ControllerError(f"controller {self.name!r} is not active")
        self._set_motion(lead_in)

    def _traj_at(self, t: float) -> CurvatureTrajectory | None:
        """The trajectory that defines the desired motion at ``t`` (None = hold)."""
        tr = self._traj
        if tr is not None and t < tr.t0 and self._lead_in is not tr:
            return self._lead_in
        return tr

    def _desired_now(self, now: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = time.monotonic() if now is None else now
        tr = self._traj_at(t)
        if tr is None:
            z = np.zeros_like(self._hold)
            return self._hold.copy(), z, z.copy()
        return tr.sample(t)

    def _stop(self, now: float) -> None:
        """Decelerate from the current desired motion to rest over ``stop_time`` s."""
        p, v, a = self._desired_now(now)
        if np.allclose(v, 0.0) and np.allclose(a, 0.0):
            self._hold = p
            self._set_motion(None)
            return
        ramp, end = self._stop_ramp(now, p, v, a)
        self._hold = end
        self._set_motion(ramp)

    def _stop_ramp(
        self,
        t0: float,
        p: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        cols: list[int] | None = None,
    ) -> tuple[CurvatureTrajectory, np.ndarray]:
        """The stop rule (cancel, preemption, a bendable a new goal leaves out): from ``p``,
        ``v``, ``a`` at ``t0`` to rest at ``p + v * stop_time / 2`` (clamped onto kappa_max)
        over ``stop_time`` s. ``cols``: only those bendables stop; the others hold at ``p``.
        Reads only configuration (safe outside the daemon lock). Returns (ramp, end)."""
        if cols is not None:
            keep = np.ones(len(self.joints), dtype=bool)
            keep[cols] = False
            v, a = v.copy(), a.copy()
            v[keep], a[keep] = 0.0, 0.0
        end = p + v * self.stop_time / 2.0
        for i in range(len(self.joints)):
            end[i, 0], end[i, 1], _ = clamp_radial(end[i, 0], end[i, 1], self._kmax[i])
        return CurvatureTrajectory(t0, p, v, a, [(self.stop_time, end)], self._rate / 0.95), end

    def _measured(
        self, state: RobotState, fallback: np.ndarray, fresh_only: bool = False
    ) -> np.ndarray:
        out = np.array(fallback, dtype=float, copy=True)
        if out.shape != (len(self.joints), 2):
            out = np.zeros((len(self.joints), 2))
        for i in range(len(self.joints)):
            si = self._state_index[i]
            # fresh or last known (never measured: keep ``fallback``); ``fresh_only``: fresh
            ok = state.valid[si] if fresh_only else state.has_value(si)
            if ok:
                out[i] = (state.kx[si], state.ky[si])
        return out

    def _remember(self, goal: Goal) -> None:
        self._goals[goal.id] = goal
        while len(self._goals) > 200:
            old_id, old = next(iter(self._goals.items()))
            if old is self._goal:
                break
            del self._goals[old_id]
