"""Defects of `ucr zenoh` and `ucr zenoh-router` from the review of 2026-11-27, each with the
behaviour before its fix: TF's namespaced topics undocumented for tf2 tools, MoveIt's start
state at time 0 refused, the router reading the session's configuration variable, option values
no run could mean taken (tracebacks, silent exits, /tf off), commands without a publisher GID
sent, the empty-trajectory claim about ROS 2's JTC, and the action's request bound fixed at start.
Zenoh sessions here are local (no router, no network)."""

from __future__ import annotations

import re
import signal
import threading
import time

import pytest

from tests.cli_run import run_ucr

pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")
zenoh = pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")

from host.api.client import ApiError  # noqa: E402
from host.api.schema import RequestError, validate_points  # noqa: E402
from interop.ros2 import actions  # noqa: E402

from .conftest import REPO, ucr, wait_for  # noqa: E402
from .test_zenoh_bridge_parts import ATT, BENDABLES, FJT, FakeDaemon, Log, call, jt_bytes  # noqa: E402
from .zenoh_query import isolated_session  # noqa: E402

DOC = REPO / "docs" / "ros2.md"
S1 = ["segment_1/kappa", "segment_1/phi"]


class StrictDaemon(FakeDaemon):
    """:class:`FakeDaemon` that checks waypoints as the real daemon does (the API's
    ``validate_points``: a time of 0 is refused) and reports a measured state."""

    def __init__(self, measured: dict | None = None) -> None:
        super().__init__()
        self.measured = measured or {
            b: {"kappa": 1.0, "phi": 0.0, "valid": True} for b in BENDABLES
        }

    def send_trajectory(self, points, wait=False, controller=None):
        try:
            validate_points(points)
        except RequestError as exc:
            raise ApiError(exc.code, exc.message) from None
        return super().send_trajectory(points, wait, controller)

    def status(self):
        return {**super().status(), "joint_states": self.measured}


@pytest.fixture
def session():
    with isolated_session() as s:
        yield s


@pytest.fixture
def commands():
    from interop.zenoh.commands import SentGoals, TrajectoryCommands

    daemon, log = StrictDaemon(), Log()
    cmds = TrajectoryCommands(daemon, BENDABLES, controller="jtc", report=log, sent=SentGoals())
    try:
        yield cmds, daemon, log
    finally:
        cmds.close()


@pytest.fixture
def action(session):
    from interop.zenoh.action import FollowJointTrajectoryServer
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="ucr_bridge", namespace="/review_robot")
    daemon, log = StrictDaemon(), Log()
    server = FollowJointTrajectoryServer(
        node, daemon, BENDABLES, controller="jtc", report=log, period_s=0.02
    )
    try:
        yield server, daemon, log, session
    finally:
        server.close()
        node.close()


# ---------------------------------------------------------------- 1: TF namespaced, tf2 remaps
def test_every_tf2_tool_in_the_docs_gets_the_tf_remaps():
    """Before: `rviz2  # RobotModel: …; TF` without remaps. The bridge publishes /<ns>/tf and
    /<ns>/tf_static (several robots must not mix), tf2 listeners read /tf and /tf_static: that
    RViz showed no transforms. Every rviz2 / tf2 command of docs/ros2.md now remaps both."""
    text = DOC.read_text()
    commands = [
        ln for ln in text.splitlines()
        if re.match(r"\s*(rviz2|ros2 run (tf2_ros|rviz2) )", ln)
    ]  # fmt: skip
    assert any(c.lstrip().startswith("rviz2") for c in commands), commands
    assert any("tf2_echo" in c for c in commands), commands
    for c in commands:
        assert "--ros-args -r /tf:=/softrobot3/tf -r /tf_static:=/softrobot3/tf_static" in c, c
    assert "**TF is namespaced**" in text  # and why: several robots on one network
    from interop.zenoh.bridge import relative

    assert relative("/tf") == "tf" and relative("/tf_static") == "tf_static"  # kept namespaced


