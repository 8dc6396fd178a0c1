"""ROS 2 services in rmw_zenoh's format as ucr serves them: RIHS01 service type hashes equal the
ones rosidl generates (published values from generated ROS 2 code), the ``SS`` liveliness token,
and the service server's envelope: attachment required and echoed, bad requests refused without
reaching the handler (with an error reply when the service has no typed refusal), a bounded
queue."""

from __future__ import annotations

import json
import threading
import time

import pytest

pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")
zenoh = pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")

from interop.ros2 import services  # noqa: E402
from interop.ros2 import type_hash as th  # noqa: E402
from interop.zenoh import rmw  # noqa: E402

from .zenoh_query import isolated_session, query  # noqa: E402

# RIHS01 hashes as rosidl generates them (Jazzy; rosidl_generator_c type hash constants as
# published in generated code and third-party rmw_zenoh clients)
TRIGGER = "RIHS01_eeff2cd6fa5ad9d27cdf4dec64818317839b62f212a91e6b5304b634b2062c5f"
TRIGGER_EVENT = "RIHS01_ec4a1d26b0575e61906890342aba9523a2360e9845857c5590fa6e23bc39e1c2"
TRIGGER_REQUEST = "RIHS01_d010825374ce8918e72bfd826c82603e60f45419e932ea976f807b74a863a199"
SET_BOOL = "RIHS01_abe9e4bb6b41b40e6789712c00ec8871923e089af3f667a79992a428cff2da0a"
EMPTY = "RIHS01_5888399dedec5ccc85ea6451949fd2c9f97bfdf963f9a588821639fcd31b5d19"


def test_trigger_service_hashes_equal_the_ones_rosidl_generates():
    assert th.service_type_hash("std_srvs/srv/Trigger") == TRIGGER
    assert th.service_type_hash("std_srvs/srv/Trigger", "Event") == TRIGGER_EVENT
    assert th.service_type_hash("std_srvs/srv/Trigger", "Request") == TRIGGER_REQUEST


def test_service_hashes_are_computed_from_the_srv_text(tmp_path, monkeypatch):
    """Other .srv texts give their own published hashes (SetBool: a request field; Empty: both
    parts empty, rosidl's placeholder member): computed, not looked up."""
    d = tmp_path / "std_srvs"
    d.mkdir()
    (d / "SetBool.srv").write_text("bool data\n---\nbool success\nstring message\n")
    (d / "Empty.srv").write_text("---\n")
    (d / "Trigger.srv").write_text((services.SRV_DIR / "std_srvs" / "Trigger.srv").read_text())
    monkeypatch.setattr(services, "SRV_DIR", tmp_path)
    for fn in (services.service_text, th._store, th.service_type_hash, th.type_hash):
        fn.cache_clear()
    try:
        assert th.service_type_hash("std_srvs/srv/SetBool") == SET_BOOL
        assert th.service_type_hash("std_srvs/srv/Empty") == EMPTY
        assert th.service_type_hash("std_srvs/srv/Trigger") == TRIGGER
    finally:
        for fn in (services.service_text, th._store, th.service_type_hash, th.type_hash):
            fn.cache_clear()


def test_unknown_service_type_is_a_clear_error():
    with pytest.raises(services.UnknownServiceType, match="no ROS 2 definition"):
        th.service_type_hash("std_srvs/srv/NoSuch")


def test_service_token_and_key():
    node = rmw.NodeId(0, "abc", 0, "/softrobot3", "ucr_bridge")
    tok = rmw.endpoint_token(
        node, 3, rmw.SERVICE, "/softrobot3/ucr/stop", "std_srvs/srv/Trigger", TRIGGER,
        rmw.SERVICE_QOS,
    )  # fmt: skip
    assert tok == (
        "@ros2_lv/0/abc/0/3/SS/%/%softrobot3/ucr_bridge/%softrobot3%ucr%stop/"
        f"std_srvs::srv::dds_::Trigger_/{TRIGGER}/::,10:,:,:,,"
    )
    ep = rmw.parse_endpoint_token(tok)
    assert ep is not None and ep.kind == rmw.SERVICE and ep.typename == "std_srvs/srv/Trigger"
    assert rmw.topic_key(0, "/softrobot3/ucr/stop", "std_srvs/srv/Trigger", TRIGGER) == (
        f"0/softrobot3/ucr/stop/std_srvs::srv::dds_::Trigger_/{TRIGGER}"
    )


