"""Issue 12 finding 3: one coherent abort reason — the segment, the measured error, the tolerance
and the cause; never NaN, "?" or an error smaller than the tolerance it claims to exceed."""

from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from host.config import bendable_limits
from host.controllers.base import ControllerContext, RobotState
from host.controllers.jtc import JointTrajectoryController
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"
DT = 0.01


@pytest.fixture(scope="module")
def ctx():
    robot = load(ROBOT)
    return ControllerContext(bendable_limits(robot), robot, lambda msg: None)


def run(jtc, t1: float, invalid: set[str], follow: bool = True) -> None:
    """Step the controller from 0 to ``t1``; the plant follows the command exactly, but the
    segments in ``invalid`` send no valid state (their last known values, ``valid`` false)."""
    names = jtc.ctx.names
    meas = {n: (0.0, 0.0) for n in names}
    t = 0.0
    while t <= t1 + 1e-9:
        kx = [meas[n][0] for n in names]
        ky = [meas[n][1] for n in names]
        st = RobotState(
            t,
            list(names),
            kx,
            ky,
            [math.hypot(a, b) for a, b in zip(kx, ky, strict=True)],
            [math.atan2(b, a) for a, b in zip(kx, ky, strict=True)],
            [n not in invalid for n in names],
            [True] * len(names),
        )
        out = jtc.update(st, DT)
        if follow:
            meas.update({n: v for n, v in out.items() if n not in invalid})
        t += DT


def coherent(st: dict) -> dict:
    assert st["state"] == "aborted", st
    reason, ab = st["reason"], st["abort"]
    assert "nan" not in reason.lower() and "?" not in reason, reason
    assert ab is not None and ab["segment"] in ("segment_1", "segment_2", "segment_3"), st
    if ab["error"] is not None:
        assert math.isfinite(ab["error"]) and ab["error"] > ab["tolerance"], st
    for err, tol in re.findall(r"error ([\d.]+) 1/m > tolerance ([\d.]+) 1/m", reason):
        assert float(err) > float(tol), reason
    return ab


def test_goal_end_with_a_segment_without_valid_state_names_it_as_link_loss(ctx):
    # today: "goal tolerance not reached …: segment_1 error 0.000 1/m > 0.050 1/m"
    jtc = JointTrajectoryController("jtc", {"goal_time_tolerance": 0.2}, ctx)
    jtc.on_activate(RobotState.zeros(ctx.names, 0.0))
    g = jtc.send_goal(
        [{"time_from_start": 0.5, "segments": {n: {"kappa": 0.5} for n in ctx.names}}], 0.0
    )
    run(jtc, 1.5, {"segment_3"})
    ab = coherent(jtc.status_of(g.id))
    assert ab["cause"] == "link_loss" and ab["segment"] == "segment_3" and ab["error"] is None
    assert "segment_3" in g.reason and "segment_1 error" not in g.reason


def test_goal_end_with_no_valid_state_at_all_has_no_nan_and_no_question_mark(ctx):
    # today: "goal tolerance not reached …: ? error nan 1/m > 0.050 1/m"
    jtc = JointTrajectoryController("jtc", {"goal_time_tolerance": 0.2}, ctx)
    jtc.on_activate(RobotState.zeros(ctx.names, 0.0))
    g = jtc.send_goal([{"time_from_start": 0.5, "segments": {"segment_2": {"kappa": 0.5}}}], 0.0)
    run(jtc, 1.5, set(ctx.names))
    ab = coherent(jtc.status_of(g.id))
    assert ab["cause"] == "link_loss" and ab["segment"] == "segment_1"


