"""Moving the robot from the page, always through the daemon's arbitration.

Sliders: the page is a manual source. A κ/φ slider sets a target; :class:`SliderDriver` streams
cFFC inputs (``ffc.input``, the same op a gamepad uses), so the arbitration, slew limits and the
daemon's deadman apply unchanged. The cFFC integrates a setpoint from the stick deflection
(host/controllers/ffc.py) and the segments follow it with a lag, so the driver steers that
setpoint, not the lagging measurement: it reads the setpoint the daemon reports
(``controllers.list`` when a move starts, each ``ffc.input`` reply after) and integrates its own
inputs on top until the next report, as the cFFC does (:class:`SetpointModel`; from the measured
state against a daemon that does not report it), and bounds each deflection so that the setpoint
could not pass the target even if that input stayed in force until the cFFC's deadman
(:class:`FfcParams`: the deadzone, gain and deadman of the daemon's cFFC, read from
``controllers.list``). So the robot never goes past a slider target, and stops at or before it
whenever the inputs end (page closed, view killed). It streams only while every page that set
one of the targets it drives is still connected (a page that stays open does not keep another's
targets alive) and the sliders were touched in the last ``idle_s``; when it stops it sends one
zero input (the daemon's deadman would stop the robot anyway 0.3 s later).

Tip gizmo: :class:`MovePlanner` solves IK (:mod:`ucrdf.ik`) for the dragged target, keeps the
reachable solution for the page to show, and on request sends it as one trajectory.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Any

import numpy as np

from host.api.client import on_behalf_of
from host.controllers.ffc import FeedForwardController
from ucrdf.ik import IKResult, IKSolver

#: cFFC defaults (host/controllers/ffc.py): deadzone (fraction of full deflection); its gain is
#: at most 1, so ``kappa_rate_max`` is the fastest a deflection moves the setpoint.
FFC_DEADZONE = FeedForwardController.defaults["deadzone"]
#: Beyond its cFFC's deadman, how long one input can still be in force: a loop period and margin.
HORIZON_MARGIN_S = 0.05
#: How long one input can stay in force with the default cFFC: its deadman (0.3 s) plus
#: :data:`HORIZON_MARGIN_S`. The setpoint speed is at most (distance to target) / HORIZON_S.
HORIZON_S = FeedForwardController.defaults["deadman_timeout"] + HORIZON_MARGIN_S
#: Smallest deflection sent above the deadzone (so the cFFC does move the setpoint).
MIN_ABOVE_DEADZONE = 0.005
#: Distance (1/m) of the modelled setpoint to the target accepted as "arrived".
ARRIVED = 0.02
#: After this long (s) without a moving input, a segment whose measured state has reached the
#: modelled setpoint (within :data:`CAUGHT_UP`), or has stood still (within :data:`STEADY`) for
#: :data:`STEADY_S` without reporting clamped setpoints, starts the model from the measured state
#: again: it follows its setpoint, so the setpoint is where it stands (the model is only an upper
#: bound of the cFFC's travel). A segment still moving towards the setpoint (a firmware slower
#: than the file's rate) or held by its own limits keeps the model: restarting from a lagging
#: measurement would carry the setpoint past the target.
SETTLE_S = 1.0
CAUGHT_UP = 0.05  # 1/m
STEADY = 0.01  # 1/m
STEADY_S = 0.5
#: Seconds of our own inputs kept to tell them from another client's (:meth:`SliderDriver.sent_at`).
SENT_MEMORY_S = 5.0


@dataclass(frozen=True)
class FfcParams:
    """The parameters of the daemon's cFFC that the slider drive depends on (its
    ``controllers.list`` entry; the defaults of host/controllers/ffc.py until it is read)."""

    deadzone: float = FFC_DEADZONE
    gain: float = 1.0
    deadman_timeout_s: float = FeedForwardController.defaults["deadman_timeout"]

    @property
    def horizon_s(self) -> float:
        """How long one input can stay in force: the deadman plus a loop period and margin."""
        return self.deadman_timeout_s + HORIZON_MARGIN_S

    @classmethod
    def from_describe(cls, d: Any) -> FfcParams | None:
        """From a cFFC's ``controllers.list`` entry; None when it does not say (an older
        daemon) or says something the cFFC could not run with."""
        try:
            dz, gain, dm = (float(d[k]) for k in ("deadzone", "gain", "deadman_timeout_s"))
        except (KeyError, TypeError, ValueError):
            return None
        if not (0.0 <= dz < 1.0 and 0.0 < gain <= 1.0 and 0.0 < dm < 60.0):
            return None
        return cls(dz, gain, dm)


DEFAULT_FFC = FfcParams()


def driven_ffc(entries: Any) -> dict | None:
    """The cFFC ``ffc.input`` drives, from a ``controllers.list`` reply: the first active one,
    else the first (as the daemon picks it); None when there is none or the reply is no list."""
    if not isinstance(entries, list):
        return None
    ffcs = [c for c in entries if isinstance(c, dict) and c.get("type") == "ffc"]
    return next((c for c in ffcs if c.get("state") == "active"), ffcs[0] if ffcs else None)


def deflection(
    target: tuple[float, float],
    setpoint: tuple[float, float],
    rate_max: float,
    ffc: FfcParams = DEFAULT_FFC,
) -> tuple[tuple[float, float], tuple[float, float]]:
    """``(stick deflection, setpoint rate)`` steering the cFFC's ``setpoint`` (kx, ky) to
    ``target``: the rate (1/m/s, the cFFC's for that deflection with its deadzone and gain) is at
    most the distance over ``ffc.horizon_s``, so the setpoint cannot pass the target while that
    input is in force; zero within :data:`ARRIVED`."""
    ex, ey = target[0] - setpoint[0], target[1] - setpoint[1]
    err = math.hypot(ex, ey)
    top = rate_max * ffc.gain  # the cFFC's setpoint speed at full deflection
    if err <= ARRIVED or not math.isfinite(top) or top <= 0:
        return (0.0, 0.0), (0.0, 0.0)
    dz = ffc.deadzone
    speed = min(top, err / ffc.horizon_s)
    mag = dz + (1.0 - dz) * speed / top  # > dz: the cFFC moves
    if (
        mag < dz + MIN_ABOVE_DEADZONE
        and top * MIN_ABOVE_DEADZONE / (1.0 - dz) * ffc.horizon_s <= err
    ):
        mag = dz + MIN_ABOVE_DEADZONE  # clear of the deadzone where that cannot pass the target
    mag = min(1.0, mag)
    speed = top * (mag - dz) / (1.0 - dz)  # what the cFFC does with it
    ux, uy = ex / err, ey / err
    return (ux * mag, uy * mag), (ux * speed, uy * speed)


def kvec(kappa: float, phi: float) -> tuple[float, float]:
    return (kappa * math.cos(phi), kappa * math.sin(phi))


class SetpointModel:
    """The cFFC's commanded curvature vector per segment: the daemon's last report of it (or,
    from a daemon that does not report it, the measured state), integrated on from the inputs
    the driver sent since (``kx += rate * dt``, each input in force until the next one or for at
    most :data:`HORIZON_S`, clamped radially at ``kappa_max``). An upper bound of how far the
    setpoint went: the cFFC's gain is at most 1."""

    def __init__(self) -> None:
        self.at: dict[str, list[float]] = {}
        self.rates: dict[str, tuple[float, float]] = {}
        self.t = -math.inf
        #: the daemon reports its cFFC's setpoint (a newer daemon): ``at`` is its report,
        #: advanced by our inputs since, and is never restarted from the measurement
        self.reported = False

    def advance(
        self, now: float, kappa_max: Callable[[str], float], horizon_s: float = HORIZON_S
    ) -> None:
        dt = min(max(0.0, now - self.t), horizon_s)
        for name, (rx, ry) in self.rates.items():
            c = self.at.get(name)
            if c is None or not (rx or ry):
                continue
            c[0] += rx * dt
            c[1] += ry * dt
            kmax = kappa_max(name)
            r = math.hypot(c[0], c[1])
            if math.isfinite(kmax) and r > kmax > 0:
                c[0], c[1] = c[0] * kmax / r, c[1] * kmax / r
        self.t = now

    def sent(self, now: float, rates: dict[str, tuple[float, float]]) -> None:
        self.rates = dict(rates)  # the cFFC replaces the whole input: others get zero rate
        self.t = now

    def forget(self) -> None:
        self.at.clear()
        self.rates = {}
        self.reported = False

    def report(self, setpoint: Any, names: Collection[str]) -> None:
        """Take the daemon's setpoint (``{segment: [kx, ky]}``, 1/m) for ``names``; anything
        else (an inactive cFFC's None) is no report."""
        if not isinstance(setpoint, dict):
            return
        for name in names:
            v = setpoint.get(name)
            ok = isinstance(v, list | tuple) and len(v) == 2
            if ok and all(isinstance(x, int | float) and math.isfinite(x) for x in v):
                self.at[name] = [float(v[0]), float(v[1])]
        self.reported = True

    def settle(self, measured: dict[str, dict[str, float]], at_rest: Callable[[str], bool]) -> None:
        """No moving input for :data:`SETTLE_S`: drop the modelled setpoint of each segment whose
        measured state has reached it or that is ``at_rest`` (standing still, not clamped): the
        next move starts from the measurement. Keep the others (still lagging or held: their
        setpoint is the model's, not the measurement)."""
        self.rates = {}
        for name, c in list(self.at.items()):
            m = measured.get(name)
            if m is None:
                continue
            mx, my = kvec(m["kappa"], m["phi"])
            if math.hypot(c[0] - mx, c[1] - my) <= CAUGHT_UP or at_rest(name):
                del self.at[name]


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
        kappa_max: Callable[[str], float] | None = None,
        clamped: Callable[[str], bool] | None = None,
        ffc_params: Callable[[], FfcParams | None] | None = None,
        pages: Callable[[], Collection[int]] | None = None,
    ):
        self.client = client
        #: the daemon's cFFC parameters as last read (None: not known, the defaults apply)
        self.ffc_params = ffc_params or (lambda: None)
        self.measured = measured
        #: whether a segment reports clamping its setpoints (held by its own limits)
        self.clamped = clamped or (lambda _name: False)
        #: per segment: (measured vector, since when it stayed within STEADY of it)
        self.still: dict[str, tuple[tuple[float, float], float]] = {}
        self.rate_max = rate_max
        self.kappa_max = kappa_max or (lambda _name: math.inf)
        self.page_open = page_open
        #: the ids of the pages connected now (None: only ``page_open`` is known)
        self.pages = pages
        #: the pages that set the targets being driven (since the last stop): the deadman
        self.owners: set[int] = set()
        #: per driven segment, the page that set its target (None: not a page)
        self.target_page: dict[str, int | None] = {}
        self.report = report
        self.period = 1.0 / rate_hz
        self.idle_s = idle_s
        self.targets: dict[str, tuple[float, float]] = {}
        self.lock = threading.Lock()
        self.t_touch = -math.inf
        self.t_moving = -math.inf  # last moving input sent
        self.streaming = False  # last input we sent was non-zero
        self.owns_control = False  # our input took over (we hand back before a move)
        self.sent = 0
        self.last_names: list[str] = []
        self.stopped_reason = ""
        #: whom the inputs are for (the page that set the latest target): their audit lines
        self.label: str | None = None
        self.model = SetpointModel()
        #: the slider touch the model was last read from the daemon for (a move's start)
        self.read_for_touch = -math.inf
        #: (start, end) monotonic times of our recent ffc.input calls: the daemon set each
        #: input in between (told apart from another client's, see sent_at)
        self.calls: collections.deque = collections.deque(maxlen=int(rate_hz * SENT_MEMORY_S) + 8)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ucr-view-sliders", daemon=True)

    def start(self) -> SliderDriver:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.halt("view closing")

    def _ffc(self) -> FfcParams:
        return self.ffc_params() or DEFAULT_FFC

    def set_target(
        self, name: str, kappa: float, phi: float, label: str | None = None, page: int | None = None
    ) -> None:
        """Drive ``name`` towards κ (1/m), φ (rad); ``label``: the page that asked (audit);
        ``page``: its id, which must stay connected for the drive to go on (deadman)."""
        with self.lock:
            self.label = label
            if page is not None:
                self.owners.add(page)
            self.target_page[name] = page
            self.targets[name] = kvec(kappa, phi)
            self.t_touch = time.monotonic()
            self.stopped_reason = ""

    def _at_rest(self, now: float) -> Callable[[str], bool]:
        def at_rest(name: str) -> bool:
            last = self.still.get(name)
            return last is not None and now - last[1] >= STEADY_S and not self.clamped(name)

        return at_rest

    def forget_setpoints(self) -> None:
        """Another source moved the cFFC's setpoint (or the daemon restarted): the next input
        starts the model from the measured state again."""
        with self.lock:
            self.model.forget()

    def _read_setpoint(self) -> tuple[bool, dict | None]:
        """``(reported, setpoint)`` of the cFFC that ``ffc.input`` drives (the active one, else
        the first), from ``controllers.list``: ``reported`` False when the daemon does not say
        (older) or cannot be asked; ``setpoint`` None while that cFFC is inactive (the input
        that takes over starts it from the measured state)."""
        try:
            chosen = driven_ffc(self.client.controllers())
        except Exception:  # noqa: BLE001 - not known: the model starts from the measurement
            return False, None
        if chosen is None or "setpoint" not in chosen:
            return False, None
        sp = chosen["setpoint"] if chosen.get("state") == "active" else None
        return True, sp if isinstance(sp, dict) else None

    def sent_at(self, earliest: float, latest: float, slack: float = 0.002) -> bool:
        """Whether the daemon's latest cFFC input, set between ``earliest`` and ``latest`` (our
        monotonic clock), can be one of ours."""
        with self.lock:
            calls = list(self.calls)
        return any(s - slack <= latest and earliest <= e + slack for s, e in calls)

    def halt(self, reason: str, send_zero: bool = True, label: str | None = None) -> None:
        """Forget the targets and send one zero input: the robot holds where it is (without
        ``send_zero``: another client's input is in force, ours is not sent over it).
        ``label``: the page that asked (else the one whose targets these were)."""
        with self.lock:
            names = list(self.targets) or list(self.last_names)
            self.targets.clear()
            self.owners.clear()
            self.target_page.clear()
            self.t_touch = -math.inf
            was = self.streaming
            self.streaming = False
            self.stopped_reason = reason
            self.model.advance(time.monotonic(), self.kappa_max, self._ffc().horizon_s)
            self.model.sent(time.monotonic(), {})
        if was and names and send_zero:
            self._send({n: (0.0, 0.0) for n in names}, report=True, label=label)

    def _send(
        self, rates: dict[str, tuple[float, float]], report: bool = False, label: str | None = None
    ) -> Any:
        call = [time.monotonic(), math.inf]  # in flight: any later input may be this one
        with self.lock:
            self.calls.append(call)
            label = label or self.label
        try:
            with on_behalf_of(label):
                return self.client.ffc_input(rates)
        except Exception as exc:  # noqa: BLE001 - the deadman stops it anyway
            if report:
                self.report(f"zero input not sent ({exc}); the daemon's deadman stops the robot")
                return None
            raise
        finally:
            call[1] = time.monotonic()

    def step(self) -> None:
        """One tick: the next input towards the targets (none when nothing is to be done)."""
        with self.lock:
            targets = dict(self.targets)
            owners = set(self.owners)
            idle = time.monotonic() - self.t_touch > self.idle_s
        if not targets:
            return
        if not self.page_open() or (
            owners and self.pages is not None and not owners <= set(self.pages())
        ):
            self.halt("page closed")
            return
        if idle:
            self.halt(f"no slider input for {self.idle_s:g} s")
            return
        meas = self.measured()
        ffc = self._ffc()
        with self.lock:
            touch = self.t_touch
            start = not self.streaming and (
                touch != self.read_for_touch or any(n not in self.model.at for n in targets)
            )
        read = self._read_setpoint() if start else None  # a move starts: where is the setpoint?
        now = time.monotonic()
        deflections: dict[str, tuple[float, float]] = {}
        rates: dict[str, tuple[float, float]] = {}
        with self.lock:
            model = self.model
            if read is not None:
                self.read_for_touch = touch
                if read[0]:  # the daemon's word, or (inactive cFFC) the measurement
                    model.at.clear()
                    model.report(read[1], targets)
                    model.reported = True  # an inactive cFFC's too: the takeover reports next
            model.advance(now, self.kappa_max, ffc.horizon_s)
            for name, m in meas.items():
                v = kvec(m["kappa"], m["phi"])
                last = self.still.get(name)
                if last is None or math.hypot(v[0] - last[0][0], v[1] - last[0][1]) > STEADY:
                    self.still[name] = (v, now)
            if now - self.t_moving > SETTLE_S and not model.reported:
                # (a daemon that does not report its setpoint) the segments that caught up, or
                # stand still unclamped, restart from there
                model.settle(meas, self._at_rest(now))
            for name, tgt in targets.items():
                m = meas.get(name)
                if m is None:
                    continue  # no valid state: not moved (zero rate)
                c = model.at.setdefault(name, list(kvec(m["kappa"], m["phi"])))
                deflections[name], rates[name] = deflection(
                    tgt, (c[0], c[1]), self.rate_max(name), ffc
                )
        moving = any(r != (0.0, 0.0) for r in deflections.values())
        if not deflections or (not moving and not self.streaming):
            return
        self.last_names = list(deflections)
        try:
            reply = self._send(deflections)  # all zero once arrived: it stops there
        except Exception as exc:  # noqa: BLE001 - refused: show why, stop streaming
            with self.lock:
                self.model.forget()
            self.halt(f"refused: {exc}")
            self.report(f"slider input refused: {exc}")
            return
        with self.lock:
            if isinstance(reply, dict) and reply.get("setpoint") is not None:
                # where this input starts from, as the daemon says; it integrates from about
                # ``now`` (the call's start: the model runs ahead of it by the call's time)
                self.model.report(reply["setpoint"], rates)
            elif isinstance(reply, dict) and reply.get("takeover"):
                # the cFFC was (re)activated by this input: it started from the measured state
                self.model.forget()
                for name, m in meas.items():
                    if name in rates:
                        self.model.at[name] = list(kvec(m["kappa"], m["phi"]))
            self.model.sent(now, rates)
            if moving:
                self.t_moving = now
        self.sent += 1
        if moving or (isinstance(reply, dict) and reply.get("takeover")):
            self.owns_control = True  # the cFFC moves on our input
        self.streaming = moving

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            self.step()


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
