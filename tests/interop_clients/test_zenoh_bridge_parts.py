"""Parts of `ucr zenoh` against a stand-in daemon client, each on its own: the services' answers
to refused requests (a response of their own type, since rmw_zenoh's client only logs an error
reply), the JointTrajectory size bound, what an empty JointTrajectory stops, CancelGoal's id and
stamp rule, the transient-local publishers' sample-miss heartbeat, the status service while the
daemon is away, the command line's checks, the systemd unit and the topic table of
docs/ros2.md. Zenoh sessions here are local (no router, no network)."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import threading
import time
from pathlib import Path

import pytest

from tests.cli_run import run_ucr

pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")
zenoh = pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")

from host.api.client import ApiConnectionError, ApiError  # noqa: E402
from host.api.client_behalf import _ON_BEHALF_OF  # noqa: E402
from interop import ros2  # noqa: E402
from interop.ros2 import actions, services  # noqa: E402
from interop.zenoh import rmw  # noqa: E402

from .conftest import REPO, wait_for  # noqa: E402
from .zenoh_query import isolated_session, query  # noqa: E402

BENDABLES = ["segment_1", "segment_2", "segment_3"]
FJT = "control_msgs/action/FollowJointTrajectory"
JT = "trajectory_msgs/msg/JointTrajectory"


class FakeDaemon:
    """The daemon client's calls the bridge makes, answered from memory. Goals run until
    :meth:`finish`, a cancel or (``replaces``) a newer goal; ``away`` makes every call fail as a
    broken connection does."""

    def __init__(self) -> None:
        self.goals: dict[str, dict] = {}
        self.sent: list[list[dict]] = []
        self.canceled: list[str] = []
        self.behalf: list[tuple[str, str | None]] = []  # (call, its on_behalf_of)
        self.away = False
        self.replaces = True
        self._n = 0
        self._lock = threading.Lock()

    def _check(self) -> None:
        if self.away:
            raise ApiConnectionError("connection to ws://fake lost")

    def send_trajectory(self, points, wait=False, controller=None):
        self._check()
        self.behalf.append(("send_trajectory", _ON_BEHALF_OF.get()))
        with self._lock:
            self._n += 1
            gid = f"jtc-{self._n}"
            for g in self.goals.values():  # a new goal replaces the running one
                if g["state"] == "running" and self.replaces:
                    g.update(state="aborted", reason=f"replaced by goal {gid}", done=True,
                             abort={"cause": "replaced"})  # fmt: skip
            self.goals[gid] = {"goal": gid, "state": "running", "done": False}
            self.sent.append(points)
        return gid

    def finish(self, gid: str, state: str = "succeeded") -> None:
        with self._lock:
            self.goals[gid].update(state=state, done=True)

    def cancel(self, goal):
        self._check()
        self.behalf.append(("cancel", _ON_BEHALF_OF.get()))
        with self._lock:
            g = self.goals.get(goal)
            if g is None:
                raise ApiError("not_found", f"unknown goal id {goal!r}")
            canceled = g["state"] == "running"
            if canceled:
                g.update(state="canceled", reason="canceled", done=True)
                self.canceled.append(goal)
            return {**g, "canceled": canceled}

    def trajectory_status(self, goal):
        self._check()
        with self._lock:
            if goal not in self.goals:
                raise ApiError("not_found", f"unknown goal id {goal!r}")
            return dict(self.goals[goal])

    def status(self):
        self._check()
        running = [g for g, s in self.goals.items() if s["state"] == "running"]
        return {"state": "connected", "joint_states": {}, "running_goals": running}


class Log:
    """``report(level, text)`` collecting what the bridge says."""

    def __init__(self) -> None:
        self.lines: list[tuple[int, str]] = []

    def __call__(self, level: int, text: str, *_: object) -> None:
        self.lines.append((level, text))

    def has(self, part: str) -> bool:
        return any(part in t for _, t in self.lines)


# rmw_zenoh's attachment, as a ROS 2 publisher sends it: the command subscription refuses
# messages without one (a plain Zenoh put has no GID to audit)
ATT = rmw.Attachment(1, 0, bytes(range(16)))


def jt_bytes(names: list[str], points: list[tuple[float, list[float]]]) -> bytes:
    return ros2.codec(JT).encode({
        "joint_names": names,
        "points": [{"positions": p, "time_from_start": {"sec": int(t), "nanosec": 0}}
                   for t, p in points],
    })  # fmt: skip


@pytest.fixture
def session():
    with isolated_session() as s:
        yield s


# ---------------------------------------------------------------- refused service requests
def test_refused_service_requests_get_a_response_of_the_service_type(session):
    """Defect: a refused request (too large, undecodable, handler failure, busy) was answered
    with a Zenoh error reply, which rmw_zenoh's client only logs: a ROS 2 caller waited forever.
    Now it gets the service's own response saying "refused", matched to the call (sequence
    number and GID echoed). Only a request without an attachment keeps the error reply."""
    from interop.zenoh.node import RmwNode
    from interop.zenoh.robot_services import status_refused

    release = threading.Event()

    def handler(req):
        if calls:
            release.wait(30)
        calls.append(req)
        raise RuntimeError("handler bug")

    calls: list = []
    node = RmwNode(session, name="t", namespace="/r")
    srv = node.service(
        "ucr/status", "std_srvs/srv/Trigger", handler, rmw.Qos(depth=1),
        refusal=status_refused, max_request_bytes=1000,
    )  # fmt: skip
    req, resp = services.codecs("std_srvs/srv/Trigger")
    gid = bytes(range(16))
    try:
        for seq, payload, why in [
            (1, b"\x00" * 1001, "1001 bytes"),
            (2, b"\xff", "not decodable CDR"),
            (3, req.encode({}), "failed: RuntimeError"),
        ]:
            att = rmw.Attachment(seq, 5, gid).encode()
            [(kind, data, ratt)] = query(session, srv.key, payload, att)
            assert kind == "ok", data
            back = resp.decode(data)
            assert back.success is False and why in json.loads(back.message)["refused"]
            assert rmw.Attachment.decode(ratt).sequence == seq
            assert rmw.Attachment.decode(ratt).gid == gid
        [(kind, text, _)] = query(session, srv.key, req.encode({}), None)
        assert kind == "err" and "no rmw_zenoh attachment" in text  # no call to match it to

        # busy: one request in the handler, one waiting, the rest answered "refused" at once
        results: list = []
        att = rmw.Attachment(9, 5, gid).encode()
        threads = [
            threading.Thread(
                target=lambda: results.append(query(session, srv.key, req.encode({}), att))
            )
            for _ in range(4)
        ]
        for t in threads:
            t.start()
        assert wait_for(lambda: len(results) >= 2, 20), results
        busy = [r for r in results if r[0][0] == "ok" and b"busy" in r[0][1]]
        assert len(busy) >= 2, results
        assert resp.decode(busy[0][0][1]).success is False
    finally:
        release.set()
        node.close()


@pytest.fixture
def action(session):
    """The FollowJointTrajectory server on a local node, with a stand-in daemon."""
    from interop.zenoh.action import FollowJointTrajectoryServer
    from interop.zenoh.commands import SentGoals
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="t", namespace="/r")
    daemon, log, sent = FakeDaemon(), Log(), SentGoals()
    server = FollowJointTrajectoryServer(
        node, daemon, BENDABLES, controller="jtc", report=log, period_s=0.02, sent=sent
    )
    try:
        yield server, daemon, log, session
    finally:
        server.close()
        node.close()


def _goal_request(uuid: bytes, kappa: float = 1.0, t: int = 5) -> dict:
    traj = {"joint_names": ["segment_1/kappa", "segment_1/phi"],
            "points": [{"positions": [kappa, 0.0], "time_from_start": {"sec": t}}]}  # fmt: skip
    return {"goal_id": {"uuid": list(uuid)}, "goal": {"trajectory": traj}}


def call(server, session, name: str, payload: bytes, seq: int = 1):
    """Call one of the action's services over Zenoh; the decoded response."""
    srv = {"send_goal": server.send_goal, "get_result": server.get_result,
           "cancel_goal": server.cancel_goal}[name]  # fmt: skip
    att = rmw.Attachment(seq, 5, bytes(16)).encode()
    [(kind, data, _)] = query(session, srv.key, payload, att)
    assert kind == "ok", data
    resp = {
        "send_goal": actions.codec(FJT, "SendGoal_Response"),
        "get_result": actions.codec(FJT, "GetResult_Response"),
        "cancel_goal": services.codecs("action_msgs/srv/CancelGoal")[1],
    }[name]
    return resp.decode(data)


