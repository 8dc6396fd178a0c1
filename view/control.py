"""Moving the robot from the page, always through the daemon's arbitration.

Sliders: the page is a manual source. A κ/φ slider sets a target; :class:`SliderDriver` streams
cFFC inputs (``ffc.input``, the same op a gamepad uses) that steer the measured curvature vector
towards it, so the arbitration, slew limits and the daemon's deadman apply unchanged. It streams
only while a page is connected and the sliders were touched in the last ``idle_s``; when it stops
it sends one zero input (the daemon's deadman would stop the robot anyway 0.3 s later).

Tip gizmo: :class:`MovePlanner` solves IK (:mod:`ucrdf.ik`) for the dragged target, keeps the
reachable solution for the page to show, and on request sends it as one trajectory.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ucrdf.ik import IKResult, IKSolver

#: Time constant (s) of the slider servo: deflection = error / (rate_max * TAU).
TAU_S = 0.25
#: cFFC defaults (host/controllers/ffc.py): deadzone (fraction of full deflection), gain.
FFC_DEADZONE = 0.05
#: Curvature-vector error (1/m) accepted as "arrived".
ARRIVED = 0.02


def deflection(
    target: tuple[float, float], measured: tuple[float, float], rate_max: float
) -> tuple[float, float]:
    """cFFC stick deflection (unit disc) steering ``measured`` (kx, ky) towards ``target``.

    Proportional with time constant TAU_S; never inside the cFFC deadzone while the error is
    above ARRIVED (or the segment would stop short of the target)."""
    ex, ey = target[0] - measured[0], target[1] - measured[1]
    err = math.hypot(ex, ey)
    if err <= ARRIVED or not math.isfinite(rate_max) or rate_max <= 0:
        return (0.0, 0.0)
    mag = min(1.0, err / (rate_max * TAU_S))
    mag = max(mag, FFC_DEADZONE + 0.03)
    return (ex / err * mag, ey / err * mag)


def kvec(kappa: float, phi: float) -> tuple[float, float]:
    return (kappa * math.cos(phi), kappa * math.sin(phi))


class SliderDriver:
    """Streams cFFC inputs towards the slider targets (see module docstring)."""

    def __init__(
        self,
        client: Any,
        measured: Callable[[], dict[str, dict[str, float]]],
        rate_max: Callable[[str], float],
        page_open: Callable[[], bool],
        report: Callable[[str], None],
        rate_hz: float = 25.0,
        idle_s: float = 10.0,
    ):
        self.client = client
        self.measured = measured
        self.rate_max = rate_max
        self.page_open = page_open
        self.report = report
        self.period = 1.0 / rate_hz
        self.idle_s = idle_s
        self.targets: dict[str, tuple[float, float]] = {}
        self.lock = threading.Lock()
        self.t_touch = -math.inf
        self.streaming = False  # last input we sent was non-zero
        self.owns_control = False  # our input took over (we hand back before a move)
        self.sent = 0
        self.last_names: list[str] = []
        self.stopped_reason = ""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ucr-view-sliders", daemon=True)

    def start(self) -> SliderDriver:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.halt("view closing")

    def set_target(self, name: str, kappa: float, phi: float) -> None:
        with self.lock:
            self.targets[name] = kvec(kappa, phi)
            self.t_touch = time.monotonic()
            self.stopped_reason = ""

    def halt(self, reason: str) -> None:
        """Forget the targets and send one zero input: the robot holds where it is."""
        with self.lock:
            names = list(self.targets) or list(self.last_names)
            self.targets.clear()
            self.t_touch = -math.inf
            was = self.streaming
            self.streaming = False
            self.stopped_reason = reason
        if was and names:
            try:
                self.client.ffc_input({n: (0.0, 0.0) for n in names})
            except Exception as exc:  # noqa: BLE001 - the deadman stops it anyway
                self.report(f"zero input not sent ({exc}); the daemon's deadman stops the robot")

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            with self.lock:
                targets = dict(self.targets)
                idle = time.monotonic() - self.t_touch > self.idle_s
            if not targets:
                continue
            if not self.page_open():
                self.halt("page closed")
                continue
            if idle:
                self.halt(f"no slider input for {self.idle_s:g} s")
                continue
            meas = self.measured()
            rates: dict[str, tuple[float, float]] = {}
            for name, tgt in targets.items():
                m = meas.get(name)
                if m is None:
                    continue
                rates[name] = deflection(tgt, kvec(m["kappa"], m["phi"]), self.rate_max(name))
            moving = any(r != (0.0, 0.0) for r in rates.values())
            if not moving and not self.streaming:
                continue
            if not rates:
                continue
            self.last_names = list(rates)
            try:
                reply = self.client.ffc_input(rates)  # all zero once arrived: it stops there
                self.sent += 1
                if moving or reply.get("takeover"):
                    self.owns_control = True  # the cFFC moves on our input
                self.streaming = moving
            except Exception as exc:  # noqa: BLE001 - refused: show why, stop streaming
                self.halt(f"refused: {exc}")
                self.report(f"slider input refused: {exc}")


class MovePlanner:
    """IK for a dragged tip target; the reachable solution waits for the user to execute it."""

    def __init__(self, solver: IKSolver):
        self.solver = solver
        self.target: np.ndarray | None = None
        self.result: IKResult | None = None
        self.executed: tuple[np.ndarray | None, IKResult] | None = None
        self.lock = threading.Lock()

    def plan(self, target_xyz: np.ndarray, current: dict[str, dict[str, float]]) -> IKResult:
        initial = {n: dict(v) for n, v in current.items() if n in self.solver.kin.models}
        res = self.solver.solve(
            [float(v) for v in target_xyz], initial=initial, restarts=4, max_iter=100
        )
        with self.lock:
            self.target, self.result = np.asarray(target_xyz, dtype=float), res
        return res

    def trajectory(
        self, current: dict[str, dict[str, float]], present: list[str], rate_max: Callable
    ) -> list[dict]:
        """One waypoint to the planned solution (segments on the chain only), timed so the
        largest curvature-vector change takes 3x its slew-limited time (at least 2 s): a dragged
        target is a calm move, well inside the cJTC's path tolerance."""
        with self.lock:
            res, target = self.result, self.target
        if res is None:
            raise ValueError("drag the tip gizmo first")
        self.executed = (target, res)  # what was sent (a later drag update may replan)
        segs: dict[str, dict[str, float]] = {}
        duration = 2.0
        for name in present:
            cfg = res.config.get(name)
            if not isinstance(cfg, dict) or "kappa" not in cfg:
                continue
            segs[name] = {"kappa": float(cfg["kappa"]), "phi": float(cfg.get("phi", 0.0))}
            cur = current.get(name, {"kappa": 0.0, "phi": 0.0})
            a, b = kvec(cur["kappa"], cur["phi"]), kvec(segs[name]["kappa"], segs[name]["phi"])
            rm = rate_max(name)
            if math.isfinite(rm) and rm > 0:
                duration = max(duration, 3.0 * math.hypot(b[0] - a[0], b[1] - a[1]) / rm)
        if not segs:
            raise ValueError("no segment of the solution is on the chain")
        return [{"time_from_start": round(duration, 3), "segments": segs}]
