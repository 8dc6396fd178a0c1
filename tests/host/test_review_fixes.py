"""Regression tests for the review findings on the daemon, HWI and controllers, on a fake chain
link (no firmware, no serial port): the loop keeps cycling while a long goal is built, segments
without a measurement are never commanded straight, finished goals drop their trajectory, …"""

from __future__ import annotations

import math
import threading

import pytest
from daemon_helpers import wait_for

import host.controllers.jtc as jtc_module
from host.config import DaemonConfig
from host.daemon import Daemon
from host.topology import chain_bendables, compare


class FakeLink:
    """Stands in for ``host.link.ChainLink``: answers DISCOVER with descriptors matching the
    robot, and SYNC/HEARTBEAT with a STATE per position at ``measured[pos]`` (kappa, phi).
    ``silent`` positions do not answer; every SYNC is recorded in ``syncs``."""

    def __init__(self, robot, measured: dict[int, tuple[float, float]] | None = None):
        self.names = chain_bendables(robot)
        self.descs = []
        for i, n in enumerate(self.names):
            b = robot.bendables[n]
            act = b.actuation
            self.descs.append(
                {
                    "position": i,
                    "uid": f"fake{i}",
                    "name": n,
                    "model": b.model.type,
                    "length": b.length,
                    "tendon_angles": list(act.angles),
                    "tendon_radius": act.radius,
                    "spool_radius": act.spool_radius,
                    "kappa_max": b.model.limits.kappa_max,
                    "kappa_rate_max": b.model.limits.kappa_rate_max,
                    "downstream_present": i < len(self.names) - 1,
                }
            )
        self.measured = dict(measured or {})
        self.silent: set[int] = set()
        self.syncs: list[tuple[list, bool]] = []
        self.heartbeats = 0
        self.cycle = 0
        self.lock = threading.Lock()
        self.stats: dict = {}

    def discover(self, timeout: float = 0.5) -> list[dict]:
        return [dict(d) for d in self.descs]

    def _states(self) -> list[dict | None]:
        out: list[dict | None] = []
        for i in range(len(self.names)):
            if i in self.silent:
                out.append(None)
                continue
            k, p = self.measured.get(i, (0.0, 0.0))
            out.append(
                {
                    "position": i,
                    "cycle": self.cycle,
                    "t_ms": self.cycle,
                    "kappa": k,
                    "phi": p,
                    "kx": k * math.cos(p),
                    "ky": k * math.sin(p),
                    "status": set(),
                }
            )
        return out

    def sync(self, setpoints, timeout=0.1, *, expected=None, resume=False):
        with self.lock:
            self.cycle += 1
            self.syncs.append((list(setpoints), resume))
            return self._states()

    def heartbeat(self, timeout=0.1, *, expected=None):
        with self.lock:
            self.cycle += 1
            self.heartbeats += 1
            return self._states()

    def hold(self, position=None) -> None:
        pass

    def events(self) -> list[dict]:
        return []

    def close(self) -> None:
        pass


@pytest.fixture()
def make_daemon(robot3):
    made: list[Daemon] = []

    def make(link: FakeLink, **cfg) -> Daemon:
        d = Daemon(
            robot3,
            DaemonConfig(**cfg) if cfg else DaemonConfig(),
            port="fake://chain",
            rate_hz=100.0,
            link_factory=lambda url, baud: link,
        )
        made.append(d)
        return d

    yield make
    for d in made:
        d.stop(hold=False)


def test_building_a_long_goal_does_not_stall_the_control_loop(robot3, make_daemon, monkeypatch):
    link = FakeLink(robot3)
    d = make_daemon(link).start()
    names = chain_bendables(robot3)
    # 1500 waypoints zig-zagging fast enough that every piece is retimed
    points = [
        {
            "time_from_start": 0.01 * (k + 1),
            "segments": {
                n: {"kappa": 1.0 + 0.8 * (k % 2), "phi": 0.3 * j} for j, n in enumerate(names)
            },
        }
        for k in range(1500)
    ]
    seen: list[int] = []
    real = jtc_module.CurvatureTrajectory

    def build_and_watch(*args, **kw):
        before = len(link.syncs)
        out = real(*args, **kw)
        # the loop must go on exchanging with the chain while the goal is being built
        wait_for(lambda: len(link.syncs) >= before + 3, 1.0)
        seen.append(len(link.syncs) - before)
        return out

    monkeypatch.setattr(jtc_module, "CurvatureTrajectory", build_and_watch)
    gid = d.send_trajectory(points)
    assert seen and seen[0] >= 3, f"loop made {seen} exchanges while the goal was built"
    st = d.trajectory_status(gid)
    assert st["state"] == "executing" and st["points"] == 1500 and st["retimed"]


