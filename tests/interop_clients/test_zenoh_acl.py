"""Zenoh's own access control (ACL) in the router's configuration, as docs/ros2.md documents it:
a `ucr zenoh-router --zenoh-config` denying ``put`` and ``query`` on the robot's command key
expressions (the trajectory topic, the ``ucr/stop`` service) to the sessions not allowed to
command. Every session is in client mode (all traffic passes the router,
which is what makes the router's ACL apply). A denied publisher's JointTrajectory never reaches
the subscriber; an allowed one's does; the robot's other topics still flow from the denied
session."""

from __future__ import annotations

import json
import time

import pytest

from .conftest import stop, ucr, wait_for
from .test_zenoh_ros2 import _connectable, free_port

zenoh = pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")
pytest.importorskip("rosbags", reason="the 'ros2' extra (rosbags) is not installed")
pytestmark = pytest.mark.timeout(120)

ALLOWED = "a1a1a1a1a1a1a1a1a1a1a1a1a1a1a1a1"  # zenoh session ids (hex), fixed in each config
DENIED = "d2d2d2d2d2d2d2d2d2d2d2d2d2d2d2d2"


def _acl(port: int) -> dict:
    return {
        "mode": "router",
        "listen": {"endpoints": [f"tcp/127.0.0.1:{port}"]},
        "scouting": {"multicast": {"enabled": False}},
        "access_control": {
            "enabled": True,
            "default_permission": "allow",
            "rules": [
                {
                    "id": "no_commands",
                    "permission": "deny",
                    "flows": ["ingress"],
                    "messages": ["put", "query"],
                    "key_exprs": ["*/**/jtc/joint_trajectory/**", "*/**/ucr/stop/**"],
                }
            ],
            "subjects": [{"id": "not_allowed", "zids": [DENIED]}],
            "policies": [{"rules": ["no_commands"], "subjects": ["not_allowed"]}],
        },
    }


def _client(port: int, zid: str | None = None):
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if zid:
        conf.insert_json5("id", json.dumps(zid))
    return zenoh.open(conf)


def test_router_acl_drops_commands_from_sessions_not_allowed(tmp_path):
    from interop import ros2
    from interop.ros2.type_hash import type_hash
    from interop.zenoh import rmw

    port = free_port()
    cfg = tmp_path / "router.json5"
    cfg.write_text(json.dumps(_acl(port)))
    router = ucr("zenoh-router", "--zenoh-config", str(cfg))
    try:
        assert wait_for(lambda: _connectable(port), 30), router.stderr.read()
        traj = "trajectory_msgs/msg/JointTrajectory"
        cmd_key = rmw.topic_key(0, "/softrobot3/jtc/joint_trajectory", traj, type_hash(traj))
        js = "sensor_msgs/msg/JointState"
        js_key = rmw.topic_key(0, "/softrobot3/joint_states", js, type_hash(js))
        payload = ros2.codec(traj).encode({"joint_names": ["segment_1/kappa"]})
        got: dict[str, list[bytes]] = {"cmd": [], "js": []}
        with _client(port) as sub_s, _client(port, ALLOWED) as ok_s, _client(port, DENIED) as bad_s:
            subs = [
                sub_s.declare_subscriber(
                    cmd_key, lambda s: got["cmd"].append(s.attachment.to_bytes())
                ),
                sub_s.declare_subscriber(js_key, lambda s: got["js"].append(b"")),
            ]
            time.sleep(1.0)  # declarations reach the router

            def sent_by(session, tag: bytes, key: str = cmd_key) -> None:
                session.put(key, payload, attachment=tag)

            # the denied session: its commands are dropped, its joint states pass
            deadline = time.monotonic() + 15
            while not got["js"] and time.monotonic() < deadline:
                sent_by(bad_s, b"denied")
                sent_by(bad_s, b"", js_key)
                time.sleep(0.2)
            assert got["js"], "nothing at all passes the router from the denied session"
            assert got["cmd"] == []
            # the allowed session's command arrives
            assert wait_for(lambda: sent_by(ok_s, b"allowed") or got["cmd"], 15, step=0.2)
            time.sleep(0.5)
            assert set(got["cmd"]) == {b"allowed"}, got["cmd"]

            # services (queries) too: ucr/stop answers the allowed session only
            stop_key = "0/softrobot3/ucr/stop/std_srvs::srv::dds_::Trigger_/RIHS01_x"
            queryable = sub_s.declare_queryable(
                stop_key, lambda q: q.reply(stop_key, b"stopped"), complete=True
            )
            time.sleep(1.0)

            def answers(session) -> bool:
                replies = list(session.get(stop_key, timeout=3.0))
                return any(r.ok is not None for r in replies)

            assert wait_for(lambda: answers(ok_s), 15, step=0.2)
            assert not answers(bad_s)
            queryable.undeclare()
            for s in subs:
                s.undeclare()
    finally:
        stop(router)