def test_refused_action_requests_get_typed_refusals(action):
    """send_goal too large -> not accepted; cancel_goal and get_result not decodable ->
    ERROR_REJECTED and status UNKNOWN with the reason; each refusal said on /rosout."""
    from interop.zenoh.commands import max_trajectory_bytes

    server, daemon, log, session = action
    big = b"\x00\x01\x00\x00" + b"\x00" * (max_trajectory_bytes(3) + 70_000)
    assert call(server, session, "send_goal", big).accepted is False
    cancel = call(server, session, "cancel_goal", b"\xff")
    assert cancel.return_code == 1 and list(cancel.goals_canceling) == []  # ERROR_REJECTED
    res = call(server, session, "get_result", b"\xff")
    assert res.status == 0 and "not decodable CDR" in res.result.error_string
    assert daemon.sent == []
    assert wait_for(lambda: log.has("bytes refused unread") and log.has("not decodable"), 10)


def test_a_goal_larger_than_64_kib_is_taken_when_the_daemon_could_take_it(action):
    """The send_goal bound is the daemon's (10 000 waypoints), not a 64 KiB service default:
    a 2000-point goal (~110 KB) is accepted."""
    server, daemon, _, session = action
    req = _goal_request(bytes(range(1, 17)))
    req["goal"]["trajectory"]["points"] = [
        {"positions": [0.001 * i, 0.0], "velocities": [0.0, 0.0], "accelerations": [0.0, 0.0],
         "time_from_start": {"sec": i}} for i in range(1, 2001)
    ]  # fmt: skip
    data = actions.codec(FJT, "SendGoal_Request").encode(req)
    assert len(data) > 64 * 1024
    assert call(server, session, "send_goal", data).accepted is True
    assert len(daemon.sent[-1]) == 2000