def _jtc(robot3):
    from host.config import bendable_limits
    from host.controllers.base import ControllerContext, RobotState
    from host.controllers.jtc import JointTrajectoryController

    ctx = ControllerContext(bendable_limits(robot3), robot3)
    c = JointTrajectoryController("jtc", {}, ctx)
    n = len(ctx.names)
    c.on_activate(
        RobotState(0.0, ctx.names, [0.0] * n, [0.0] * n, [0.0] * n, [0.0] * n, [True] * n)
    )
    return c


def test_goal_built_while_the_motion_changed_is_refused_and_lead_in_has_no_jump(robot3):
    from host.controllers.jtc import StaleGoalError

    c = _jtc(robot3)
    pts = [{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 1.0, "phi": 0.0}}}]
    first = c.send_goal(pts, now=0.0)
    # a replacement planned to start at t = 0.5 while the first goal is moving
    start = c.goal_snapshot(0.5)
    goal, traj = c.build_goal(pts, start)
    c.cancel(first.id, now=0.3)  # the motion changes before it is installed
    with pytest.raises(StaleGoalError, match="changed its motion"):
        c.install_goal(goal, traj, start, 0.4)
    # built again from the new motion and installed ahead of its start: the old motion runs
    # until then, so the desired position is continuous across the hand-over
    start = c.goal_snapshot(0.5)
    goal, traj = c.build_goal(pts, start)
    before = c._desired_now(0.45)[0]
    c.install_goal(goal, traj, start, 0.45)
    assert c._desired_now(0.45)[0] == pytest.approx(before)
    assert c._desired_now(0.5)[0] == pytest.approx(start.p)
    # installing after the planned start of a moving motion would jump: refused
    c2 = _jtc(robot3)
    c2.send_goal(pts, now=0.0)
    start = c2.goal_snapshot(0.2)
    goal, traj = c2.build_goal(pts, start)
    with pytest.raises(StaleGoalError, match="longer than planned"):
        c2.install_goal(goal, traj, start, 0.25)


def _limits(robot3, **changes):
    import dataclasses

    from host.config import bendable_limits

    lim = bendable_limits(robot3)
    return {n: dataclasses.replace(b, **changes.get(n, {})) for n, b in lim.items()}


def test_segment_missing_at_activation_gets_hold_entries_then_its_measured_value(
    robot3, make_daemon
):
    link = FakeLink(robot3, measured={0: (1.0, 0.5), 1: (2.5, 1.2), 2: (0.5, -1.0)})
    link.silent = {1}  # segment_2's STATE is missing at configure/activate
    d = make_daemon(link).start()
    assert wait_for(lambda: len(link.syncs) >= 2, 2.0)
    link.silent = set()
    assert wait_for(lambda: len(link.syncs) >= 12, 2.0)
    d.stop(hold=False)
    entries = [sps[1] for sps, _ in link.syncs]
    assert entries[0] is None  # not measured yet: hold, never (0, 0)
    for e in entries:
        assert e is None or e == pytest.approx((2.5, 1.2), abs=1e-6), entries
    assert entries[-1] == pytest.approx((2.5, 1.2), abs=1e-6)
    # the other segments were held at their measured values throughout
    assert all(sps[0] == pytest.approx((1.0, 0.5)) for sps, _ in link.syncs)


def test_rebuilt_controllers_hold_a_missing_segment_at_its_last_known_state(robot3):
    from host.controllers.base import ControllerContext
    from host.controllers.ffc import FeedForwardController
    from host.controllers.jtc import JointTrajectoryController
    from host.hwi import HardwareInterface, robot_state_from

    link = FakeLink(robot3, measured={0: (1.0, 0.5), 1: (2.5, 1.2), 2: (0.5, -1.0)})
    lim = _limits(robot3)
    old = HardwareInterface(lim, link)
    old.configure()
    link.silent = {1}  # the rebuild's heartbeat misses segment_2
    hwi = HardwareInterface(lim, link, known=dict(zip(old.names, old.last_states, strict=True)))
    hwi.configure()
    hwi.activate()
    state = robot_state_from(hwi, 1.0)
    assert not state.valid[1] and state.known[1]
    assert (state.kappa[1], state.phi[1]) == pytest.approx((2.5, 1.2))
    ctx = ControllerContext(lim, robot3)
    jtc = JointTrajectoryController("jtc", {}, ctx)
    ffc = FeedForwardController("ffc", {}, ctx)
    jtc.on_activate(state)
    ffc.on_activate(state)
    want = (2.5 * math.cos(1.2), 2.5 * math.sin(1.2))
    assert jtc.update(state, 0.01)["segment_2"] == pytest.approx(want)
    assert ffc.update(state, 0.01)["segment_2"] == pytest.approx(want)
    hwi.write()  # not measured since activation: a hold entry, not (0, 0)
    assert link.syncs[-1][0][1] is None


