"""``ucr zenoh``: the robot as a ROS 2 node on a Zenoh network, in rmw_zenoh's wire format.

A client of the daemon's API in its own process (like ``ucr record``):
:class:`~interop.live.LiveFeed` turns the daemon's stream into the ROS 2 messages of
:mod:`interop.topics`, :class:`ZenohSink` publishes them under the robot's namespace. With
``--enable-commands`` a subscription on ``<controller>/joint_trajectory`` feeds
:class:`~interop.zenoh.commands.TrajectoryCommands`.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

from interop.ros2 import full_name
from interop.sinks import Fanout
from interop.topics import LATCHED, TOPICS, Message
from interop.zenoh import rmw
from interop.zenoh.node import RmwNode, RmwPublisher

DISTROS = ("jazzy", "kilted", "lyrical", "rolling")  # rmw_zenoh with RIHS01 type hashes
GLOBAL_TOPICS = ("/rosout",)  # ROS convention: every node logs to the one /rosout


def relative(topic: str) -> str:
    """A topic of :data:`interop.topics.TOPICS` as the node publishes it: relative to the
    namespace (``/joint_states`` -> ``joint_states``), except the global ``/rosout``."""
    return topic if topic in GLOBAL_TOPICS else topic.lstrip("/")


class ZenohSink:
    """A :class:`interop.sinks.Sink` publishing every topic on an :class:`RmwNode`. All topics
    of :data:`TOPICS` are declared at start, so the graph shows them before data flows."""

    def __init__(self, node: RmwNode, topics: dict[str, str] | None = None) -> None:
        self.node = node
        self.pubs: dict[str, RmwPublisher] = {}
        for topic, typename in (topics or TOPICS).items():
            self._declare(topic, typename)

    def _declare(self, topic: str, typename: str) -> RmwPublisher:
        qos = rmw.LATCHED_QOS if topic in LATCHED else rmw.DEFAULT_QOS
        pub = self.node.publisher(relative(topic), full_name(typename), qos)
        self.pubs[topic] = pub
        return pub

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        pub = self.pubs.get(topic) or self._declare(topic, typename)
        pub.publish(data, t_ns)

    def tick(self) -> None:
        """Nothing to flush: Zenoh sends at once, advanced publishers keep the latched data."""

    def close(self) -> None:
        self.node.close()


class NamedFanout(Fanout):
    """Fanout that names the robot in /rosout entries (``ucr.<ns>.<event>``): /rosout is shared
    by every robot on the network."""

    def __init__(self, sinks: list[Any], namespace: str) -> None:
        super().__init__(sinks)
        self.prefix = "ucr" + namespace.replace("/", ".").rstrip(".")
        self._lock = threading.Lock()

    def publish(self, m: Message) -> None:
        if m.topic == "/rosout" and str(m.msg.get("name", "")).startswith("ucr."):
            m = replace(m, msg={**m.msg, "name": self.prefix + m.msg["name"][3:]})
        with self._lock:
            super().publish(m)


@dataclass
class BridgeInfo:
    namespace: str
    domain_id: int
    node: str
    topics: dict[str, str]  # fully qualified name -> type
    command_topic: str | None
    services: dict[str, str]  # fully qualified name -> type


def log_message(level: int, text: str, name: str) -> Message:
    """An rcl_interfaces/Log for /rosout from the bridge itself."""
    t = time.time_ns()
    msg = {
        "stamp": {"sec": t // 1_000_000_000, "nanosec": t % 1_000_000_000},
        "level": level,
        "name": name,
        "msg": text,
        "file": "",
        "function": "",
        "line": 0,
    }
    return Message("/rosout", TOPICS["/rosout"], msg, t)


def run(args: Any) -> int:
    """The ``ucr zenoh`` command (dependencies already checked)."""
    import zenoh  # noqa: PLC0415

    from host.api.client import ApiError  # noqa: PLC0415
    from host.client_common import CliError, connect_daemon  # noqa: PLC0415
    from interop.live import FeedError, LiveFeed, robot_for  # noqa: PLC0415
    from interop.topics import RobotTopics  # noqa: PLC0415
    from interop.zenoh import config  # noqa: PLC0415
    from interop.zenoh.action import FollowJointTrajectoryServer  # noqa: PLC0415
    from interop.zenoh.commands import TRAJECTORY_TYPE, TrajectoryCommands  # noqa: PLC0415
    from interop.zenoh.robot_services import (  # noqa: PLC0415
        STATUS,
        STOP,
        TRIGGER,
        RobotServices,
    )

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        if args.namespace is not None:
            rmw.check_namespace(args.namespace)
        rmw.check_node_name(args.node_name)
        conf = config.build(
            config.SessionOptions(
                mode=args.mode,
                connect=args.connect,
                listen=args.listen,
                config_file=args.zenoh_config,
                multicast=args.multicast_scouting,
            )
        )
    except (rmw.RosNameError, config.ZenohConfigError) as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 2
    try:
        client = connect_daemon(args)
    except CliError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    session = node = commands = fjt = None
    try:
        robot, text = robot_for(client, args.robot)
        namespace = rmw.check_namespace(args.namespace or rmw.namespace_for(robot.name))
        topics = RobotTopics(robot, text, args.subdivisions)
        try:
            session = zenoh.open(conf)
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: no router in client mode, bad TLS
            print(
                f"ucr: cannot open the Zenoh session ({config.describe(conf)}): {exc}",
                file=sys.stderr,
            )
            return 1
        node = RmwNode(session, name=args.node_name, namespace=namespace, domain_id=args.domain_id)
        sink = ZenohSink(node)
        fanout = NamedFanout([sink], namespace)
        command_topic = None
        notes: list[str] = []
        log_name = "ucr.commands"  # NamedFanout adds the namespace

        def report(level: int, text: str) -> None:
            print(f"ucr zenoh: {text}", file=sys.stderr, flush=True)
            fanout.publish(log_message(level, text, log_name))

        handlers = RobotServices(client, report)
        srvs = [node.service(STATUS, TRIGGER, handlers.status)]
        if args.enable_commands:
            srvs.append(node.service(STOP, TRIGGER, handlers.stop))
            fjt = FollowJointTrajectoryServer(
                node, client, list(robot.bendables), controller=args.controller, report=report
            )
            srvs += [fjt.send_goal, fjt.get_result, fjt.cancel_goal]
            if args.distro != "jazzy":
                notes.append(
                    "ucr zenoh: FollowJointTrajectory is control_msgs 5.x (Jazzy); control_msgs "
                    "6.3+ (newer distributions) added feedback fields, so its feedback topic "
                    "does not match there (goals, results, cancel and status do)"
                )

            commands = TrajectoryCommands(
                client, list(robot.bendables), controller=args.controller, report=report
            )
            sub = node.subscription(
                f"{args.controller}/joint_trajectory", TRAJECTORY_TYPE, commands.on_message
            )
            command_topic = sub.fqn
        info = BridgeInfo(
            namespace,
            args.domain_id,
            args.node_name,
            {p.fqn: p.typename for p in sink.pubs.values()},
            command_topic,
            {s.fqn: s.srvtype for s in srvs},
        )
        print(
            f"ucr: ROS 2 node {namespace.rstrip('/')}/{args.node_name} on Zenoh "
            f"({config.describe(conf)}; domain {args.domain_id}; {args.distro}): "
            f"{len(info.topics)} topics, {len(info.services)} services; commands "
            + (f"on {command_topic}" if command_topic else "off (--enable-commands)"),
            file=sys.stderr,
            flush=True,
        )
        for note in notes:
            print(note, file=sys.stderr, flush=True)
        feed = LiveFeed(client, topics, fanout, viz_rate=args.viz_rate)
        feed.run(stop, duration=args.duration)
        return 0
    except FeedError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:
        print(f"ucr: Zenoh bridge stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        if commands is not None:
            commands.close()
        if fjt is not None:
            fjt.close()
        if node is not None:
            node.close()
        if session is not None:
            session.close()
        client.close()
