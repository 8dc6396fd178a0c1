"""Unit tests of the host controllers on pure state computations (no chain, no firmware):
cJTC sampling, limits, retiming, replacement without a jump, tolerances; cFFC rate mapping,
clamping and deadman on a recorded input stream; controller manager claims and switching;
arbitration (manual takeover and explicit hand-back)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from host.arbitration import Arbitrator
from host.config import bendable_limits
from host.controller_manager import ControllerManager, SwitchError
from host.controllers import controller_class, known_types
from host.controllers.base import ControllerContext, ControllerError, RobotState
from host.controllers.ffc import FeedForwardController
from host.controllers.jtc import CurvatureTrajectory, JointTrajectoryController
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"
DT = 0.01


@pytest.fixture(scope="module")
def robot():
    return load(ROBOT)


@pytest.fixture()
def ctx(robot):
    published: list[dict] = []
    c = ControllerContext(bendable_limits(robot), robot, published.append)
    c.published = published  # type: ignore[attr-defined]
    return c


def state_at(names, t, kx=None, ky=None) -> RobotState:
    n = len(names)
    kx = list(kx) if kx is not None else [0.0] * n
    ky = list(ky) if ky is not None else [0.0] * n
    kappa = [math.hypot(a, b) for a, b in zip(kx, ky, strict=True)]
    phi = [math.atan2(b, a) for a, b in zip(kx, ky, strict=True)]
    return RobotState(t, list(names), kx, ky, kappa, phi, [True] * n)


def run(ctrl, t0, t1, follow=True, names=None, start=None):
    """Step a controller from t0 to t1; the 'plant' follows the command exactly (one-cycle lag).
    Returns times and commands (T, J, 2)."""
    names = names or ctrl.ctx.names
    meas = dict(start or {n: (0.0, 0.0) for n in names})
    ts, cmds = [], []
    t = t0
    while t <= t1 + 1e-9:
        st = state_at(names, t, [meas[n][0] for n in names], [meas[n][1] for n in names])
        out = ctrl.update(st, DT)
        if follow:
            meas.update(out)
        ts.append(t)
        cmds.append([out[n] for n in ctrl.joints])
        t += DT
    return np.array(ts), np.array(cmds)


# -- cJTC ---------------------------------------------------------------------------------------


def test_trajectory_passes_waypoints_and_ends_at_rest():
    p0 = np.zeros((1, 2))
    knots = [(1.0, np.array([[1.0, 0.0]])), (2.0, np.array([[1.0, 1.0]]))]
    tr = CurvatureTrajectory(0.0, p0, p0.copy(), p0.copy(), knots, np.array([100.0]))
    assert not tr.retimed
    p, _, _ = tr.sample(1.0)
    assert np.allclose(p, [[1.0, 0.0]], atol=1e-9)
    p, v, a = tr.sample(2.5)
    assert np.allclose(p, [[1.0, 1.0]]) and np.allclose(v, 0) and np.allclose(a, 0)


def test_rate_limit_retimes_a_too_fast_goal():
    """3 1/m in 0.1 s needs far more than 5 1/m/s: the pieces are stretched until it holds."""
    p0 = np.zeros((1, 2))
    knots = [(0.1, np.array([[3.0, 0.0]]))]
    rate = np.array([5.0 * 0.95])
    tr = CurvatureTrajectory(0.0, p0, p0.copy(), p0.copy(), knots, rate)
    assert tr.retimed and tr.duration > 0.6
    ts = np.linspace(0, tr.duration, 2000)
    speeds = [np.hypot(*tr.sample(t)[1][0]) for t in ts]
    assert max(speeds) <= rate[0] * 1.001


def test_jtc_holds_measured_position_on_activation(ctx):
    jtc = JointTrajectoryController("jtc", {}, ctx)
    names = ctx.names
    jtc.on_activate(state_at(names, 0.0, [1.0, 0.5, 0.0], [0.0, 0.5, -1.0]))
    out = jtc.update(state_at(names, 0.01, [1.0, 0.5, 0.0], [0.0, 0.5, -1.0]), DT)
    assert out == {"segment_1": (1.0, 0.0), "segment_2": (0.5, 0.5), "segment_3": (0.0, -1.0)}


def test_jtc_interpolates_in_curvature_vector_so_phi_does_not_whip(ctx):
    """From kappa=1 at phi=0 to kappa=1 at phi=pi: the path crosses straight (kappa=0) along
    the x axis; ky stays 0 the whole way (interpolating phi would swing through ky != 0)."""
    jtc = JointTrajectoryController("jtc", {"joints": ["segment_1"]}, ctx)
    names = ctx.names
    start = {"segment_1": (1.0, 0.0), "segment_2": (0.0, 0.0), "segment_3": (0.0, 0.0)}
    jtc.on_activate(state_at(names, 0.0, [1.0, 0, 0], [0, 0, 0]))
    goal = jtc.send_goal(
        [{"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 1.0, "phi": math.pi}}}], 0.0
    )
    _, cmds = run(jtc, 0.0, 3.0, start=start)
    assert np.abs(cmds[:, 0, 1]).max() < 1e-9
    assert cmds[-1, 0, 0] == pytest.approx(-1.0, abs=1e-6)
    assert jtc.status_of(goal.id)["state"] == "succeeded"


def test_jtc_rejects_a_waypoint_beyond_kappa_max_with_reason(ctx):
    jtc = JointTrajectoryController("jtc", {}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    with pytest.raises(ControllerError, match=r"point 2\.segment_2: kappa 4 1/m exceeds kappa_max"):
        jtc.send_goal(
            [
                {"time_from_start": 1.0, "segments": {"segment_2": {"kappa": 1.0}}},
                {"time_from_start": 2.0, "segments": {"segment_2": {"kappa": 4.0}}},
            ],
            0.0,
        )
    assert jtc.current_goal is None


@pytest.mark.parametrize(
    ("points", "match"),
    [
        ([], "non-empty list"),
        ([{"time_from_start": 0.0, "segments": {"segment_1": {"kappa": 1}}}], "must be > 0"),
        ([{"time_from_start": 1.0, "segments": {"nope": {"kappa": 1}}}], "'nope' is not"),
        ([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": -1}}}], "kappa must be"),
        ([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": math.nan}}}], "kappa"),
        ([{"time_from_start": 1.0, "segment": {}}], "unknown key"),
        (
            [
                {"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 1}}},
                {"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1}}},
            ],
            "strictly increasing",
        ),
    ],
)
def test_jtc_bad_goals_are_rejected_with_a_clear_reason(ctx, points, match):
    jtc = JointTrajectoryController("jtc", {}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    with pytest.raises(ControllerError, match=match):
        jtc.send_goal(points, 0.0)


def test_jtc_commands_never_exceed_kappa_max_or_rate(ctx):
    """A goal at kappa_max with waypoints that would overshoot: command stays on the disc and
    the command rate stays below kappa_rate_max."""
    jtc = JointTrajectoryController("jtc", {}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    kmax = ctx.limits["segment_1"].kappa_max
    pts = [
        {"time_from_start": 0.3, "segments": {"segment_1": {"kappa": kmax, "phi": 0.0}}},
        {"time_from_start": 0.6, "segments": {"segment_1": {"kappa": kmax, "phi": 1.5}}},
        {"time_from_start": 0.9, "segments": {"segment_1": {"kappa": kmax, "phi": 3.0}}},
    ]
    jtc.send_goal(pts, 0.0)
    _, cmds = run(jtc, 0.0, 6.0)
    k = np.hypot(cmds[:, 0, 0], cmds[:, 0, 1])
    assert k.max() <= kmax + 1e-9
    rates = np.hypot(*np.diff(cmds[:, 0, :], axis=0).T) / DT
    assert rates.max() <= ctx.limits["segment_1"].kappa_rate_max * 1.001


def test_jtc_replacement_mid_way_has_no_jump_in_position_or_velocity(ctx):
    jtc = JointTrajectoryController("jtc", {"joints": ["segment_1"]}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    g1 = jtc.send_goal(
        [{"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.0}}}], 0.0
    )
    _, c1 = run(jtc, 0.0, 0.995)
    g2 = jtc.send_goal(
        [{"time_from_start": 1.5, "segments": {"segment_1": {"kappa": 1.0, "phi": 1.57}}}], 1.0
    )
    plant = {n: (0.0, 0.0) for n in ctx.names} | {"segment_1": tuple(c1[-1, 0])}
    _, c2 = run(jtc, 1.0, 3.0, start=plant)
    path = np.concatenate([c1[:, 0, :], c2[:, 0, :]])
    vel = np.diff(path, axis=0) / DT
    seam = len(c1) - 1  # vel[seam] is the step across the replacement
    assert np.abs(vel).max() < 5.0  # no position jump anywhere (a jump would be ~100 1/m/s)
    assert np.linalg.norm(vel[seam] - vel[seam - 1]) < 0.2  # no velocity step at the seam
    assert jtc.status_of(g1.id)["state"] == "aborted"
    assert "replaced by goal" in jtc.status_of(g1.id)["reason"]
    assert jtc.status_of(g2.id)["state"] in ("executing", "succeeded")


def test_jtc_path_tolerance_aborts_with_reason_and_holds_measured(ctx):
    jtc = JointTrajectoryController("jtc", {"path_tolerance": 0.2}, ctx)
    names = ctx.names
    jtc.on_activate(state_at(names, 0.0))
    g = jtc.send_goal(
        [{"time_from_start": 2.0, "segments": {"segment_3": {"kappa": 2.0, "phi": 0.0}}}], 0.0
    )
    # the plant does not move (a stuck segment): the error grows until the tolerance trips
    _, cmds = run(jtc, 0.0, 2.0, follow=False)
    st = jtc.status_of(g.id)
    assert st["state"] == "aborted"
    assert "path tolerance violated on segment_3" in st["reason"]
    assert np.allclose(cmds[-1], 0.0)  # holds the measured (unmoved) position


def test_jtc_goal_tolerance_not_reached_aborts(ctx):
    jtc = JointTrajectoryController("jtc", {"path_tolerance": 0.0, "goal_time_tolerance": 0.2}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    g = jtc.send_goal([{"time_from_start": 0.5, "segments": {"segment_1": {"kappa": 1.0}}}], 0.0)
    run(jtc, 0.0, 1.5, follow=False)
    st = jtc.status_of(g.id)
    assert st["state"] == "aborted" and "goal tolerance not reached" in st["reason"]


def test_jtc_cancel_decelerates_instead_of_stopping_dead(ctx):
    jtc = JointTrajectoryController("jtc", {"joints": ["segment_1"], "stop_time": 0.3}, ctx)
    jtc.on_activate(state_at(ctx.names, 0.0))
    g = jtc.send_goal([{"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 3.0}}}], 0.0)
    _, c1 = run(jtc, 0.0, 0.995)
    assert jtc.cancel(g.id, 1.0)
    _, c2 = run(jtc, 1.0, 2.0)
    path = np.concatenate([c1[:, 0, 0], c2[:, 0, 0]])
    vel = np.diff(path) / DT
    assert abs(vel[len(c1)] - vel[len(c1) - 2]) < 0.3  # no velocity step at the cancel
    assert abs(vel[-1]) < 1e-9  # at rest after stop_time
    assert jtc.status_of(g.id)["state"] == "canceled"


# -- cFFC ---------------------------------------------------------------------------------------

# A recorded stick stream: (t s, deflection x, y) for segment_1, then the stick stops sending.
RECORDED = [(0.00, 1.0, 0.0), (0.10, 1.0, 0.0), (0.20, 0.5, 0.5), (0.30, 0.0, 1.0), (0.40, 0, 0)]


def test_ffc_rate_follows_deflection_scaled_by_kappa_rate_max(ctx):
    ffc = FeedForwardController("ffc", {"deadzone": 0.0, "deadman_timeout": 1.0}, ctx)
    ffc.on_activate(state_at(ctx.names, 0.0))
    ffc.set_input({"segment_1": (1.0, 0.0)}, now=0.0)
    out = ffc.update(state_at(ctx.names, 0.01), 0.01)
    assert out["segment_1"] == pytest.approx((5.0 * 0.01, 0.0))
    ffc.set_input({"segment_1": (0.0, -0.5)}, now=0.01)
    out = ffc.update(state_at(ctx.names, 0.02), 0.01)
    assert out["segment_1"] == pytest.approx((0.05, -2.5 * 0.01))
    assert out["segment_2"] == (0.0, 0.0)


def test_ffc_recorded_stream_then_deadman_stops_motion(ctx):
    ffc = FeedForwardController("ffc", {"deadman_timeout": 0.3}, ctx)
    ffc.on_activate(state_at(ctx.names, 0.0))
    cmds = []
    events = list(RECORDED[:-1])  # the last sample never arrives: the stick stream dies
    t = 0.0
    while t < 1.2:
        while events and events[0][0] <= t + 1e-9:
            _, x, y = events.pop(0)
            ffc.set_input({"segment_1": (x, y)}, now=t)
        cmds.append(ffc.update(state_at(ctx.names, t), DT)["segment_1"])
        t += DT
    cmds = np.array(cmds)
    moving = np.hypot(*np.diff(cmds, axis=0).T)
    assert moving[:30].min() > 0  # moves while input streams
    assert ffc.deadman_tripped
    last_input, timeout = RECORDED[-2][0], 0.3
    stop_idx = int(round((last_input + timeout) / DT)) + 2
    assert np.all(moving[stop_idx:] == 0.0)  # stopped after the deadman timeout


@pytest.mark.parametrize(
    ("source", "described"),
    [
        (None, None),
        ("127.0.0.1:4000", None),  # not a mapping: not said
        ({"peer": "127.0.0.1:4000", "client": "ucr view", "for": "view page=1"},
         {"peer": "127.0.0.1:4000", "client": "ucr view", "for": "view page=1"}),
        ({"peer": "[::1]:5", "token": "operator", "for": 7, "x": "y"}, {"peer": "[::1]:5"}),
        ({"client": "c" * 500}, {"client": "c" * 80}),
        ({"for": None}, None),
    ],
    ids=["none", "not-a-mapping", "all", "unknown-and-non-strings-dropped", "cut", "empty"],
)  # fmt: skip
def test_ffc_describes_who_sent_its_latest_input_and_only_that(ctx, source, described):
    """The cFFC's description names the sender of its latest input (``input_from``), so a
    client (ucr view) can tell its own input from another's exactly; whatever the caller gives,
    only short strings under the known keys are kept (no token label: any client reads it)."""
    ffc = FeedForwardController("ffc", {}, ctx)
    ffc.on_activate(state_at(ctx.names, 0.0))
    assert ffc.describe()["input_from"] is None
    ffc.set_input({"segment_1": (0.5, 0.0)}, now=0.0, source=source)
    assert ffc.describe()["input_from"] == described
    # the next input replaces it, also when that one says nothing
    ffc.set_input({"segment_1": (0.0, 0.0)}, now=0.1)
    assert ffc.describe()["input_from"] is None


def test_ffc_describes_its_setpoint_only_while_active(ctx):
    """A client steering the cFFC (ucr view's sliders) reads its setpoint instead of modelling
    it: the integrated commanded curvature vector, [kx, ky] per bendable; none while inactive
    (then it is stale: an activation starts from the measured state)."""
    ffc = FeedForwardController("ffc", {"deadzone": 0.0}, ctx)
    assert ffc.describe()["setpoint"] is None
    ffc.on_activate(state_at(ctx.names, 0.0))
    assert ffc.describe()["setpoint"] == {n: [0.0, 0.0] for n in ctx.names}
    ffc.set_input({"segment_1": (1.0, 0.0)}, now=0.0)
    for k in range(1, 11):
        ffc.update(state_at(ctx.names, k * 0.01), 0.01)
    sp = ffc.setpoint()
    assert sp["segment_1"] == pytest.approx([0.5, 0.0])  # 5 1/m/s for 0.1 s
    assert ffc.describe()["setpoint"] == sp
    ffc.on_deactivate()
    assert ffc.describe()["setpoint"] is None


def test_ffc_clamps_at_kappa_max(ctx):
    # the input streams, as a client sends it (a deadman beyond 2 s is refused since 2026-11-27)
    ffc = FeedForwardController("ffc", {"deadman_timeout": 0.3}, ctx)
    ffc.on_activate(state_at(ctx.names, 0.0))
    for i in range(300):
        ffc.set_input({"segment_2": (0.6, 0.8)}, now=i * DT)
        out = ffc.update(state_at(ctx.names, i * DT), DT)
    kmax = ctx.limits["segment_2"].kappa_max
    assert math.hypot(*out["segment_2"]) == pytest.approx(kmax)
    assert ffc.clamped


@pytest.mark.parametrize(
    ("rates", "match"),
    [
        ({"segment_1": (2.0, 0.0)}, "outside"),
        ({"x": (0, 0)}, "not commanded"),
        ({"segment_1": (math.inf, 0)}, "finite"),
        ({"segment_1": 1.0}, "expected"),
    ],
)
def test_ffc_bad_input_is_an_error(ctx, rates, match):
    ffc = FeedForwardController("ffc", {}, ctx)
    with pytest.raises(ControllerError, match=match):
        ffc.set_input(rates)


# -- controller manager and arbitration ------------------------------------------------------


SPECS = {
    "jtc": {"type": "jtc", "params": {}},
    "jtc12": {"type": "jtc", "params": {"joints": ["segment_1", "segment_2"]}},
    "ffc": {"type": "ffc", "params": {}},
    "jsb": {"type": "jsb", "params": {"rate_hz": 10.0}},
}


def test_registry_knows_the_paper_controllers():
    assert {"jtc", "ffc", "jsb", "rsp", "cJTC"} <= set(known_types())
    assert controller_class("cJTC") is JointTrajectoryController
    with pytest.raises(ControllerError, match="unknown controller type 'nope'"):
        controller_class("nope")


def test_manager_claims_are_exclusive_and_conflicts_name_the_holder(ctx):
    cm = ControllerManager(SPECS, ctx)
    st = state_at(ctx.names, 0.0)
    cm.switch(["jtc", "jsb"], [], st)
    assert cm.claims()["segment_3/phi"] == "jtc"
    with pytest.raises(SwitchError, match="'segment_1/kappa' is claimed by 'jtc'"):
        cm.switch(["jtc12"], [], st)
    assert cm.active_names() == ["jtc", "jsb"]  # the failed switch changed nothing
    res = cm.switch(["jtc12"], ["jtc"], st)
    assert res == {"started": ["jtc12"], "stopped": ["jtc"]}
    assert "segment_3/kappa" not in cm.claims()
    with pytest.raises(SwitchError, match="unknown controller 'zzz'"):
        cm.switch(["zzz"], [], st)


def test_manager_reports_a_broken_controller_without_breaking_the_rest(ctx):
    specs = {**SPECS, "bad": {"type": "jtc", "params": {"bogus": 1}}}
    cm = ControllerManager(specs, ctx)
    assert "bad" in cm.failed and "unknown parameter" in cm.failed["bad"]
    states = {d["name"]: d["state"] for d in cm.describe()}
    assert states["bad"] == "failed" and states["jtc"] == "inactive"


def test_broadcaster_publishes_joint_states_at_its_rate(ctx):
    cm = ControllerManager(SPECS, ctx)
    cm.switch(["jsb"], [], state_at(ctx.names, 0.0))
    for i in range(100):  # 1 s at 100 Hz
        cm.update(state_at(ctx.names, i * DT, [0.1, 0.2, 0.3]), DT)
    msgs = [m for m in ctx.published if m["kind"] == "joint_states"]
    assert 9 <= len(msgs) <= 11
    assert msgs[-1]["names"] == ctx.names and msgs[-1]["kappa"][2] == pytest.approx(0.3)


def test_manual_input_takes_over_from_a_trajectory_and_hands_back_explicitly(ctx):
    cm = ControllerManager(SPECS, ctx)
    arb = Arbitrator()
    st = state_at(ctx.names, 0.0)
    cm.switch(["jtc"], [], st)
    jtc = cm.controllers["jtc"]
    g = jtc.send_goal([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1}}}], 0.0)
    assert arb.manual_input(cm, "ffc", deflected=False, state=st) is None  # deadzone: no change
    rec = arb.manual_input(cm, "ffc", deflected=True, state=st)
    assert rec["preempted"] == ["jtc"] and rec["aborted_goals"] == [g.id]
    assert jtc.status_of(g.id)["reason"] == "preempted by manual control ('ffc')"
    assert cm.active_names() == ["ffc"]
    assert arb.blocking_manual(cm, "jtc") == "ffc"
    back = arb.hand_back(cm, "ffc", st)
    assert back["restarted"] == ["jtc"] and cm.active_names() == ["jtc"]


@pytest.mark.parametrize("target", [{"kx": 0.5}, {"ky": 1.0}, {"kx": 0.1, "ky": 0.1, "phi": 0.3}])
def test_a_waypoint_with_half_a_curvature_vector_is_rejected_not_completed_with_zero(robot, target):
    """Review 2026-11-26: in-process callers (the API validates too) got a missing kx/ky as 0."""
    from host.controllers.waypoints import parse_waypoints

    names = list(robot.bendables)
    pts = [{"time_from_start": 1.0, "segments": {"segment_1": target}}]
    with pytest.raises(ControllerError, match="give both kx and ky"):
        parse_waypoints(pts, np.zeros((len(names), 2)), names, bendable_limits(robot), "jtc")


def test_a_refusal_shows_enough_digits_to_tell_kappa_from_kappa_max(robot):
    """Review 2026-11-26: `ucr move --kappa 3.314` said "kappa 3.314 1/m exceeds kappa_max
    3.314 1/m" (the limit is 3.3139163...)."""
    from host.controllers.waypoints import parse_waypoints

    names = list(robot.bendables)
    pts = [{"time_from_start": 1.0, "segments": {"segment_2": {"kappa": 3.314, "phi": 0.0}}}]
    with pytest.raises(ControllerError) as ei:
        parse_waypoints(pts, np.zeros((len(names), 2)), names, bendable_limits(robot), "jtc")
    assert "kappa 3.314 1/m exceeds kappa_max 3.3139 1/m" in str(ei.value)