def test_trigger_codecs_round_trip_and_empty_request_has_the_placeholder_byte():
    req, resp = services.codecs("std_srvs/srv/Trigger")
    assert req.encode({}) == b"\x00\x01\x00\x00\x00"  # CDR LE header + uint8 0
    back = resp.decode(resp.encode({"success": True, "message": "held"}))
    assert back.success is True and back.message == "held"


@pytest.fixture
def session():
    with isolated_session() as s:
        yield s


def test_service_server_echoes_the_request_id_and_refuses_bad_envelopes(session):
    """A service without a typed refusal (the bridge's all have one: test_zenoh_bridge_parts.py)
    answers refused requests with a Zenoh error reply, none reaching the handler."""
    from interop.zenoh.node import MAX_REQUEST_BYTES, RmwNode

    calls = []
    node = RmwNode(session, name="t", namespace="/r")
    srv = node.service(
        "ucr/status", "std_srvs/srv/Trigger",
        lambda req: calls.append(req) or {"success": True, "message": json.dumps({"n": 1})},
    )  # fmt: skip
    req, resp = services.codecs("std_srvs/srv/Trigger")
    gid = bytes(range(16))
    att = rmw.Attachment(41, 123, gid).encode()
    try:
        replies = query(session, srv.key, req.encode({}), att)
        assert len(replies) == 1, replies
        [(kind, data, ratt)] = replies
        assert kind == "ok"
        assert resp.decode(data).success is True
        back = rmw.Attachment.decode(ratt)
        assert back.sequence == 41 and back.gid == gid and back.timestamp_ns > 123
        assert len(calls) == 1

        for payload, attachment, why in [
            (req.encode({}), None, "no rmw_zenoh attachment"),
            (req.encode({}), b"\x01\x02", "too short"),
            (b"\x00" * (MAX_REQUEST_BYTES + 1), att, "bytes refused unread (at most"),
            (b"\xff", att, "not decodable CDR"),
        ]:
            [(kind, text, _)] = query(session, srv.key, payload, attachment)
            assert kind == "err" and why in text, text
        assert len(calls) == 1  # none of them reached the handler
    finally:
        node.close()


def test_service_server_answers_busy_when_its_queue_is_full(session):
    """A handler that takes long never makes Zenoh's threads wait: requests beyond the queue
    depth are answered with an error at once."""
    from interop.zenoh.node import RmwNode

    release = threading.Event()
    node = RmwNode(session, name="t", namespace="/r")
    srv = node.service(
        "slow", "std_srvs/srv/Trigger",
        lambda req: release.wait(30) and {"success": True, "message": ""},
        rmw.Qos(depth=1),
    )  # fmt: skip
    req, _ = services.codecs("std_srvs/srv/Trigger")
    att = rmw.Attachment(1, 1, bytes(16)).encode()
    results: list = []
    threads = [
        threading.Thread(
            target=lambda: results.append(query(session, srv.key, req.encode({}), att))
        )
        for _ in range(4)
    ]
    try:
        for t in threads:
            t.start()
            time.sleep(0.2)
        deadline = time.monotonic() + 20
        while len(results) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        busy = [r for r in results if r and r[0][0] == "err" and "busy" in r[0][1]]
        assert len(busy) >= 2, results  # one runs, one waits, the others are refused
    finally:
        release.set()
        for t in threads:
            t.join(15)
        node.close()