# ---------------------------------------------------------------- CancelGoal: id and stamp
def test_cancel_goal_with_an_id_and_a_stamp_also_cancels_goals_accepted_up_to_the_stamp(action):
    """action_msgs/srv/CancelGoal: a goal id and a non-zero stamp cancel that goal AND every goal
    accepted at or before the stamp (the defect: the stamp was ignored, and an unknown id
    answered ERROR_UNKNOWN_GOAL_ID)."""
    server, daemon, _, session = action
    daemon.replaces = False  # goals of other controllers, say: all of them run
    req = actions.codec(FJT, "SendGoal_Request")
    cancel = services.codecs("action_msgs/srv/CancelGoal")[0]
    old, new = bytes([1] * 16), bytes([2] * 16)
    assert call(server, session, "send_goal", req.encode(_goal_request(old))).accepted
    t_between = time.time_ns()
    time.sleep(0.01)
    assert call(server, session, "send_goal", req.encode(_goal_request(new))).accepted
    unknown = bytes([9] * 16)
    stamp = {"sec": t_between // 10**9, "nanosec": t_between % 10**9}
    resp = call(server, session, "cancel_goal",
                cancel.encode({"goal_info": {"goal_id": {"uuid": list(unknown)},
                                             "stamp": stamp}}))  # fmt: skip
    assert resp.return_code == 0
    assert [bytes(g.goal_id.uuid) for g in resp.goals_canceling] == [old]
    assert daemon.canceled == ["jtc-1"]
    # the id's goal and those up to the stamp: here the id names a goal after the stamp
    third = bytes([3] * 16)
    assert call(server, session, "send_goal", req.encode(_goal_request(third))).accepted
    resp = call(server, session, "cancel_goal",
                cancel.encode({"goal_info": {"goal_id": {"uuid": list(third)},
                                             "stamp": stamp}}))  # fmt: skip
    assert resp.return_code == 0
    assert sorted(bytes(g.goal_id.uuid) for g in resp.goals_canceling) == [third]  # old: ended
    assert daemon.canceled == ["jtc-1", "jtc-3"]  # not jtc-2, accepted after the stamp


# ---------------------------------------------------------------- preempted goals
def test_a_goal_replaced_by_a_newer_goal_ends_canceled_as_in_the_jtc(action):
    """ros2_control's JTC sets a goal preempted by a new one CANCELED with INVALID_GOAL; it was
    reported ABORTED."""
    server, daemon, _, session = action
    req = actions.codec(FJT, "SendGoal_Request")
    first, second = bytes([4] * 16), bytes([5] * 16)
    assert call(server, session, "send_goal", req.encode(_goal_request(first))).accepted
    assert call(server, session, "send_goal", req.encode(_goal_request(second, 2.0))).accepted
    get = actions.codec(FJT, "GetResult_Request")
    res = call(server, session, "get_result", get.encode({"goal_id": {"uuid": list(first)}}))
    assert (res.status, res.result.error_code) == (5, -1), res  # CANCELED, INVALID_GOAL
    assert "replaced by goal jtc-2" in res.result.error_string


# ---------------------------------------------------------------- JointTrajectory topic
@pytest.fixture
def commands():
    from interop.zenoh.commands import SentGoals, TrajectoryCommands

    daemon, log, sent = FakeDaemon(), Log(), SentGoals()
    cmds = TrajectoryCommands(daemon, BENDABLES, controller="jtc", report=log, sent=sent)
    try:
        yield cmds, daemon, log, sent
    finally:
        cmds.close()


def test_a_joint_trajectory_larger_than_the_daemon_could_take_is_refused_unread(commands):
    """Defect: a 16 MB JointTrajectory was decoded into Python objects (RSS +470 MB). A message
    over the bound (the daemon's 10 000 waypoints for 6 joints) is refused by its size, never
    decoded, and the refusal says the size and the bound."""
    from interop.zenoh.commands import max_trajectory_bytes

    cmds, daemon, log, _ = commands
    decoded: list = []
    real = cmds._codec

    class Watch:
        def decode(self, data):
            decoded.append(len(data))
            return real.decode(data)

    cmds._codec = Watch()
    limit = max_trajectory_bytes(len(BENDABLES))
    cmds.on_message(b"\x00\x01\x00\x00" + b"\x00" * limit, ATT)
    assert wait_for(lambda: log.has("refused unread"), 10), log.lines
    [(level, text)] = log.lines
    assert level == 40 and f"({limit + 4} bytes)" in text and f"({limit} bytes)" in text
    assert "10000 waypoints of 6 joints" in text
    assert decoded == [] and daemon.sent == []
    cmds.on_message(jt_bytes(["segment_2/kappa", "segment_2/phi"], [(1, [1.0, 0.2])]), ATT)
    assert wait_for(lambda: daemon.sent, 10)  # the next message is taken as usual


def test_the_size_bound_admits_the_largest_trajectory_the_daemon_takes():
    """10 000 points with positions, velocities, accelerations and efforts for every joint:
    within the bound (for one and for three bendables)."""
    from host.api.schema import MAX_POINTS
    from interop.zenoh.commands import max_trajectory_bytes

    for bendables in (BENDABLES[:1], BENDABLES):
        names = [f"{b}/{a}" for b in bendables for a in ("kappa", "phi")]
        full = [1.0] * len(names)
        msg = {
            "header": {"frame_id": "base"},
            "joint_names": names,
            "points": [{"positions": full, "velocities": full, "accelerations": full,
                        "effort": full, "time_from_start": {"sec": i, "nanosec": 5}}
                       for i in range(MAX_POINTS)],
        }  # fmt: skip
        assert len(ros2.codec(JT).encode(msg)) <= max_trajectory_bytes(len(bendables))


def test_an_empty_joint_trajectory_stops_the_action_goal_and_says_what_it_did(commands):
    """Defect: an empty JointTrajectory cancelled only the last *topic* goal (even a finished
    one) and always logged "canceled". It stops the newest goal of the bridge's commands, topic
    or action, and says "nothing to cancel" when there is nothing."""
    cmds, daemon, log, sent = commands
    empty = jt_bytes([], [])
    cmds.on_message(empty, ATT)
    assert wait_for(lambda: log.lines, 10)
    nothing = "empty JointTrajectory: nothing to cancel (this bridge has started no goal)"
    assert log.lines[-1] == (20, nothing)

    cmds.on_message(jt_bytes(["segment_1/kappa", "segment_1/phi"], [(1, [1.0, 0.0])]), ATT)
    assert wait_for(lambda: daemon.sent, 10)
    topic_goal = sent.last()[0]
    daemon.finish(topic_goal)
    action_goal = daemon.send_trajectory([{"time_from_start": 9}])  # as the action does
    sent.note(action_goal, "action")
    log.lines.clear()
    cmds.on_message(empty, ATT)
    assert wait_for(lambda: log.lines, 10)
    assert daemon.canceled == [action_goal]
    assert log.lines[-1][1].startswith(f"empty JointTrajectory: goal {action_goal} (from the "
                                       "action) canceled")  # fmt: skip
    log.lines.clear()
    cmds.on_message(empty, ATT)  # again: that goal has ended
    assert wait_for(lambda: log.lines, 10)
    assert daemon.canceled == [action_goal]
    assert "nothing to cancel" in log.lines[-1][1] and "already canceled" in log.lines[-1][1]


# ---------------------------------------------------------------- transient local heartbeat
def test_transient_local_publishers_send_sample_miss_heartbeats(session):
    """As rmw_zenoh for RELIABLE + TRANSIENT_LOCAL: a sporadic heartbeat (its
    SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD, 500 ms) carries the last sequence number, so an
    advanced subscriber notices a missed /robot_description and fetches it from the cache."""
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="t", namespace="/r")
    pub = node.publisher("robot_description", "std_msgs/msg/String", rmw.LATCHED_QOS)
    beats: list[str] = []
    sub = session.declare_subscriber(
        f"{pub.key}/@adv/pub/**", lambda s: beats.append(str(s.key_expr))
    )
    try:
        pub.publish(ros2.codec("std_msgs/msg/String").encode({"data": "<robot/>"}))
        assert wait_for(lambda: beats, 10), "no sample-miss heartbeat"
    finally:
        sub.undeclare()
        node.close()


