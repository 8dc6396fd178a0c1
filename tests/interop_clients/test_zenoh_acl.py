"""Zenoh's own access control (ACL) in the router's configuration, as docs/ros2.md documents it:
a `ucr zenoh-router --zenoh-config` denying ``put`` and ``query`` on the robot's command key
expressions (the trajectory topic, the FollowJointTrajectory action's services, the ``ucr/stop``
service) to the sessions not allowed to command. Every session is in client mode (all traffic
passes the router, which is what makes the router's ACL apply). Against a stand-in subscriber: a
denied publisher's JointTrajectory never reaches it, an allowed one's does, the robot's other
topics still flow from the denied session. Against the real `ucr zenoh --enable-commands`
behind that router: a denied session's action goal gets no answer and its JointTrajectory never
reaches the bridge; an allowed session's do."""

from __future__ import annotations

import json
import signal
import threading
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
                    "key_exprs": [  # docs/ros2.md, verbatim
                        "*/**/jtc/joint_trajectory/**",
                        "*/**/jtc/follow_joint_trajectory/**",
                        "*/**/ucr/stop/**",
                    ],
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


def test_router_acl_keeps_the_real_bridge_s_commands_from_sessions_not_allowed(rig):
    """The documented ACL in front of `ucr zenoh --enable-commands` (client mode): the denied
    session's FollowJointTrajectory send_goal query is refused by the router (no answer) and its
    JointTrajectory never reaches the bridge (no audit line with its GID); the allowed session's
    goal is answered by the bridge and its JointTrajectory audited. Both commands are harmless:
    an empty goal (not accepted) and an empty JointTrajectory (nothing to cancel)."""
    from interop import ros2
    from interop.ros2 import actions
    from interop.ros2.type_hash import action_type_hash, type_hash
    from interop.zenoh import rmw

    port = free_port()
    # the router in this process (the same configuration `ucr zenoh-router --zenoh-config`
    # loads, as the test above runs it): one process fewer to start
    router = zenoh.open(zenoh.Config.from_json5(json.dumps(_acl(port))))
    bridge = None
    err: list[str] = []
    try:
        bridge = ucr("zenoh", "--url", rig.ensure_whole(), "--mode", "client",
                     "--connect", f"tcp/127.0.0.1:{port}", "--namespace", "/acl_robot",
                     "--enable-commands")  # fmt: skip
        reader = threading.Thread(target=lambda: err.extend(bridge.stderr), daemon=True)
        reader.start()
        fjt = "control_msgs/action/FollowJointTrajectory"
        goal_key = rmw.topic_key(0, "/acl_robot/jtc/follow_joint_trajectory/_action/send_goal",
                                 f"{fjt}_SendGoal", action_type_hash(fjt, "SendGoal"))  # fmt: skip
        goal = actions.codec(fjt, "SendGoal_Request").encode(
            {"goal_id": {"uuid": list(b"\x01" * 16)}, "goal": {"trajectory": {}}}
        )
        answer = actions.codec(fjt, "SendGoal_Response")
        traj = "trajectory_msgs/msg/JointTrajectory"
        cmd_key = rmw.topic_key(0, "/acl_robot/jtc/joint_trajectory", traj, type_hash(traj))
        empty = ros2.codec(traj).encode({})
        gids = {"ok": b"\xa1" * 16, "bad": b"\xd2" * 16}

        def att(who: str) -> bytes:
            return rmw.Attachment(1, time.time_ns(), gids[who]).encode()

        def send_goal(session, who: str, timeout: float) -> list:
            replies = session.get(goal_key, payload=goal, attachment=att(who), timeout=timeout)
            return [answer.decode(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

        def audited(who: str) -> bool:
            return any(f"publisher={gids[who].hex()} op=joint_trajectory.stop" in ln for ln in err)

        with _client(port, ALLOWED) as ok_s, _client(port, DENIED) as bad_s:
            # the allowed goal reaches the bridge (once it has started): answered, not accepted
            got: list = []
            assert wait_for(lambda: got.extend(send_goal(ok_s, "ok", 2.0)) or got, 60, 0.2), err
            assert got[0].accepted is False  # an empty trajectory
            assert send_goal(bad_s, "bad", 2.0) == []  # the router refused the query

            def both() -> bool:  # the denied one first: it would arrive before the allowed one
                bad_s.put(cmd_key, empty, attachment=att("bad"))
                ok_s.put(cmd_key, empty, attachment=att("ok"))
                return audited("ok")

            assert wait_for(both, 20, 0.5), err
            time.sleep(0.3)
            assert not audited("bad"), err
    finally:
        if bridge is not None:
            bridge.send_signal(signal.SIGINT)
            assert bridge.wait(30) == 130, "".join(err)[-2000:]  # Ctrl-C
            reader.join(5)
        router.close()