# control_msgs 5.x (Jazzy) FollowJointTrajectory and action_msgs, as rosidl_generator_c writes
# their type hashes into generated code
FJT = "control_msgs/action/FollowJointTrajectory"
FJT_HASHES = {
    "": "RIHS01_738ebcb7a2d7cfa42f9f1001cc99ce3a4383d1cfe508015d9be8485e4b1c66f6",
    "Goal": "RIHS01_8a9060704b269608f5a340934cc26e66869dd14bdac29e2e7fd9ec8b9882d205",
    "Result": "RIHS01_8002e99ed2c14c6faa522f2a93c26d744c5982f254f9e98ff9c6f19789bdb220",
    "Feedback": "RIHS01_3fd0aaecf71725121ae1ff7f01098a5e0da581e672be18a6b2c286cb43d96b49",
    "SendGoal": "RIHS01_b13789dddc325a7a962825c45e28c77d37237ec129dd0c34dc5994562938c57f",
    "SendGoal_Request": "RIHS01_179c93691f1f6d1d115881ff88c3917b7cc6eac2ba4bf56766cc7c4389e19ef1",
    "GetResult": "RIHS01_e3ceb38e3e1867c8dc0f46014df26e90eb93422f27e9e97f936e07f94be4bc8b",
    "FeedbackMessage": "RIHS01_80398fcb9674a79081a9906e2ccf0c804dd7cb15e22e362e606ee87186beab71",
}
CANCEL_GOAL = "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
GOAL_STATUS_ARRAY = "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e"


@pytest.mark.parametrize("part", sorted(FJT_HASHES))
def test_follow_joint_trajectory_hashes_equal_the_ones_rosidl_generates(part):
    assert th.action_type_hash(FJT, part) == FJT_HASHES[part]


def test_action_msgs_hashes_equal_the_ones_rosidl_generates():
    assert th.service_type_hash("action_msgs/srv/CancelGoal") == CANCEL_GOAL
    assert th.type_hash("action_msgs/msg/GoalStatusArray") == GOAL_STATUS_ARRAY


def test_action_cdr_decodes_with_rosbags_independent_codec():
    """Our SendGoal request (mcap-ros2-support) is what rosbags' CDR reads, and rosbags'
    GetResult response is what ours reads."""
    from interop.ros2 import actions

    store = th._store()
    ours = actions.codec(FJT, "SendGoal_Request").encode(
        {
            "goal_id": {"uuid": list(range(16))},
            "goal": {
                "trajectory": {
                    "joint_names": ["s/kappa", "s/phi"],
                    "points": [{"positions": [1.5, 0.2], "time_from_start": {"sec": 2}}],
                },
                "goal_time_tolerance": {"sec": 3, "nanosec": 4},
            },
        }
    )
    m = store.deserialize_cdr(ours, f"{FJT}_SendGoal_Request")
    assert bytes(m.goal_id.uuid) == bytes(range(16))
    assert list(m.goal.trajectory.points[0].positions) == [1.5, 0.2]
    assert (m.goal.goal_time_tolerance.sec, m.goal.goal_time_tolerance.nanosec) == (3, 4)
    t = store.types
    theirs = store.serialize_cdr(
        t[f"{FJT}_GetResult_Response"](
            status=6, result=t[f"{FJT}_Result"](error_code=-4, error_string="path")
        ),
        f"{FJT}_GetResult_Response",
    )
    back = actions.codec(FJT, "GetResult_Response").decode(bytes(theirs))
    assert back.status == 6 and back.result.error_code == -4 and back.result.error_string == "path"


@pytest.mark.parametrize(
    ("state", "reason", "cause", "want"),
    [
        ("succeeded", "", "", (4, 0)),
        ("canceled", "", "", (5, 0)),
        ("aborted", "path tolerance violated on segment_1", "path_tolerance", (6, -4)),
        ("aborted", "goal tolerance not reached", "goal_tolerance", (6, -5)),
        ("aborted", "link loss: … from the goal's path (> tolerance)", "link_loss", (6, -1)),
        ("aborted", "replaced by goal jtc-3", "replaced", (5, -1)),  # preempted: as the JTC
        ("aborted", "preempted by manual control ('ffc')", "replaced", (6, -1)),
        ("aborted", "preempted by manual control ('ffc')", "", (6, -1)),
    ],
)
def test_daemon_end_states_map_to_the_actions_status_and_error_code(state, reason, cause, want):
    from interop.zenoh.action import result_of

    status, code, text = result_of(state, reason, cause)
    assert (status, code) == want
    assert reason in text