def test_uncommanded_phi_keeps_its_measured_value_and_uncommanded_bendable_holds(robot3):
    from host.hwi import HardwareInterface

    link = FakeLink(robot3, measured={0: (1.0, 0.5), 1: (2.5, 1.2), 2: (0.5, -1.0)})
    lim = _limits(
        robot3,
        segment_1={"command_interfaces": ("kappa",)},
        segment_3={"command_interfaces": ()},
    )
    hwi = HardwareInterface(lim, link)
    hwi.configure()
    hwi.activate()
    hwi.set_command("segment_1/kappa", 2.0)
    hwi.write()
    sps = link.syncs[-1][0]
    assert sps[0] == pytest.approx((2.0, 0.5))  # phi measured at activation, not 0
    assert sps[1] == pytest.approx((2.5, 1.2))
    assert sps[2] is None  # no command interface: hold entry, not (0, 0)


def test_finished_goals_drop_their_trajectory_and_keep_their_status(robot3):
    from host.controllers.base import RobotState

    c = _jtc(robot3)
    names = c.ctx.names
    n = len(names)
    fast = [{"time_from_start": 0.1, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.0}}}]
    replaced = c.send_goal(fast, now=0.0)
    goal = c.send_goal(fast, now=0.05)
    assert replaced.state == "aborted" and replaced.trajectory is None
    running = goal.status()
    assert goal.trajectory is not None and running["retimed"]
    t, meas = 0.05, [[0.0, 0.0]] * n
    while not goal.status()["done"] and t < 5.0:
        st = RobotState(
            t,
            names,
            [m[0] for m in meas],
            [m[1] for m in meas],
            [math.hypot(*m) for m in meas],
            [math.atan2(m[1], m[0]) for m in meas],
            [True] * n,
        )
        out = c.update(st, 0.01)
        meas = [list(out[j]) for j in names]
        t += 0.01
    done = goal.status()
    assert done["state"] == "succeeded" and goal.trajectory is None
    for key in ("duration", "requested_duration", "retimed", "points"):
        assert done[key] == running[key]
    assert done["requested_duration"] == pytest.approx(0.1)
    assert replaced.status()["duration"] is not None


@pytest.mark.parametrize(
    ("times", "match"),
    [
        ([1e-200], "at least 1 ms between points"),
        ([0.5, 0.5 + 1e-6], "point 2: .* at least 1 ms between points"),
    ],
)
def test_waypoints_too_close_in_time_are_rejected_with_a_reason(robot3, times, match):
    from host.controllers.base import ControllerError

    c = _jtc(robot3)
    pts = [
        {"time_from_start": t, "segments": {"segment_1": {"kappa": 1.0 + k, "phi": 0.0}}}
        for k, t in enumerate(times)
    ]
    with pytest.raises(ControllerError, match=match):
        c.send_goal(pts, now=0.0)
    assert c.current_goal is None  # nothing moved


def test_nan_rate_ratio_is_retimed_not_skipped():
    import numpy as np

    from host.controllers.base import ControllerError
    from host.controllers.jtc import CurvatureTrajectory

    class NanOnce(CurvatureTrajectory):
        """A rate check that cannot tell on the first pass (NaN), then a fine one."""

        calls = 0

        def _rate_ratios(self):
            NanOnce.calls += 1
            return np.array([np.nan]) if NanOnce.calls == 1 else np.array([0.5])

    z = np.zeros((1, 2))
    tr = NanOnce(0.0, z, z, z, [(1.0, np.array([[0.2, 0.0]]))], np.array([5.0]))
    assert tr.retimed and tr.duration == pytest.approx(2.0)  # stretched, not accepted as is
    with pytest.raises(ControllerError, match="cannot be computed"):
        CurvatureTrajectory(0.0, z, z, z, [(1e-200, np.array([[1.0, 0.0]]))], np.array([1.0]))