# ---------------------------------------------------------------- nobody listening
def test_the_bridge_sink_wants_a_periodic_topic_only_while_a_subscriber_matches(session):
    """With no subscriber the feed skips the FK and CDR of /tf, /ucr/arcs and /joint_states
    (interop/live.py): the sink says whether one matches now; a latched topic always (its cache
    serves a late reader from what was put)."""
    from interop.zenoh.bridge import ZenohSink
    from interop.zenoh.node import RmwNode

    node = RmwNode(session, name="t", namespace="/r")
    sink = ZenohSink(node)
    try:
        assert not sink.wants("/tf") and not sink.wants("/joint_states")
        assert sink.wants("/robot_description") and sink.wants("/tf_static")
        sub = session.declare_subscriber(sink.pubs["/tf"].key, lambda s: None)
        try:
            assert wait_for(lambda: sink.wants("/tf"), 10), "a subscriber did not match"
            assert not sink.wants("/joint_states")  # only the topic it reads
        finally:
            sub.undeclare()
        assert wait_for(lambda: not sink.wants("/tf"), 10), "still matching after it left"
    finally:
        sink.close()


# ---------------------------------------------------------------- the daemon away
def test_status_service_says_the_daemon_is_away_and_stop_cancels_nothing():
    from interop.live import DaemonLink
    from interop.zenoh.robot_services import RobotServices

    daemon, log = FakeDaemon(), Log()
    link = DaemonLink(daemon)
    handlers = RobotServices(link, log)
    ok = json.loads(handlers.status(None)["message"])
    assert ok["daemon"] == "connected" and ok["state"] == "connected"
    daemon.away = True
    link.lost("connection to ws://fake lost — reconnecting (attempt 2, next in 2.0 s)")
    st = handlers.status(None)
    assert st["success"] is False
    assert json.loads(st["message"])["daemon"].startswith("connection to ws://fake lost")
    stop = handlers.stop(None)
    assert stop["success"] is False and "not connected" in stop["message"]
    link.replace(FakeDaemon())
    assert json.loads(handlers.status(None)["message"])["daemon"] == "connected"


