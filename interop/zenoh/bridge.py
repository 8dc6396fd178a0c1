"""``ucr zenoh``: the robot as a ROS 2 node on a Zenoh network, in rmw_zenoh's wire format.

A client of the daemon's API in its own process (like ``ucr record``):
:class:`~interop.live.LiveFeed` turns the daemon's stream into the ROS 2 messages of
:mod:`interop.topics`, :class:`ZenohSink` publishes them under the robot's namespace. With
``--enable-commands`` a subscription on ``<controller>/joint_trajectory`` feeds
:class:`~interop.zenoh.commands.TrajectoryCommands`.

The bridge outlives the daemon: when the API connection breaks, the node stays in the ROS graph,
says on ``ucr/status`` and ``/ucr/segments`` that the daemon is away, and connects again with
``ucr view``'s back-off (:func:`_serve`).
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

from host.stopsignals import StopSignals
from interop.ros2 import full_name
from interop.sinks import Fanout
from interop.topics import LATCHED, TOPICS, Message
from interop.zenoh import rmw
from interop.zenoh.node import GraphWatch, RmwNode, RmwPublisher
from interop.zenoh.router import wait_time

DISTROS = rmw.DISTROS
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

    def wants(self, topic: str) -> bool:
        """Whether a subscriber matches ``topic`` now (a latched or undeclared topic: always):
        with nobody listening, the feed neither computes nor encodes its periodic topics."""
        pub = self.pubs.get(topic)
        return True if pub is None else pub.matching()

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


def daemon_away(bendables: list[str], why: str, t_ns: int) -> Message:
    """/ucr/segments while the daemon is not connected: every segment STALE, saying why."""
    text = f"daemon not connected: {why}"
    status = [
        {"level": 3, "name": f"ucr/{name}", "message": text, "hardware_id": "",
         "values": [{"key": "daemon", "value": "disconnected"}]}
        for name in bendables
    ]  # fmt: skip
    stamp = {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}
    msg = {"header": {"stamp": stamp, "frame_id": ""}, "status": status}
    return Message("/ucr/segments", TOPICS["/ucr/segments"], msg, t_ns)


GRAPH_SETTLE_S = 1.0  # how long the start waits for the graph's tokens to reach it


def describe_clash(key: str, domain_id: int, *, joined: bool = False) -> str:
    """One phrase naming what a liveliness token of :func:`watch_clashes` announces."""
    node = rmw.parse_node_token(key)
    if node is not None:
        zid, ns, name = node
        return (
            f"a ROS 2 node {ns.rstrip('/')}/{name} "
            f"{'joined' if joined else 'is already on'} this Zenoh network (domain {domain_id}, "
            f"Zenoh session {zid})"
        )
    e = rmw.parse_endpoint_token(key)
    if e is not None:
        action = e.topic.removesuffix("/_action/send_goal")
        return (
            f"the action {action} is {'now also' if joined else 'already'} served on this Zenoh "
            f"network (by node {e.namespace.rstrip('/')}/{e.node}, domain {domain_id}, Zenoh "
            f"session {e.zid})"
        )
    return key


def watch_clashes(
    session: Any, domain_id: int, namespace: str, node_name: str, action: str | None = None
) -> GraphWatch:
    """Watch the graph for what would clash with this node: a node of the same fully qualified
    name in the domain and, given the ``action`` this node serves with commands enabled, another
    server of that action (a node of another name in the same namespace would take the same
    commands). Returns once the tokens already there have arrived (:data:`GRAPH_SETTLE_S`), at
    once when a node of the same name is seen (the clearer clash to name). Not at the first
    token of any kind: the action's token of a node of the same name could arrive before that
    node's own, and the refusal named the action (whichever token won the race)."""
    keys = [rmw.node_query(domain_id, namespace, node_name)]
    if action:
        keys.append(rmw.server_query(domain_id, f"{action}/_action/send_goal"))
    watch = GraphWatch(session, keys)
    watch.settle(GRAPH_SETTLE_S, lambda seen: any(rmw.parse_node_token(k) for k in seen))
    return watch


def stop_after(duration: float | None, stop: threading.Event) -> threading.Timer | None:
    """Set ``stop`` after ``duration`` s (``--duration``; None: never). A duration beyond what
    ``threading`` can wait (``threading.TIMEOUT_MAX``, about 292 years) waits that long: 1e300 s
    raised OverflowError in the timer's thread (a traceback, and the bridge ran on)."""
    if duration is None:
        return None
    timer = threading.Timer(wait_time(duration), stop.set)
    timer.daemon = True
    timer.start()
    return timer