def test_tolerance_aborts_carry_segment_error_tolerance_and_cause(ctx):
    jtc = JointTrajectoryController("jtc", {"path_tolerance": 0.2}, ctx)
    jtc.on_activate(RobotState.zeros(ctx.names, 0.0))
    g = jtc.send_goal([{"time_from_start": 2.0, "segments": {"segment_3": {"kappa": 2.0}}}], 0.0)
    run(jtc, 2.0, set(), follow=False)  # a stuck plant
    ab = coherent(jtc.status_of(g.id))
    assert ab["cause"] == "path_tolerance" and ab["segment"] == "segment_3"
    assert ab["tolerance"] == 0.2 and ab["error"] > 0.2

    jtc = JointTrajectoryController("jtc", {"path_tolerance": 0.0, "goal_time_tolerance": 0.2}, ctx)
    jtc.on_activate(RobotState.zeros(ctx.names, 0.0))
    g = jtc.send_goal([{"time_from_start": 0.5, "segments": {"segment_1": {"kappa": 1.0}}}], 0.0)
    run(jtc, 1.5, set(), follow=False)
    ab = coherent(jtc.status_of(g.id))
    assert ab["cause"] == "goal_tolerance" and ab["segment"] == "segment_1"
    assert ab["error"] == pytest.approx(1.0, abs=1e-3)


def test_aborts_from_the_daemon_parts_name_their_cause(ctx):
    jtc = JointTrajectoryController("jtc", {}, ctx)
    jtc.on_activate(RobotState.zeros(ctx.names, 0.0))
    for reason, cause in (
        ("topology changed: DOWNSTREAM_DOWN from position 2", "topology_change"),
        ("link lost: port vanished", "link_loss"),
        ("segment(s) segment_2 holding (watchdog or HOLD)", "segment_fault"),
        ("preempted by manual control (ffc)", "replaced"),
        ("daemon stopping", "stopped"),
    ):
        g = jtc.send_goal([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 0.3}}}])
        jtc.abort_active(reason)
        assert jtc.status_of(g.id)["abort"]["cause"] == cause, reason


def _state(names: list[str], t: float, kx1: float) -> RobotState:
    """segment_1 measured at (kx1, 0), the others at rest; all valid."""
    kx = [kx1 if n == "segment_1" else 0.0 for n in names]
    ky = [0.0] * len(names)
    return RobotState(
        t, list(names), kx, ky, [abs(x) for x in kx], [0.0] * len(names),
        [True] * len(names), [True] * len(names),
    )  # fmt: skip


def _shown_pair(reason: str) -> tuple[float, float]:
    """The (error, tolerance) a reason shows, whichever of the three phrasings it uses."""
    m = re.search(r"error ([\d.e+-]+) 1/m > tolerance ([\d.e+-]+) 1/m", reason) or re.search(
        r"([\d.e+-]+) 1/m from the goal's path \(> tolerance ([\d.e+-]+) 1/m\)", reason
    )
    assert m, reason
    return float(m[1]), float(m[2])


@pytest.mark.parametrize("kind", ["path_tolerance", "goal_tolerance", "link_loss"])
def test_an_error_just_over_its_tolerance_reads_larger_than_it(ctx, kind):
    """Audit of issue 12: ``.3f`` showed an error of tolerance + 1e-5 as "0.050 > 0.050"."""
    tol = 0.05
    params = {
        "path_tolerance": tol if kind == "path_tolerance" else 0.0,
        "goal_tolerance": tol,
        "goal_time_tolerance": 0.2,
    }
    jtc = JointTrajectoryController("jtc", params, ctx)
    names = ctx.names
    jtc.on_activate(RobotState.zeros(names, 0.0))
    g = jtc.send_goal([{"time_from_start": 0.5, "segments": {"segment_1": {"kappa": 0.0}}}], 0.0)
    off = tol + 1e-5  # the goal holds segment_1 at 0: measured here, its error is exactly this
    if kind == "link_loss":
        jtc.update(RobotState.zeros(names, 0.0), DT)
        jtc.adopt_measured(["segment_1"], _state(names, DT, off))
    else:
        t = 0.0
        while t <= 1.0 and jtc.status_of(g.id)["state"] != "aborted":
            jtc.update(_state(names, t, off), DT)
            t += DT
    st = jtc.status_of(g.id)
    ab = coherent(st)
    assert ab["cause"] == kind and ab["segment"] == "segment_1"
    assert ab["error"] == pytest.approx(off) and ab["tolerance"] == tol
    err, shown_tol = _shown_pair(st["reason"])
    assert err > shown_tol, st["reason"]
    assert shown_tol == tol, st["reason"]  # the tolerance as configured, not rounded