# ---------------------------------------------------------------- command line
def test_a_bad_ros_domain_id_concerns_ucr_zenoh_only():
    """Defect: a non-integer $ROS_DOMAIN_ID crashed every `ucr` command with a traceback (the
    default was computed while building the parser)."""
    res = run_ucr("check", str(REPO / "robots" / "softrobot3.ucrdf"), env={"ROS_DOMAIN_ID": "abc"})
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    for bad in ("abc", "300"):
        res = run_ucr("zenoh", "--url", "ws://127.0.0.1:9", env={"ROS_DOMAIN_ID": bad})
        assert res.returncode == 2, res.stderr
        said = (
            f"ucr: $ROS_DOMAIN_ID: {bad!r} is not a ROS 2 domain id (an integer 0..232); set it "
            "to one, unset it, or pass --domain-id"
        )
        assert res.stderr.strip().splitlines() == [said]


@pytest.mark.parametrize(
    ("option", "value", "says"),
    [
        ("--domain-id", "300", "'300' is not a ROS 2 domain id (an integer 0..232)"),
        ("--domain-id", "-1", "'-1' is not a ROS 2 domain id (an integer 0..232)"),
        ("--subdivisions", "0", "must be >= 1, got 0"),
        ("--subdivisions", "-3", "must be >= 1, got -3"),
    ],
)
def test_impossible_options_are_usage_errors_before_anything_opens(option, value, says):
    """Defect: they ended in tracebacks after connecting to the daemon and opening Zenoh. Now a
    usage error (exit 2) names the bound; the daemon is never asked (none runs at that URL)."""
    res = run_ucr("zenoh", option, value, "--url", "ws://127.0.0.1:9")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert f"ucr zenoh: error: argument {option}: {says}" in res.stderr
    assert "daemon" not in res.stderr


