"""A ROS 2 peer written by somebody else: zenoh-ros2-sdk (ROBOTIS), run as its own process so its
singleton Zenoh session never mixes with ours. It reads message definitions from a local folder
(it cannot download them here) laid out as ``<pkg>/msg/<Type>.msg``.

    python zenoh_sdk_peer.py ROUTER MSGDIR echo TOPIC TYPE COUNT [--transient-local]
        one JSON line per received message (fields named as in ROS 2)
    python zenoh_sdk_peer.py ROUTER MSGDIR echo TOPIC TYPE COUNT --until TEXT
        counts only messages whose JSON contains TEXT
    python zenoh_sdk_peer.py ROUTER MSGDIR trajectory TOPIC JSON [REPEAT]
        publishes a JointTrajectory {"joint_names": [...], "points": [[t, [positions]], ...]}
        REPEAT times, 0.3 s apart (a fresh publisher is matched only after discovery)
    python zenoh_sdk_peer.py ROUTER MSGDIR call SERVICE TYPE
        calls a service with an empty request (its own type hash from MSGDIR/<pkg>/srv/) and
        prints the response as one JSON line; exit 3 without a response
"""

from __future__ import annotations

import json
import sys
import threading
import time


def plain(obj):
    """A rosbags message object as JSON-able data."""
    if hasattr(obj, "__dataclass_fields__"):
        return {k: plain(getattr(obj, k)) for k in obj.__dataclass_fields__}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


def main() -> int:
    router, msgdir, cmd, *rest = sys.argv[1:]
    ip, port = router.rsplit(":", 1)
    from zenoh_ros2_sdk.message_registry import get_registry

    get_registry(msgdir)  # the global registry, before anything asks for a type
    if cmd == "echo":
        from zenoh_ros2_sdk import ROS2Subscriber
        from zenoh_ros2_sdk.qos import QosDurability, QosProfile

        topic, typename, count = rest[0], rest[1], int(rest[2])
        qos = (
            QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
            if ("--transient-local" in rest)
            else None
        )
        until = rest[rest.index("--until") + 1] if "--until" in rest else ""
        got = []
        done = threading.Event()

        def on_msg(msg):
            text = json.dumps(plain(msg))
            print(text, flush=True)
            if until not in text:
                return
            got.append(msg)
            if len(got) >= count:
                done.set()

        sub = ROS2Subscriber(
            topic=topic,
            msg_type=typename,
            callback=on_msg,
            router_ip=ip,
            router_port=int(port),
            qos=qos,
        )
        ok = done.wait(60)
        sub.close()
        return 0 if ok else 3
    if cmd == "trajectory":
        from zenoh_ros2_sdk import ROS2Publisher, get_message_class

        topic, spec = rest[0], json.loads(rest[1])
        repeat = int(rest[2]) if len(rest) > 2 else 1
        pub = ROS2Publisher(
            topic=topic,
            msg_type="trajectory_msgs/msg/JointTrajectory",
            router_ip=ip,
            router_port=int(port),
        )
        point = get_message_class("trajectory_msgs/msg/JointTrajectoryPoint")
        duration = get_message_class("builtin_interfaces/msg/Duration")
        header = get_message_class("std_msgs/msg/Header")
        stamp = get_message_class("builtin_interfaces/msg/Time")
        import numpy as np

        points = [
            point(
                positions=np.array(pos, dtype=np.float64),
                velocities=np.array([], np.float64),
                accelerations=np.array([], np.float64),
                effort=np.array([], np.float64),
                time_from_start=duration(sec=int(t), nanosec=int((t % 1) * 1e9)),
            )
            for t, pos in spec["points"]
        ]
        time.sleep(1.0)  # let discovery connect us to the bridge
        for _ in range(repeat):
            pub.publish(
                header=header(stamp=stamp(sec=0, nanosec=0), frame_id=""),
                joint_names=spec["joint_names"],
                points=points,
            )
            time.sleep(0.3)
        pub.close()
        return 0
    if cmd == "call":
        from pathlib import Path

        from zenoh_ros2_sdk import ROS2ServiceClient

        service, srvtype = rest[0], rest[1]
        pkg, _, name = srvtype.split("/")
        text = (Path(msgdir) / pkg / "srv" / f"{name}.srv").read_text()
        # the SDK's registry refuses an empty request (Trigger's): give it rosidl's placeholder
        # member, which its hash computation also substitutes for an empty part
        req, resp = (part.strip() for part in text.split("---", 1))
        empty = "uint8 structure_needs_at_least_one_member"
        cli = ROS2ServiceClient(
            service_name=service,
            srv_type=srvtype,
            request_definition=req or empty,
            response_definition=resp or empty,
            router_ip=ip,
            router_port=int(port),
            timeout=20.0,
        )
        print(json.dumps({"key": cli.keyexpr}), flush=True)
        time.sleep(1.0)  # let discovery connect us to the server
        resp = cli.call()
        cli.close()
        if resp is None:
            return 3
        print(json.dumps(plain(resp)), flush=True)
        return 0
    print(f"unknown command {cmd}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