def run(args: Any) -> int:
    """The ``ucr zenoh`` command (dependencies and the domain id already checked)."""
    import zenoh  # noqa: PLC0415

    from host.api.client import ApiError  # noqa: PLC0415
    from host.client_common import CliError, connect_daemon  # noqa: PLC0415
    from interop.live import DaemonLink, FeedError, robot_for  # noqa: PLC0415
    from interop.topics import RobotTopics  # noqa: PLC0415
    from interop.zenoh import config  # noqa: PLC0415
    from interop.zenoh.action import FollowJointTrajectoryServer  # noqa: PLC0415
    from interop.zenoh.commands import TRAJECTORY_TYPE, SentGoals, TrajectoryCommands  # noqa: PLC0415
    from interop.zenoh.robot_services import (  # noqa: PLC0415
        STATUS,
        STOP,
        TRIGGER,
        RobotServices,
        status_refused,
        stop_refused,
    )

    signals = StopSignals().install()
    stop = signals.stop
    try:
        if args.namespace is not None:
            rmw.check_namespace(args.namespace)
        rmw.check_node_name(args.node_name)
        rmw.check_controller_name(args.controller)  # also when run() is called without argparse
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
        link = DaemonLink(connect_daemon(args))
    except CliError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return exc.exit_code
    session = node = commands = fjt = watch = None
    try:
        robot, robot_text = robot_for(link, args.robot)
        namespace = rmw.check_namespace(args.namespace or rmw.namespace_for(robot.name))
        topics = RobotTopics(robot, robot_text, args.subdivisions)
        try:
            session = zenoh.open(conf)
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: no router in client mode, bad TLS
            print(
                f"ucr: cannot open the Zenoh session ({config.describe(conf)}): {exc}",
                file=sys.stderr,
            )
            return 1
        # the graph before this node joins it: a second bridge of the same name with commands
        # would take the same JointTrajectory (both robots move): refused. ROS 2 itself only
        # warns about two nodes of one name: so does a bridge without commands.
        action = rmw.fully_qualified(namespace, f"{args.controller}/follow_joint_trajectory")
        try:
            watch = watch_clashes(
                session, args.domain_id, namespace, args.node_name,
                action if args.enable_commands else None,
            )  # fmt: skip
            # a node of the same name first (the clearer clash), whichever token came first
            keys = sorted(watch.current(), key=lambda k: rmw.parse_node_token(k) is None)
            found = [describe_clash(k, args.domain_id) for k in keys]
        except Exception as exc:  # noqa: BLE001 - zenoh.ZError: the check itself failed
            found = []
            print(f"ucr zenoh: warning: could not look for a node of the same name: {exc}",
                  file=sys.stderr, flush=True)  # fmt: skip
        if found and args.enable_commands:
            print(
                f"ucr: {found[0]}: with --enable-commands both would take the same commands "
                "(one JointTrajectory would move both robots); not started: give this robot its "
                f"own --namespace (e.g. --namespace {namespace.rstrip('/')}_2)",
                file=sys.stderr,
                flush=True,
            )
            return 2
        node = RmwNode(session, name=args.node_name, namespace=namespace, domain_id=args.domain_id)
        sink = ZenohSink(node)
        fanout = NamedFanout([sink], namespace)
        command_topic = None
        notes: list[str] = []
        log_name = "ucr.commands"  # NamedFanout adds the namespace

        def report(level: int, text: str, name: str = log_name) -> None:
            print(f"ucr zenoh: {text}", file=sys.stderr, flush=True)
            fanout.publish(log_message(level, text, name))

        handlers = RobotServices(link, report)
        srvs = [node.service(STATUS, TRIGGER, handlers.status, refusal=status_refused)]
        if args.enable_commands:
            srvs.append(node.service(STOP, TRIGGER, handlers.stop, refusal=stop_refused))
            sent = SentGoals()  # what an empty JointTrajectory stops: topic's or action's goal
            fjt = FollowJointTrajectoryServer(
                node, link, list(robot.bendables), controller=args.controller, report=report,
                sent=sent,
            )  # fmt: skip
            srvs += [fjt.send_goal, fjt.get_result, fjt.cancel_goal]
            if args.distro != "jazzy":
                notes.append(
                    "ucr zenoh: FollowJointTrajectory is control_msgs 5.x (Jazzy); control_msgs "
                    "6.3+ (newer distributions) added feedback fields, so its feedback topic "
                    "does not match there (goals, results, cancel and status do)"
                )

            commands = TrajectoryCommands(
                link, list(robot.bendables), controller=args.controller, report=report, sent=sent
            )
            sub = node.subscription(
                f"{args.controller}/joint_trajectory",
                TRAJECTORY_TYPE,
                commands.on_message,
                # a sample without a publisher GID (a plain Zenoh put) is refused, not sent
                unattributed=commands.unattributed_message,
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
        for said in found:  # without commands: ROS 2 itself only warns
            report(
                30,
                f"warning: {said}: two nodes of one name confuse ROS 2 tools; give this one its "
                "own --namespace (or --node-name)",
                "ucr.bridge",
            )
        if watch is not None:  # one joining later: it refuses itself if it has commands

            def joined(key: str) -> None:
                said = describe_clash(key, args.domain_id, joined=True)
                report(30, f"warning: {said}: give one of them its own --namespace", "ucr.bridge")

            watch.on_join = joined
        stop_after(args.duration, stop)

        def reopen() -> tuple[Any, Any, str]:
            """A new connection and the robot the daemon runs now."""
            try:
                client = connect_daemon(args)
            except CliError as exc:
                raise ConnectionError(str(exc)) from None
            try:
                return (client, *robot_for(client, args.robot))
            except BaseException:
                client.close()
                raise

        def robot_changed(new_robot: Any, new_text: str) -> None:
            nonlocal topics
            topics = RobotTopics(new_robot, new_text, args.subdivisions)
            for part in (commands, fjt):
                if part is not None:
                    part.bendables = list(new_robot.bendables)
            said = f"the daemon now runs robot {new_robot.name!r}: description and joints updated"
            if args.namespace is None and rmw.namespace_for(new_robot.name) != namespace:
                said += f"; the node keeps its namespace {namespace} (restart ucr zenoh to move it)"
            report(30, said, "ucr.bridge")

        served = _serve(
            link, lambda: topics, fanout, stop, args, report, reopen, robot_changed, robot_text
        )
        return signals.exit_code(served)
    except FeedError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:
        print(f"ucr: Zenoh bridge stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        if watch is not None:
            watch.close()
        if commands is not None:
            commands.close()
        if fjt is not None:
            fjt.close()
        if node is not None:
            node.close()
        if session is not None:
            session.close()
        link.close()


def _serve(
    link: Any,
    topics: Callable[[], Any],
    fanout: NamedFanout,
    stop: threading.Event,
    args: Any,
    report: Callable[..., None],
    reopen: Callable[[], tuple[Any, Any, str]],
    robot_changed: Callable[[Any, str], None],
    robot_text: str,
) -> int:
    """Feed the node until ``stop``. When the daemon goes away the node stays in the ROS graph
    (its services answer that the daemon is away, ``/ucr/segments`` says so every second) and the
    bridge connects again with ``ucr view``'s back-off (:func:`interop.live.reconnect`)."""
    from host.api.client import ApiConnectionError, ApiTimeoutError  # noqa: PLC0415
    from host.api.reconnect import reconnect  # noqa: PLC0415
    from interop.live import LiveFeed  # noqa: PLC0415

    while not stop.is_set():
        feed = LiveFeed(link.client, topics(), fanout, viz_rate=args.viz_rate)
        try:
            feed.run(stop)
            return 0
        except (ApiConnectionError, ApiTimeoutError, StopIteration, ConnectionError) as exc:
            why = str(exc) or "the connection closed"
        if stop.is_set():
            break
        link.lost(f"{why} — reconnecting")
        report(30, f"lost the daemon ({why}); the node stays up, reconnecting", "ucr.bridge")

        def away() -> None:
            fanout.publish(daemon_away(topics().bendables, link.why, time.time_ns()))

        def retry(reason: str, attempt: int, next_s: float) -> None:
            link.why = f"{reason} — reconnecting (attempt {attempt}, next in {next_s:.1f} s)"
            if attempt <= 3 or attempt % 12 == 0:  # about once a minute after the first ones
                report(30, f"daemon still away: {link.why}", "ucr.bridge")

        away()
        back = reconnect(reopen, stop, retry, tick=away)
        if back is None:
            break
        (client, new_robot, new_text), _attempt = back
        link.replace(client)
        if new_text != robot_text:
            robot_text = new_text
            robot_changed(new_robot, new_text)
        report(20, f"reconnected to the daemon at {client.url}", "ucr.bridge")
    return 0