# ---------------------------------------------------------------- 2: MoveIt's start state
def test_a_trajectory_whose_first_point_is_the_start_state_at_time_0_is_taken(commands):
    """Before: the first point's time_from_start 0 went to the daemon, which refuses it
    (`points[0].time_from_start: must be > 0`): every MoveIt trajectory (its first point is the
    start state at 0) was refused. Now that point is not sent; it is where the robot is: no
    warning."""
    cmds, daemon, log = commands
    cmds.on_message(jt_bytes(S1, [(0, [1.0, 0.0]), (2, [2.0, 0.5])]), ATT)
    assert wait_for(lambda: daemon.sent or log.has("refused"), 10), log.lines
    assert daemon.sent == [
        [{"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.5}}}]
    ], log.lines
    assert not [t for lv, t in log.lines if lv >= 30], log.lines
    assert log.has("1 points after the start state")


def test_a_start_state_away_from_the_robot_is_not_jumped_to_and_says_so(commands):
    """Not silent: a start state farther than the tolerance from the measured state gives a
    WARN saying the trajectory starts from the measured state; still no jump (not sent)."""
    cmds, daemon, log = commands
    cmds.on_message(jt_bytes(S1, [(0, [3.0, 1.0]), (2, [2.0, 0.5])]), ATT)
    assert wait_for(lambda: daemon.sent, 10), log.lines
    assert [p["time_from_start"] for p in daemon.sent[-1]] == [2.0]
    [(level, text)] = [(lv, t) for lv, t in log.lines if lv == 30]
    assert "points[0] (time_from_start 0, the start state) is not where the robot is" in text
    assert "segment_1" in text and "starts from the measured state instead" in text


def test_time_zero_is_refused_anywhere_but_the_first_point(commands):
    """A point at 0 after the first, or a start state alone, is refused (nothing sent), named
    by its index in the message; a daemon's refusal after a dropped start says how it counts."""
    cmds, daemon, log = commands
    cmds.on_message(jt_bytes(S1, [(0, [1.0, 0.0]), (0, [2.0, 0.5])]), ATT)
    assert wait_for(lambda: log.has("refused"), 10), log.lines
    assert log.has("points[1].time_from_start: must be > 0 (only points[0], the start state")
    log.lines.clear()
    cmds.on_message(jt_bytes(S1, [(0, [1.0, 0.0])]), ATT)
    assert wait_for(lambda: log.has("refused"), 10), log.lines
    assert log.has("only a start state (points[0] at time_from_start 0): no point to move to")
    log.lines.clear()
    cmds.on_message(jt_bytes(S1, [(0, [1.0, 0.0]), (3, [2.0, 0.5]), (2, [2.0, 0.4])]), ATT)
    assert wait_for(lambda: log.has("refused"), 10), log.lines
    assert log.has("times must increase strictly") and log.has("is the message's points[i+1]")
    assert daemon.sent == []


def test_an_action_goal_from_moveit_with_its_start_state_is_accepted(action):
    """The same for FollowJointTrajectory (MoveIt's controller interface): before, not accepted
    (the daemon refused time 0)."""
    server, daemon, log, session = action
    traj = {"joint_names": S1, "points": [
        {"positions": [1.0, 0.0], "time_from_start": {"sec": 0}},
        {"positions": [2.0, 0.5], "time_from_start": {"sec": 2}}]}  # fmt: skip
    req = {"goal_id": {"uuid": list(range(1, 17))}, "goal": {"trajectory": traj}}
    data = actions.codec(FJT, "SendGoal_Request").encode(req)
    assert call(server, session, "send_goal", data).accepted is True, log.lines
    assert [p["time_from_start"] for p in daemon.sent[-1]] == [2.0]


# ---------------------------------------------------------------- 3: the router's variable
def test_the_router_reads_zenoh_router_config_uri_not_the_session_variable(tmp_path):
    """Before: `ucr zenoh-router` read $ZENOH_SESSION_CONFIG_URI (the nodes' file: a router run
    as a session's client) and ignored $ZENOH_ROUTER_CONFIG_URI, which rmw_zenohd reads."""
    from interop.zenoh import config, router

    class Args:
        connect = listen = zenoh_config = None
        multicast_scouting = False

    missing = str(tmp_path / "missing.json5")
    opts = router.options(Args())
    config.build(opts, environ={"ZENOH_SESSION_CONFIG_URI": missing})  # not read
    with pytest.raises(config.ZenohConfigError, match=r"^\$ZENOH_ROUTER_CONFIG_URI: .*no such"):
        config.build(opts, environ={"ZENOH_ROUTER_CONFIG_URI": missing})
    session_opts = config.SessionOptions()  # `ucr zenoh` keeps the session's variable
    config.build(session_opts, environ={"ZENOH_ROUTER_CONFIG_URI": missing})
    with pytest.raises(config.ZenohConfigError, match=r"^\$ZENOH_SESSION_CONFIG_URI: "):
        config.build(session_opts, environ={"ZENOH_SESSION_CONFIG_URI": missing})
    # the command: one line, exit 2, nothing opened (before: it ran its second and exited 0)
    res = run_ucr("zenoh-router", "--listen", "tcp/127.0.0.1:0", "--duration", "1",
                  env={"ZENOH_ROUTER_CONFIG_URI": missing})  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"ucr: $ZENOH_ROUTER_CONFIG_URI: Zenoh configuration file {missing}: no such file"
    ]
    assert "$ZENOH_ROUTER_CONFIG_URI" in run_ucr("zenoh-router", "--help").stdout


# ---------------------------------------------------------------- 4, 5, 6: option values
@pytest.mark.parametrize(
    ("argv", "says"),
    [
        # before: connected, then a ConfigError traceback (no upper bound)
        (["zenoh", "--subdivisions", "1001"], "argument --subdivisions: must be <= 1000, got 1001"),
        # before: -1, 0, nan exited 0 at once; inf/1e400 an OverflowError traceback
        (["zenoh", "--duration", "-1"], "argument --duration: must be a finite number of s > 0"),
        (["zenoh", "--duration", "0"], "argument --duration: must be a finite number of s > 0"),
        (["zenoh", "--duration", "nan"], "argument --duration: must be a finite number of s > 0"),
        (["zenoh", "--duration", "inf"], "argument --duration: must be a finite number of s > 0"),
        (["zenoh-router", "--duration", "0"], "argument --duration: must be a finite number"),
        (["zenoh-router", "--duration", "1e400"], "argument --duration: must be a finite number"),
        # before: /tf and /ucr/arcs silently off for good
        (["zenoh", "--viz-rate", "0"], "argument --viz-rate: must be a finite number of Hz > 0"),
        (["zenoh", "--viz-rate", "-5"], "argument --viz-rate: must be a finite number of Hz > 0"),
        (["zenoh", "--viz-rate", "nan"], "argument --viz-rate: must be a finite number of Hz > 0"),
    ],
)  # fmt: skip
def test_option_values_no_run_could_mean_are_usage_errors(argv, says):
    """Exit 2 and argparse's one line before anything opens (no daemon at that URL is asked; a
    router that did start, as before, would listen on a free port, not the default 7447)."""
    extra = ["--url", "ws://127.0.0.1:9"] if argv[0] == "zenoh" else ["--listen", "tcp/127.0.0.1:0"]
    res = run_ucr(*argv, *extra)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert says in res.stderr.strip().splitlines()[-1]
    assert "daemon" not in res.stderr


def test_a_huge_duration_waits_without_a_traceback():
    """--duration 1e300 is finite and > 0, but beyond what threading can wait: the router died
    with an OverflowError traceback, the bridge's timer thread printed one. Both wait at most
    threading.TIMEOUT_MAX (about 292 years) instead."""
    from interop.zenoh.bridge import stop_after

    errors: list = []
    old, threading.excepthook = threading.excepthook, errors.append
    try:
        stop = threading.Event()
        timer = stop_after(1e300, stop)
        time.sleep(0.3)
        assert errors == [] and timer is not None and timer.is_alive() and not stop.is_set()
        timer.cancel()
    finally:
        threading.excepthook = old
    proc = ucr("zenoh-router", "--listen", "tcp/127.0.0.1:0", "--duration", "1e300")
    try:
        line = proc.stderr.readline()
        assert line.startswith("ucr: Zenoh router "), line
        time.sleep(0.5)
        assert proc.poll() is None  # still running: it waits
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0 and "Traceback" not in err, err


# ---------------------------------------------------------------- 7: no publisher GID
def test_a_command_without_a_publisher_gid_is_refused_with_one_warning_per_burst(commands):
    """Before: a JointTrajectory without rmw_zenoh's attachment (a plain Zenoh put) was sent to
    the daemon, audited as publisher=unknown. Now refused, counted, one WARN per burst."""
    cmds, daemon, log = commands
    msg = jt_bytes(S1, [(2, [2.0, 0.5])])
    for _ in range(5):
        cmds.on_message(msg)
    assert wait_for(lambda: log.lines, 10)
    time.sleep(0.3)
    assert daemon.sent == [] and cmds.unattributed == 5 and cmds.refused == 5
    [(level, text)] = log.lines
    assert level == 30 and text.startswith("JointTrajectory refused (no rmw_zenoh attachment)")
    cmds.on_message(msg, ATT)  # a ROS 2 publisher's message: sent, and ends the burst
    assert wait_for(lambda: daemon.sent, 10)
    cmds.on_message(msg)
    assert wait_for(lambda: len([1 for lv, _ in log.lines if lv == 30]) == 2, 10), log.lines


def test_the_command_subscription_refuses_samples_without_a_valid_attachment(session):
    """Over Zenoh: a sample with no attachment or a malformed one never reaches the command
    callback (before: delivered with None, then sent); one with rmw_zenoh's does."""
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="ucr_bridge", namespace="/review_robot")
    got, refused = [], []
    try:
        sub = node.subscription(
            "jtc/joint_trajectory",
            "trajectory_msgs/msg/JointTrajectory",
            lambda data, att: got.append(att),
            unattributed=refused.append,
        )
        session.put(sub.key, b"x")
        session.put(sub.key, b"x", attachment=b"\x01\x02")
        session.put(sub.key, b"x", attachment=ATT.encode())
        assert wait_for(lambda: got and len(refused) == 2, 10), (got, refused)
        assert got == [ATT] and sub.refused == 2 and sub.bad_attachments == 1
        assert refused[0] == "no rmw_zenoh attachment"
        assert refused[1].startswith("bad rmw_zenoh attachment: ")
    finally:
        node.close()


