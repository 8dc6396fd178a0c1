"""ROS 2 services in rmw_zenoh's format as ucr serves them: RIHS01 service type hashes equal the
ones rosidl generates (published values from generated ROS 2 code), the ``SS`` liveliness token,
and the service server's envelope: attachment required and echoed, bad requests answered with an
error without reaching the handler, a bounded queue."""

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
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(conf) as s:
        yield s


def _get(session, key, payload, attachment):
    """One query; its replies as ("ok", bytes, attachment bytes) / ("err", text, None)."""
    out = []
    kw = {"payload": payload, "timeout": 10.0}
    if attachment is not None:
        kw["attachment"] = attachment
    for reply in session.get(key, **kw):
        if reply.ok is not None:
            att = reply.ok.attachment.to_bytes() if reply.ok.attachment is not None else None
            out.append(("ok", reply.ok.payload.to_bytes(), att))
        else:
            out.append(("err", reply.err.payload.to_bytes().decode(), None))
    return out


def test_service_server_echoes_the_request_id_and_refuses_bad_envelopes(session):
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
        replies = _get(session, srv.key, req.encode({}), att)
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
            (b"\x00" * (MAX_REQUEST_BYTES + 1), att, "bytes (at most"),
            (b"\xff", att, "not decodable CDR"),
        ]:
            [(kind, text, _)] = _get(session, srv.key, payload, attachment)
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
        threading.Thread(target=lambda: results.append(_get(session, srv.key, req.encode({}), att)))
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
