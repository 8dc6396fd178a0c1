"""Review of the daemon's motion control (stalls, goals naming some segments, cFFC pauses,
restricted phi ranges): deterministic, no chain, no daemon thread — the controllers, the manager
and ``Motion.update`` on a simulated clock (the review's sim1..sim6 scripts, made tests)."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

from host.config import DaemonConfig
from host.controller_manager import ControllerManager
from host.controllers.base import ControllerContext, ControllerError, RobotState
from host.controllers.ffc import FeedForwardController
from host.controllers.jtc import JointTrajectoryController
from host.hwi import ACTIVE, HardwareInterface
from host.limits import BendableLimits
from host.motion import Motion

DT = 0.01
NAMES = ("segment_1", "segment_2")


def _limits(phi_range: tuple[float, float] | None = None) -> dict[str, BendableLimits]:
    lo, hi = phi_range or (-math.pi, math.pi)
    return {n: BendableLimits(n, 0.316, 3.314, 5.0, phi_min=lo, phi_max=hi) for n in NAMES}


def _state(t: float, kx: list[float], ky: list[float] | None = None) -> RobotState:
    ky = ky or [0.0] * len(kx)
    n = len(kx)
    return RobotState(
        t, list(NAMES), list(kx), list(ky), [math.hypot(a, b) for a, b in zip(kx, ky, strict=True)],
        [math.atan2(b, a) for a, b in zip(kx, ky, strict=True)], [True] * n, [None] * n, [True] * n,
    )  # fmt: skip


# -- 1. a stall (same chain, resumed) never aborts the goal it paused --------------------------


class _Hwi:
    """What ``Motion.update`` uses of the HWI: ``first_measured``, ``limits``, ``set_curvature``."""

    def __init__(self, limits: dict[str, BendableLimits]):
        self.limits = limits
        self.first_measured: list[str] = []
        self.cmd: dict[str, tuple[float, float]] = {}

    def set_curvature(self, name: str, kx: float, ky: float) -> None:
        self.cmd[name] = (kx, ky)


def _motion_moving(lag: float = 0.0) -> tuple[Motion, _Hwi, JointTrajectoryController, float]:
    """A Motion whose cJTC runs a 4 s goal 0 -> 3 1/m on segment_1, tracked perfectly (segment_1
    measured ``lag`` 1/m behind its command) for 1.5 s on a 10 ms clock; returns it at that time."""
    lim = _limits()
    cfg = DaemonConfig(controllers={"jtc": {"type": "jtc", "params": {}}}, active=["jtc"])
    m = Motion(cfg, threading.RLock(), lambda *a, **k: None, lambda: None, DT)
    t = 1.0
    m.build(ControllerContext(lim), _state(t, [0.0, 0.0]), "start")
    jtc = m.cm.controllers["jtc"]
    jtc.send_goal([{"t": 4.0, "segments": {"segment_1": {"kappa": 3.0, "phi": 0.0}}}], now=t)
    hwi = _Hwi(lim)
    m._t_last = t
    kx = 0.0
    while t < 2.5 - 1e-9:
        t += DT
        m.update(hwi, _state(t, [max(0.0, kx - lag), 0.0]), t)
        kx = hwi.cmd["segment_1"][0]
    return m, hwi, jtc, t


def test_a_stall_that_resumes_keeps_the_goal_and_continues_without_a_step():
    """Review 1 (sim4): the loop pauses 0.6 s (a stall: same chain, rediscovered), the segment
    sat at its last setpoint and is measured again there; the goal aborted "link loss:
    segment_1 … from the goal's path (> tolerance …)" — adopt_measured compared it with the
    path at the time the pause had not been taken out of yet (beyond even the path tolerance
    for a pause this long), and against goal_tolerance."""
    m, hwi, jtc, t = _motion_moving()
    goal = jtc.current_goal
    last = hwi.cmd["segment_1"][0]
    step_before = last - jtc._desired_now(t - DT)[0][0][0]
    t += 0.6 + DT  # the pause (the path would have run on ~0.7 1/m), then the next cycle
    hwi.first_measured = ["segment_1", "segment_2"]  # measured again after the gap
    m.update(hwi, _state(t, [last, 0.0]), t)
    hwi.first_measured = []
    assert goal.state == "executing", goal.reason
    assert jtc.current_goal is goal
    # the path continues from where it sat: one cycle's step, not the pause's
    assert hwi.cmd["segment_1"][0] - last == pytest.approx(step_before, abs=2e-3)
    for _ in range(400):
        t += DT
        m.update(hwi, _state(t, [hwi.cmd[n][0] for n in NAMES]), t)
    assert goal.state == "succeeded", goal.reason


def test_a_segment_measured_again_while_the_path_moves_it_is_judged_by_the_path_tolerance():
    """Review 1 (a loaded host, `ucr trajectory examples/wave.yaml` aborted "segment_2 …
    0.3015 1/m"): a segment re-measured mid-motion lags its command by the tracking error the
    path tolerance (0.5) allows; goal_tolerance (0.05) aborted the goal."""
    m, hwi, jtc, t = _motion_moving(lag=0.3)
    goal = jtc.current_goal
    t += DT
    hwi.first_measured = ["segment_1"]
    m.update(hwi, _state(t, [hwi.cmd["segment_1"][0] - 0.3, 0.0]), t)
    assert goal.state == "executing", goal.reason


def test_a_stall_that_resumes_far_from_the_path_still_aborts_and_holds_where_measured():
    """The safety rule stays: re-measured beyond the path tolerance, taking the segment back
    would be a jump: the goal ends (link_loss) and the segment holds where it is measured."""
    m, hwi, jtc, t = _motion_moving()
    goal = jtc.current_goal
    t += 0.1 + DT
    hwi.first_measured = ["segment_1"]
    far = hwi.cmd["segment_1"][0] - 0.8
    m.update(hwi, _state(t, [far, 0.0]), t)
    assert goal.state == "aborted" and goal.abort["cause"] == "link_loss"
    assert goal.abort["tolerance"] == pytest.approx(0.5)
    assert hwi.cmd["segment_1"] == pytest.approx((far, 0.0))


def test_a_segment_the_goal_holds_still_is_judged_by_the_goal_tolerance():
    lim = _limits()
    jtc = JointTrajectoryController("jtc", {}, ControllerContext(lim))
    jtc.on_activate(_state(0.0, [0.0, 0.0]))
    g = jtc.send_goal([{"t": 2.0, "segments": {"segment_1": {"kappa": 2.0}}}], now=0.0)
    jtc.adopt_measured(["segment_2"], _state(0.5, [jtc._desired_now(0.5)[0][0][0], 0.1]))
    assert g.state == "aborted" and g.abort["tolerance"] == pytest.approx(0.05), g.reason


# -- 2. a segment a new goal does not name stops as a cancel stops it ---------------------------


def _two_segment_jtc() -> JointTrajectoryController:
    c = JointTrajectoryController("jtc", {}, ControllerContext(_limits()))
    c.on_activate(_state(0.0, [0.0, 0.0]))
    c.send_goal([{"t": 2.0, "segments": {"segment_2": {"kappa": 3.0, "phi": 0}}}], now=0.0)
    return c


def test_a_segment_left_out_of_a_new_goal_stops_as_a_cancel_stops_it_and_never_comes_back():
    """Review 2 (sim6, t10): `ucr move --segment segment_1` while segment_2 moved: segment_2
    ran on 0.952 -> 2.120 and came back to 0.952 by itself; docs/api.md: "others hold"."""
    t1 = 0.8
    c = _two_segment_jtc()
    ref = _two_segment_jtc()
    ref.cancel(ref.current_goal.id, now=t1)  # the daemon's stop rule
    stop_end = ref._hold[1]
    p1, v1, _ = c._desired_now(t1)
    assert v1[1][0] > 2.0  # segment_2 is moving fast
    g = c.send_goal([{"t": 2.0, "segments": {"segment_1": {"kappa": 1.0, "phi": 0}}}], now=t1)
    assert c._traj.moving(list(NAMES), t1) == set(NAMES)  # stopping is moving (rebuild carry)
    kx2, kx1 = [], []
    t, meas = t1, [p1[0][0], p1[1][0]]
    while t < t1 + 2.5:
        cmd = c.update(_state(t, meas), DT)  # tracked perfectly
        meas = [cmd["segment_1"][0], cmd["segment_2"][0]]
        kx1.append(cmd["segment_1"][0])
        kx2.append(cmd["segment_2"][0])
        t += DT
    assert np.all(np.diff(kx2) >= -1e-12), "segment_2 turned round"
    assert kx2[-1] == pytest.approx(stop_end[0], abs=1e-9)  # where a cancel stops it
    assert max(kx2) == pytest.approx(stop_end[0], abs=1e-9)
    assert kx2[-1] - p1[1][0] < 0.5  # stopped within the stop ramp, not run on to 2.1
    assert np.diff(kx2)[int(c.stop_time / DT) + 1 :] == pytest.approx(0.0, abs=1e-12)  # then holds
    assert kx1[-1] == pytest.approx(1.0)  # the named segment does what the goal says
    assert g.state == "succeeded", g.reason


def test_a_left_out_segment_that_stops_keeps_its_stop_over_a_remap_and_a_replacement():
    c = _two_segment_jtc()
    c.send_goal([{"t": 1.0, "segments": {"segment_1": {"kappa": 1.0}}}], now=0.8)
    tr = c._traj
    same = tr.remapped(list(NAMES), list(NAMES), np.zeros((2, 2)))
    for t in np.linspace(0.8, 2.0, 25):
        assert np.array(same.position(t)) == pytest.approx(np.array(tr.position(t)))
    # a goal replacing it mid-stop starts from the stop's own velocity (no step)
    p, v, a = c._desired_now(0.9)
    assert v[1][0] > 0.0
    c.send_goal([{"t": 1.0, "segments": {"segment_1": {"kappa": 0.5}}}], now=0.9)
    p2, v2, _ = c._desired_now(0.9)
    assert np.allclose(p2, p) and np.allclose(v2, v)


# -- 3. the cFFC does not fold a loop pause into one step ---------------------------------------


def test_the_cffc_integrates_one_period_after_a_pause_not_the_pause():
    """Review 3 (sim3): after a 0.25 s pause the command stepped kx 0.250 -> 1.500."""
    lim = {"s1": BendableLimits("s1", 0.316, 3.314, 5.0)}
    cm = ControllerManager({"ffc": {"type": "ffc", "params": {}}}, ControllerContext(lim))
    st = RobotState(0.0, ["s1"], [0.0], [0.0], [0.0], [0.0], [True], [None], [True])
    cm.switch(["ffc"], [], st)
    ffc = cm.controllers["ffc"]
    t, prev = 0.0, 0.0
    for _ in range(5):
        t += DT
        st.t = t
        ffc.set_input({"s1": (1.0, 0.0)}, now=t)
        prev = cm.update(st, DT, DT)["s1"][0]
    t += 0.25
    st.t = t
    ffc.set_input({"s1": (1.0, 0.0)}, now=t - DT)
    step = cm.update(st, 0.25, DT)["s1"][0] - prev
    assert step == pytest.approx(5.0 * DT)  # one period at the full rate


# -- 4. the first waypoint's spacing is measured from the start ---------------------------------


def test_a_first_point_too_soon_is_said_to_be_too_soon_after_the_start():
    c = JointTrajectoryController("jtc", {}, ControllerContext(_limits()))
    c.on_activate(_state(0.0, [0.0, 0.0]))
    with pytest.raises(ControllerError) as exc:
        c.send_goal([{"t": 0.0005, "segments": {"segment_1": {"kappa": 0.1}}}], now=0.0)
    assert "0.5 ms after the start" in str(exc.value)
    with pytest.raises(ControllerError) as exc:
        c.send_goal(
            [{"t": 0.5, "segments": {"segment_1": {"kappa": 0.1}}},
             {"t": 0.5005, "segments": {"segment_1": {"kappa": 0.2}}}], now=0.0,
        )  # fmt: skip
    assert "point 2" in str(exc.value) and "after the previous point" in str(exc.value)


# -- 5. a restricted phi range: no flip of the bending plane ------------------------------------

PHI_RANGE = (-3 * math.pi / 4, 3 * math.pi / 4)  # [-135, 135] deg


def _polar(k: float, deg: float) -> tuple[float, float]:
    return k * math.cos(math.radians(deg)), k * math.sin(math.radians(deg))


def test_a_goal_whose_path_leaves_the_phi_range_between_waypoints_is_rejected():
    """Review 5 (sim2b): from phi = 120 deg to -120 deg (both allowed) the chord crosses
    180 deg; the goal was accepted and the HWI flipped the plane 135 -> -135 deg in a cycle."""
    lim = _limits(PHI_RANGE)
    c = JointTrajectoryController("jtc", {}, ControllerContext(lim))
    kx, ky = _polar(2.0, 120)
    c.on_activate(_state(0.0, [kx, 0.0], [ky, 0.0]))
    with pytest.raises(ControllerError) as exc:
        c.send_goal(
            [{"t": 2.0, "segments": {"segment_1": {"kappa": 2.0, "phi": math.radians(-120)}}}],
            now=0.0,
        )
    msg = str(exc.value)
    assert "segment_1" in msg and "leaves its phi range" in msg and "nothing moved" in msg
    assert " at t = " in msg and "deg) at t" in msg
    assert c.current_goal is None and c._traj is None  # nothing moves
    # through straight, or round inside the range: accepted
    for via in ({"kappa": 0.0}, {"kappa": 2.0, "phi": 0.0}):
        g = c.send_goal(
            [{"t": 1.0, "segments": {"segment_1": via}},
             {"t": 2.0, "segments": {"segment_1": {"kappa": 2.0, "phi": math.radians(-120)}}}],
            now=0.0,
        )  # fmt: skip
        assert g.state == "executing"


def test_the_hwi_clamps_phi_to_the_bound_nearer_around_the_circle():
    lim = _limits(PHI_RANGE)
    hwi = HardwareInterface(lim, link=None)
    hwi.state = ACTIVE
    for deg, bound in ((150, 135), (179, 135), (-179, -135), (-150, -135), (100, 100)):
        hwi.set_curvature("segment_1", *_polar(2.0, deg))
        assert math.degrees(hwi.command["segment_1/phi"]) == pytest.approx(bound), deg
    # exactly midway (180 deg): the bound nearer to the command it had, never a flip
    hwi.set_curvature("segment_1", *_polar(2.0, -130))
    hwi.set_curvature("segment_1", -2.0, 0.0)
    assert math.degrees(hwi.command["segment_1/phi"]) == pytest.approx(-135)
    hwi.set_command("segment_1/phi", 3.5)  # 3.5 rad = -160 deg: nearer -135 than 135
    assert hwi.command["segment_1/phi"] == pytest.approx(PHI_RANGE[0])


def test_the_cffc_setpoint_stays_in_the_phi_sector_and_slides_along_its_edge():
    lim = _limits(PHI_RANGE)
    ffc = FeedForwardController("ffc", {}, ControllerContext(lim))
    kx, ky = _polar(2.0, 130)
    ffc.on_activate(_state(0.0, [kx, 0.0], [ky, 0.0]))
    t = 0.0
    prev = (kx, ky)
    for _ in range(150):  # push towards phi = 180 deg (and beyond) for 1.5 s
        t += DT
        ffc.set_input({"segment_1": (-1.0, -0.2)}, now=t)
        cmd = ffc.update(_state(t, [0.0, 0.0]), DT)["segment_1"]
        phi = math.degrees(math.atan2(cmd[1], cmd[0]))
        assert -135 - 1e-6 <= phi <= 135 + 1e-6 or math.hypot(*cmd) < 1e-9, phi
        assert math.hypot(cmd[0] - prev[0], cmd[1] - prev[1]) <= 5.0 * DT + 1e-9  # no flip
        prev = cmd
    from host.limits import clamp_to_sector

    # exactly midway, the edge on the side the setpoint came from
    assert clamp_to_sector(-2.0, 0.0, *PHI_RANGE, prefer=_polar(1.0, -100))[1] < 0
    assert clamp_to_sector(-2.0, 0.0, *PHI_RANGE, prefer=_polar(1.0, 100))[1] > 0


def test_goals_replaced_before_they_start_do_not_break_the_cycle():
    """Code review of the stop-ramp change: a path asked for a time before its start (tau < 0:
    a goal replaced during its 50 ms lead, which a client streaming goal updates does) took the
    stop-ramp branch of a path without one and raised AttributeError in every cycle until the
    next goal started. Goals replaced every 20 ms with the daemon's 50 ms lead now run."""
    m, hwi, jtc, t = _motion_moving()
    k = 1.0
    for _ in range(5):  # as host/motion.py send_trajectory: start = now + 50 ms lead
        s = jtc.goal_snapshot(t + 0.05)
        g, tr = jtc.build_goal([{"t": 1.0, "segments": {"segment_1": {"kappa": k, "phi": 0.0}}}], s)
        jtc.install_goal(g, tr, s, t)
        k += 0.1
        for _ in range(2):
            t += DT
            jtc.update(_state(t, [hwi.cmd["segment_1"][0], 0.0]), DT)
    assert jtc.current_goal is not None and jtc.current_goal.state == "executing"