def test_manual_takeover_survives_a_rebuild_while_the_manual_controller_stays_active(
    robot3, make_daemon
):
    link = FakeLink(robot3, measured={0: (1.0, 0.5), 1: (2.5, 1.2), 2: (0.5, -1.0)})
    d = make_daemon(link).start()
    res = d.ffc_input({"segment_1": [1.0, 0.0]})
    assert res["takeover"] is not None and d.status()["manual_control"] == ["ffc"]
    d.loop.stop()  # rebuild from this thread, as the loop would after a topology change
    descs = link.discover()
    d._build(descs, compare(d.full_robot, descs), "test rebuild")
    assert d.cm.get("ffc").active and not d.cm.get("jtc").active
    assert d.status()["manual_control"] == ["ffc"]
    rec = d.hand_back()
    assert rec["manual"] == "ffc" and "jtc" in rec["restarted"]
    assert d.cm.get("jtc").active and not d.cm.get("ffc").active
    # a takeover whose manual controller is no longer active is forgotten by a rebuild
    from host.arbitration import Takeover

    d.arb.takeovers["ffc"] = Takeover("ffc", ["jtc"])
    d._build(descs, compare(d.full_robot, descs), "test rebuild")
    assert d.status()["manual_control"] == []


def test_a_failed_start_leaves_no_controller_manager_so_a_retry_activates_the_controllers(
    robot3, make_daemon
):
    from host.daemon import DaemonError

    link = FakeLink(robot3)
    d = make_daemon(
        link,
        controllers={
            "jtc": {"type": "jtc", "params": {"rate_margin": 5.0}},
            "jsb": {"type": "jsb"},
        },
        active=["jsb", "jtc"],
    )
    with pytest.raises(DaemonError, match="rate_margin"):
        d.start()
    assert d.cm is None
    d.cfg.controllers["jtc"]["params"] = {}  # the operator fixes the configuration
    d.start()
    assert sorted(d.status()["active_controllers"]) == ["jsb", "jtc"]


def test_a_segment_silent_for_a_gap_gets_hold_entries_then_is_held_where_measured(robot3):
    """Issue 12 finding 2, at the one place the rule is enforced (docs/daemon.md "No motion
    without a command"): a segment whose STATEs stop for the gap keeps no command — its SYNC
    entries become hold entries while a controller's setpoint (here kappa 1.0, produced while
    the host could not see it) waits in the command interfaces — and when it answers again the
    HWI commands its measured pose, not that stale setpoint."""
    from host.hwi import HardwareInterface

    link = FakeLink(robot3, measured={0: (0.0, 0.0), 1: (0.0, 0.0), 2: (0.2, 0.0)})
    hwi = HardwareInterface(_limits(robot3), link)  # the default gap
    hwi.configure()
    hwi.activate()
    link.silent = {2}  # segment_3's replies stop (late or lost)
    for _ in range(hwi.gap_cycles):
        hwi.write()
        hwi.read()
    hwi.set_command("segment_3/kappa", 1.0)  # a goal goes on meanwhile
    for _ in range(5):
        hwi.write()
        hwi.read()
        assert link.syncs[-1][0][2] is None, link.syncs[-1][0]  # a hold entry, not kappa 1.0
    link.measured[2] = (0.3, 0.1)  # it answers again, where it drifted to
    link.silent = set()
    hwi.write()
    hwi.read()
    assert "segment_3" in hwi.first_measured  # every active controller re-anchors there
    hwi.write()
    assert link.syncs[-1][0][2] == pytest.approx((0.3, 0.1))  # held where measured


def test_a_full_garbage_collection_after_start_does_not_traverse_what_was_alive_at_start(
    robot3, make_daemon
):
    """A full (generation 2) collection holds the interpreter lock for every object it
    traverses: measured 30-90 ms in the running daemon, the control loop stopped meanwhile.
    Daemon.start() freezes what is alive then (host/realtime.freeze_heap), so a later
    collection traverses only what came after."""
    import gc

    ballast = [{"k": [i]} for i in range(50_000)]  # this process's objects: test modules etc.
    gc.collect()
    before = len(gc.get_objects(generation=2))
    try:
        make_daemon(FakeLink(robot3)).start()
        after = len(gc.get_objects(generation=2))
        assert after < before / 10, (before, after)
    finally:
        gc.unfreeze()  # the rest of the test process collects as before
    del ballast


def test_recent_events_keep_no_waypoint_lists_subscribers_get_them() -> None:
    """A goal's waypoints (2000 per event: ~10^4 objects) are not kept in the daemon's list of
    recent events, where 50 of them would be ~10^6 objects for every full collection."""
    from host.publisher import Fanout

    f = Fanout()
    q = f.subscribe(["event"])
    wps = [[0.1 * i, [[0.0, 0.0]]] for i in range(2000)]
    f.emit_event("goal_waypoints", "goal g: waypoints, part 2 of 2", goal="g", waypoints=wps)
    assert q.get_nowait()["waypoints"] is wps
    kept = f.recent_events[-1]
    assert kept["event"] == "goal_waypoints" and kept["goal"] == "g" and "waypoints" not in kept