# ---------------------------------------------------------------- 8: empty trajectory claim
def test_the_docs_do_not_claim_ros_2_jtc_stops_on_an_empty_trajectory():
    """Before: "stops what this bridge's commands started, as the JTC does with an empty
    trajectory"; ROS 2's JTC rejects one (stopping was ROS 1's). The stop is kept, said as a
    difference, with why."""
    text = " ".join(DOC.read_text().split())
    assert "as the JTC does with an empty trajectory" not in text
    differs = "**This differs from ROS 2's joint trajectory controller**, which rejects an empty"
    assert differs in text
    from interop.zenoh import commands

    assert "the JTC's convention for an empty trajectory" not in commands.__doc__


# ---------------------------------------------------------------- 9: the action's bound follows
def test_the_send_goal_bound_follows_the_robot_after_a_reconnect(session):
    """Before: the send_goal request bound was the first robot's for good; the bridge's
    reconnect to a robot with more bendables updated the joints but not the bound, so a goal
    that robot's daemon would take was refused unread."""
    from interop.zenoh.action import FollowJointTrajectoryServer
    from interop.zenoh.commands import ENVELOPE_BYTES, max_trajectory_bytes
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="ucr_bridge", namespace="/review_robot")
    daemon, log = FakeDaemon(), Log()
    server = FollowJointTrajectoryServer(node, daemon, BENDABLES[:1], controller="jtc", report=log)
    try:
        assert server.send_goal.max_request_bytes == max_trajectory_bytes(1) + ENVELOPE_BYTES
        server.bendables = list(BENDABLES)  # as the bridge's robot_changed does
        big = max_trajectory_bytes(3) + ENVELOPE_BYTES
        assert server.send_goal.max_request_bytes == big
        names = [f"{b}/{a}" for b in BENDABLES for a in ("kappa", "phi")]
        full = [0.1] * 6
        traj = {"joint_names": names, "points": [
            {"positions": full, "velocities": full, "accelerations": full, "effort": full,
             "time_from_start": {"sec": i}} for i in range(1, 7601)]}  # fmt: skip
        req = {"goal_id": {"uuid": list(range(1, 17))}, "goal": {"trajectory": traj}}
        data = actions.codec(FJT, "SendGoal_Request").encode(req)
        assert max_trajectory_bytes(1) + ENVELOPE_BYTES < len(data) < big
        assert call(server, session, "send_goal", data).accepted is True, log.lines
        assert len(daemon.sent[-1]) == 7600
    finally:
        server.close()
        node.close()
