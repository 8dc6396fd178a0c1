"""The cJTC's path and goal record: piecewise quintic Hermite curves in (kx, ky) per bendable
(:class:`CurvatureTrajectory`, evaluation and retiming to the rate limit), and :class:`Goal`, one
trajectory request and its fate. How waypoints become a path is described in
:mod:`host.controllers.jtc`, which builds and runs them.
"""

from __future__ import annotations

import bisect
import copy
import math
from typing import Any

import numpy as np

from host.controllers.base import ControllerError

_SAMPLES = 33  # samples per piece when checking the rate limit
_BLOCK = (
    2048  # pieces per block in the vectorised rate check (about 8 MB of temporaries at 8 bendables)
)
TERMINAL_STATES = ("succeeded", "aborted", "canceled", "rejected")

# why a goal was aborted (``Goal.abort["cause"]``); docs/controllers.md lists them
ABORT_CAUSES = (
    "path_tolerance",  # a measured segment left the path by more than path_tolerance
    "goal_tolerance",  # not within goal_tolerance goal_time_tolerance s after the end
    "topology_change",  # the chain changed (hot-plug, rejoin)
    "segment_fault",  # a segment holds on its own (watchdog, HOLD, fault)
    "link_loss",  # a segment's states stopped (gap) or the port failed
    "replaced",  # a newer goal or a manual takeover replaced it
    "stopped",  # the controller was deactivated or the daemon stopped
)


def abort_cause(reason: str) -> str:
    """The cause of an abort from the reason the daemon's parts give (first word decides)."""
    r = reason.lower()
    for key, cause in (
        ("topology", "topology_change"),
        ("link lost", "link_loss"),
        ("link loss", "link_loss"),
        ("holding", "segment_fault"),
        ("fault", "segment_fault"),
        ("preempted", "replaced"),
        ("replaced", "replaced"),
    ):
        if key in r:
            return cause
    return "stopped"