@pytest.mark.parametrize("value", ["bad-name", "/x"])
def test_an_impossible_controller_is_a_usage_error_before_anything_opens(value):
    """Defect: `--controller bad-name` ended in a RosNameError traceback after the Zenoh session
    had opened, and `--controller /x` made the command topic and action absolute (/x/…, outside
    the robot's namespace). Now one line, exit 2, before the daemon is asked (none runs there)."""
    res = run_ucr("zenoh", "--enable-commands", "--controller", value, "--url", "ws://127.0.0.1:9")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    said = (
        f"ucr: invalid controller name {value!r}: letters, digits and '_', not starting with a "
        "digit (its topics stay inside the robot's namespace: no '/')"
    )
    assert res.stderr.strip().splitlines() == [said]
    assert rmw.check_controller_name("jtc_2") == "jtc_2"
    for bad in ("a/b", "~x", "1jtc", "", "jtc/"):  # the same check, without a process each
        with pytest.raises(rmw.RosNameError, match="invalid controller name"):
            rmw.check_controller_name(bad)


# ---------------------------------------------------------------- systemd unit, docs
UNIT = REPO / "host" / "ucr-zenoh.service"


def _service_section() -> dict[str, list[str]]:
    section, out = None, {}
    for line in UNIT.read_text().splitlines():
        line = line.strip()
        if line.startswith("["):
            section = line
        elif line and not line.startswith(("#", ";")) and section == "[Service]":
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