def quintic_coeffs(
    p0: np.ndarray,
    v0: np.ndarray,
    a0: np.ndarray,
    p1: np.ndarray,
    v1: np.ndarray,
    a1: np.ndarray,
    T: float,
) -> np.ndarray:
    """Coefficients c0..c5 (last axis) of the quintic with the given boundary values over [0, T]."""
    T2, T3 = T * T, T * T * T
    c3 = (20 * (p1 - p0) - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    c4 = (30 * (p0 - p1) + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T3 * T)
    c5 = (12 * (p1 - p0) - 6 * (v1 + v0) * T - (a0 - a1) * T2) / (2 * T3 * T2)
    return np.stack([p0, v0, a0 / 2.0, c3, c4, c5], axis=-1)


class CurvatureTrajectory:
    """A timed path for J bendables in (kx, ky): knots, piecewise quintics, evaluation.

    ``start`` arrays are (J, 2): position (1/m), velocity (1/m/s), acceleration (1/m/s^2) at
    ``t0``; ``knots`` is a list of (time_from_start s, (J, 2) positions) with increasing times.
    ``rate_max`` (J,) is the allowed |d(kx, ky)/dt| per bendable; pieces are stretched until it
    holds (``retimed`` tells whether that happened).
    """

    def __init__(
        self,
        t0: float,
        p0: np.ndarray,
        v0: np.ndarray,
        a0: np.ndarray,
        knots: list[tuple[float, np.ndarray]],
        rate_max: np.ndarray,
        max_iterations: int = 30,
    ):
        self.t0 = t0
        if hasattr(knots, "positions"):  # waypoints.Knots: arrays already (no loop over points)
            self.positions = np.concatenate([np.asarray(p0, dtype=float)[None], knots.positions])
            times = np.concatenate([[0.0], knots.times])
        else:
            self.positions = np.stack([p0] + [p for _, p in knots])  # (m+1, J, 2)
            times = np.array([0.0] + [t for t, _ in knots])
        self.requested_durations = np.diff(times)
        self.durations = self.requested_durations.astype(float).copy()
        self.v0, self.a0 = v0, a0
        self.rate_max = rate_max
        self.retimed = False
        # columns that follow a stop ramp instead (``with_stops``): (ramp, its end, columns)
        self._stop: CurvatureTrajectory | None = None
        self._stop_end = 0.0
        self._stop_cols: list[int] = []
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            self._retime(max_iterations)  # non-finite values are checked, not warned about
        self.ends = np.cumsum(self.durations).tolist()
        self._end = self.ends[-1]  # the end of the pieces (``duration``: of the stops too)
        self.duration = self._end
        self.final = self.positions[-1]
        self._final_list = self.final.tolist()

    def _retime(self, max_iterations: int) -> None:
        """Stretch the pieces until the rate limit holds (raises ControllerError if the path
        cannot be computed)."""
        for _ in range(max_iterations):
            self._build()
            if not np.isfinite(self.coeffs).all():
                raise ControllerError(
                    "trajectory: the path cannot be computed (non-finite coefficients; are the "
                    "waypoints too close in time?)"
                )
            ratio = self._rate_ratios()
            over = ~(ratio <= 1.0)  # NaN counts as over: never skip retiming on it
            if not over.any():
                break
            self.retimed = True
            finite = np.isfinite(ratio)
            self.durations[over & finite] *= ratio[over & finite] * 1.02
            self.durations[over & ~finite] *= 2.0
        else:
            self._build()  # the coefficients must match the last stretched durations
            if not (np.isfinite(self.coeffs).all() and np.isfinite(self._rate_ratios()).all()):
                raise ControllerError("trajectory: the rate along the path cannot be computed")

    def _build(self) -> None:
        P, d = self.positions, self.durations
        m = len(d)
        V = np.zeros_like(P)
        A = np.zeros_like(P)
        V[0], A[0] = self.v0, self.a0
        if m > 1:
            slopes = (P[1:] - P[:-1]) / d[:, None, None]
            s_in, s_out = slopes[:-1], slopes[1:]
            same = np.sign(s_in) * np.sign(s_out) > 0
            V[1:-1] = np.where(same, 0.5 * (s_in + s_out), 0.0)
        T = d[:, None, None]  # (m, 1, 1): every piece at once (a 10,000-waypoint goal builds in ms)
        self.coeffs = quintic_coeffs(P[:-1], V[:-1], A[:-1], P[1:], V[1:], A[1:], T)  # (m, J, 2, 6)

    def _rate_ratios(self) -> np.ndarray:
        """Per piece: max over samples and bendables of |v| / rate_max (vectorised over pieces,
        in blocks so a long goal's temporary arrays stay a few MB)."""
        m = len(self.durations)
        out = np.empty(m)
        u = np.linspace(0.0, 1.0, _SAMPLES)
        for lo in range(0, m, _BLOCK):
            hi = min(m, lo + _BLOCK)
            tau = self.durations[lo:hi, None] * u  # (b, S)
            pw = np.stack(
                [
                    np.zeros_like(tau),
                    np.ones_like(tau),
                    2 * tau,
                    3 * tau**2,
                    4 * tau**3,
                    5 * tau**4,
                ],
                axis=1,
            )  # (b, 6, S)
            vel = np.einsum("bjkc,bcs->bjks", self.coeffs[lo:hi], pw)  # (b, J, 2, S)
            speed = np.hypot(vel[:, :, 0, :], vel[:, :, 1, :]).max(axis=2)  # (b, J)
            out[lo:hi] = (speed / self.rate_max).max(axis=1)
        return out

    def with_stops(self, ramp: CurvatureTrajectory, cols: list[int]) -> CurvatureTrajectory:
        """Let the columns ``cols`` follow ``ramp`` (a path over the same joints, its time from
        this path's start: ``t0`` = 0) instead of the pieces, until the ramp ends; the pieces
        must hold those columns still where the ramp ends. A goal uses it for the bendables it
        does not name that were moving: they stop as a cancel stops them (no running on and
        coming back). Returns self."""
        self._stop, self._stop_cols = ramp, sorted(cols)
        self._stop_end = ramp.duration
        self.duration = max(self._end, self._stop_end)
        return self

    def phi_leaves(
        self, ranges: dict[int, tuple[float, float]], kappa_min: float = 1e-6
    ) -> tuple[int, float, float] | None:
        """Where the sampled pieces first leave a restricted phi range: ``ranges`` maps a column
        to its (phi_min, phi_max) rad; samples as in the rate check (``_SAMPLES`` per piece),
        straight ones (kappa <= ``kappa_min``) count as inside. A column that starts outside
        (a hold measured there) is checked from where it first is inside. Returns (column, time
        from the start s, phi rad) of the first sample outside, or None."""
        if not ranges:
            return None
        eps = 1e-6  # rad: beyond float rounding at a bound
        cols = sorted(ranges)
        m = len(self.durations)
        u = np.linspace(0.0, 1.0, _SAMPLES)
        entered = dict.fromkeys(cols, False)
        starts = np.concatenate([[0.0], np.asarray(self.ends[:-1])])
        for lo in range(0, m, _BLOCK):
            hi = min(m, lo + _BLOCK)
            tau = self.durations[lo:hi, None] * u  # (b, S)
            pw = np.stack([np.ones_like(tau), tau, tau**2, tau**3, tau**4, tau**5], axis=1)
            pos = np.einsum("bjkc,bcs->bjks", self.coeffs[lo:hi][:, cols], pw)  # (b, C, 2, S)
            times = (starts[lo:hi, None] + tau).reshape(-1)
            found = []
            for k, c in enumerate(cols):
                kx = pos[:, k, 0, :].reshape(-1)
                ky = pos[:, k, 1, :].reshape(-1)
                phi = np.arctan2(ky, kx)
                pmin, pmax = ranges[c]
                d = np.mod(phi - pmin, math.tau)  # around the circle from phi_min
                inside = (d <= pmax - pmin + eps) | (d >= math.tau - eps)
                inside |= np.hypot(kx, ky) <= kappa_min
                if not entered[c]:
                    first = np.flatnonzero(inside)
                    if not len(first):
                        continue  # outside since the start: it has not left the range
                    entered[c] = True
                    inside[: first[0]] = True
                bad = np.flatnonzero(~inside)
                if len(bad):
                    found.append((float(times[bad[0]]), c, float(phi[bad[0]])))
            if found:
                t, c, ph = min(found)
                return c, t, ph
        return None

    def position(self, t: float) -> list[list[float]]:
        """Position only (J lists of [kx, ky]) at absolute time ``t``: the per-cycle fast path."""
        tau = t - self.t0
        if self._stop is not None and tau < self._stop_end:
            out = [list(r) for r in self._position(tau)]  # a copy: _final_list is shared
            ramp = self._stop.position(max(tau, 0.0))
            for c in self._stop_cols:
                out[c] = ramp[c]
            return out
        return self._position(tau)

    def _position(self, tau: float) -> list[list[float]]:
        if tau >= self._end:
            return self._final_list
        tau = max(tau, 0.0)
        i = bisect.bisect_right(self.ends, tau)
        s = tau - (self.ends[i - 1] if i > 0 else 0.0)
        s2 = s * s
        return (self.coeffs[i] @ (1.0, s, s2, s2 * s, s2 * s2, s2 * s2 * s)).tolist()

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (each (J, 2)) at absolute time ``t``."""
        tau = t - self.t0
        p, v, a = self._sample(tau)
        if self._stop is not None and tau < self._stop_end:
            rp, rv, ra = self._stop.sample(max(tau, 0.0))
            cols = self._stop_cols
            p[cols], v[cols], a[cols] = rp[cols], rv[cols], ra[cols]
        return p, v, a

    def _sample(self, tau: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if tau >= self._end:
            z = np.zeros_like(self.final)
            return self.final.copy(), z, z.copy()
        tau = max(tau, 0.0)
        i = bisect.bisect_right(self.ends, tau)
        start = self.ends[i - 1] if i > 0 else 0.0
        s = tau - start
        c = self.coeffs[i]
        s2, s3 = s * s, s * s * s
        p = c @ np.array([1.0, s, s2, s3, s3 * s, s3 * s2])
        v = c @ np.array([0.0, 1.0, 2 * s, 3 * s2, 4 * s3, 5 * s3 * s])
        a = c @ np.array([0.0, 0.0, 2.0, 6 * s, 12 * s2, 20 * s3])
        return p, v, a

    def moving(self, joints: list[str], t: float) -> set[str]:
        """The joints (named in the order of the path's columns) this path moves at or after
        ``t``: a joint whose every knot is where the path starts, with no starting velocity or
        acceleration, is held still (a goal that names only other segments); before the path's
        start (a lead-in still running) every joint counts as moved."""
        if t < self.t0:
            return set(joints)
        P = self.positions
        still = (np.abs(P - P[0]) <= 1e-12).all(axis=(0, 2))
        still &= (np.asarray(self.v0) == 0).all(axis=1) & (np.asarray(self.a0) == 0).all(axis=1)
        if t - self.t0 < self._stop_end:
            still[self._stop_cols] = False  # still stopping
        return {j for j, s in zip(joints, still.tolist(), strict=True) if not s}

    def remapped(
        self,
        joints: list[str],
        new_joints: list[str],
        hold: np.ndarray,
        held: set[str] | frozenset[str] = frozenset(),
    ) -> Any:
        """The same timed path over ``new_joints`` (a rebuilt controller's bendables): the
        columns of joints in both are copied; a joint new to the path, or named in ``held``,
        holds ``hold[k]`` (its row in ``new_joints`` order) for the whole path. Times are
        unchanged."""
        idx = {j: i for i, j in enumerate(joints) if j not in held}
        m1, J = self.positions.shape[0], len(new_joints)
        P = np.empty((m1, J, 2))
        C = np.zeros((self.coeffs.shape[0], J, 2, 6))
        v0, a0 = np.zeros((J, 2)), np.zeros((J, 2))
        rate = np.ones(J)
        for k, j in enumerate(new_joints):
            i = idx.get(j)
            if i is None:
                P[:, k] = hold[k]
                C[:, k, :, 0] = hold[k]
                continue
            P[:, k], C[:, k] = self.positions[:, i], self.coeffs[:, i]
            v0[k], a0[k], rate[k] = self.v0[i], self.a0[i], self.rate_max[i]
        out = copy.copy(self)
        out.positions, out.coeffs, out.v0, out.a0, out.rate_max = P, C, v0, a0, rate
        out.final = P[-1]
        out._final_list = out.final.tolist()
        if self._stop is not None:  # the stop ramps of the joints that keep their column
            stopping = {joints[c] for c in self._stop_cols}
            out._stop = self._stop.remapped(joints, new_joints, hold, held)
            out._stop_cols = [k for k, j in enumerate(new_joints) if j in stopping and j in idx]
            if not out._stop_cols:
                out._stop, out._stop_end = None, 0.0
        return out


class StaleGoalError(ControllerError):
    """A goal built outside the daemon lock no longer fits: the controller's motion changed (or
    the build took longer than the lead it was planned with) before it could be installed."""


class GoalStart:
    """Where a goal built outside the daemon lock starts: a snapshot of the controller's desired
    motion at ``t_start`` (s, monotonic), taken under the lock by ``goal_snapshot``."""

    def __init__(
        self,
        t_start: float,
        p: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        generation: int,
        at_rest: bool,
    ):
        self.t_start = t_start
        self.p, self.v, self.a = p, v, a
        self.generation = generation
        self.at_rest = at_rest


class Goal:
    """One trajectory request and its fate; ``status()`` is what the caller sees."""

    def __init__(self, goal_id: str, controller: str, n_points: int):
        self.id = goal_id
        self.controller = controller
        self.n_points = n_points
        self.state = "pending"
        self.reason = ""
        self.t_accepted: float | None = None
        # the path while the goal runs; dropped when it ends (a 10,000-point path is megabytes and
        # hundreds of finished goals are kept), leaving only the figures below
        self.trajectory: CurvatureTrajectory | None = None
        self.duration: float | None = None  # s, after retiming
        self.requested_duration: float | None = None  # s, as requested
        self.retimed = False
        self.progress = 0.0
        self.max_error = 0.0
        self.final_error: dict[str, float] = {}
        # for an aborted goal: {"cause", "segment", "error" (1/m or None), "tolerance" (1/m or
        # None)} — the error, when given, is a measured finite value above the tolerance
        self.abort: dict[str, Any] | None = None
        # True while a rebuild carries the goal from one controller instance to the next
        # (host/controller_manager.py): the old instance's deactivation must not end it
        self.carried = False
        # who sent it (host.controllers.base.sender_of), None: not said
        self.sender: dict[str, str] | None = None

    def finish(
        self,
        state: str,
        reason: str = "",
        *,
        cause: str | None = None,
        segment: str | None = None,
        error: float | None = None,
        tolerance: float | None = None,
    ) -> None:
        if self.carried:
            return  # being handed to the rebuilt controller: it runs on
        if self.state not in TERMINAL_STATES:
            self.state, self.reason = state, reason
            if state == "aborted":
                if error is not None and not (
                    math.isfinite(error) and (tolerance is None or error > tolerance)
                ):
                    error = None  # never report a figure that contradicts the cause
                self.abort = {
                    "cause": cause or abort_cause(reason),
                    "segment": segment,
                    "error": None if error is None else round(error, 5),
                    "tolerance": tolerance,
                }
        self._summarise()
        self.trajectory = None

    def _summarise(self) -> None:
        tr = self.trajectory
        if tr is not None:
            self.duration = tr.duration
            self.requested_duration = float(tr.requested_durations.sum())
            self.retimed = bool(tr.retimed)

    def status(self) -> dict[str, Any]:
        self._summarise()
        return {
            "id": self.id,
            "controller": self.controller,
            "state": self.state,
            "reason": self.reason,
            "progress": round(self.progress, 4),
            "duration": self.duration,
            "requested_duration": self.requested_duration,
            "retimed": self.retimed,
            "points": self.n_points,
            "max_path_error": self.max_error,
            "final_error": dict(self.final_error),
            "abort": dict(self.abort) if self.abort else None,
            "done": self.state in TERMINAL_STATES,
            "from": dict(self.sender) if self.sender else None,
        }