def test_the_bridge_unit_runs_ucr_zenoh_at_nice_10_and_is_valid(tmp_path):
    """docs/ros2.md says the bridge runs at Nice=10 from its systemd unit: the unit exists, its
    command line is one `ucr zenoh` accepts, and `systemd-analyze verify` finds nothing."""
    from tools.cli import build_parser

    svc = _service_section()
    assert svc["Nice"] == ["10"] and svc["User"] == ["ucr"] and svc["Restart"] == ["on-failure"]
    argv = shlex.split(svc["ExecStart"][-1])
    assert argv[0] == "/opt/ucr/.venv/bin/ucr" and argv[1] == "zenoh"
    args = build_parser().parse_args(argv[1:])
    assert args.func is not None and not args.enable_commands  # commands stay opt-in
    text = (REPO / "docs" / "ros2.md").read_text()
    assert "sudo cp host/ucr-zenoh.service /etc/systemd/system/" in text
    units = Path("/lib/systemd/system")
    if shutil.which("systemd-analyze") is None or not (units / "sysinit.target").exists():
        pytest.skip("systemd-analyze or this machine's system units missing")
    root = tmp_path / "root"
    shutil.copytree(units, root / "usr" / "lib" / "systemd" / "system", symlinks=True)
    (root / "etc" / "systemd" / "system").mkdir(parents=True)
    shutil.copy(UNIT, root / "etc" / "systemd" / "system" / UNIT.name)
    exe = root / argv[0].lstrip("/")
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    proc = subprocess.run(["systemd-analyze", "verify", f"--root={root}", UNIT.name],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 0 and not (proc.stdout + proc.stderr).strip(), (
        proc.stdout + proc.stderr
    )


def test_the_topic_table_of_docs_ros2_lists_every_topic_the_bridge_publishes():
    from interop.topics import TOPICS
    from interop.zenoh.bridge import relative

    text = (REPO / "docs" / "ros2.md").read_text()
    table = text.split("## Topics", 1)[1].split("Services (", 1)[0]
    listed = {}
    for row in table.splitlines():
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        if row.startswith("|") and len(cells) > 2:
            for name in re.findall(r"`([^`]+)`", cells[0]):
                listed[name] = cells[1]
    assert listed.get("joint_states") == "sensor_msgs/msg/JointState"  # the parse sees rows
    for topic, typename in TOPICS.items():
        assert listed.get(relative(topic)) == typename, (topic, listed)


def test_each_command_from_ros_is_audited_with_its_ros_identity(commands, action, caplog):
    """Review 2026-11-26: the daemon's audit line names only the bridge's token; who on the ROS
    side moved the robot was written nowhere. The bridge's own audit line names the
    JointTrajectory publisher's GID and the action goal's UUID, and (2026-11-27) each request
    it sends the daemon for them says so (``on_behalf_of``, the daemon's ``for=``)."""
    import logging

    from host.api.audit import audit_logger
    from interop.zenoh import rmw

    audit_logger().addHandler(caplog.handler)
    caplog.set_level(logging.INFO, logger="ucr.audit")
    try:
        cmds, daemon, _, _ = commands
        att = rmw.Attachment(1, 0, bytes(range(16)))
        cmds.on_message(jt_bytes(["segment_1/kappa", "segment_1/phi"], [(1, [1.0, 0.0])]), att)
        assert wait_for(lambda: daemon.sent, 10)
        lines = [r.getMessage() for r in caplog.records]
        assert any(
            ln.startswith(f"zenoh publisher={bytes(range(16)).hex()} op=joint_trajectory goal=")
            for ln in lines
        ), lines
        server, action_daemon, _, session = action
        req = actions.codec(FJT, "SendGoal_Request")
        assert call(
            server, session, "send_goal", req.encode(_goal_request(bytes([7] * 16)))
        ).accepted
        lines = [r.getMessage() for r in caplog.records]
        mark = f"zenoh goal_uuid={bytes([7] * 16).hex()} op=follow_joint_trajectory goal="
        assert any(ln.startswith(mark) for ln in lines), lines
        # and each request to the daemon says whom it is for: its audit line names them too
        assert daemon.behalf == [
            ("send_trajectory", f"zenoh publisher={bytes(range(16)).hex()}")
        ], daemon.behalf
        assert action_daemon.behalf == [
            ("send_trajectory", f"zenoh goal_uuid={bytes([7] * 16).hex()}")
        ], action_daemon.behalf
    finally:
        audit_logger().removeHandler(caplog.handler)
