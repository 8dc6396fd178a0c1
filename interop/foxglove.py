"""``ucr foxglove``: the live robot on the Foxglove WebSocket protocol (foxglove-sdk's server), with
the same topics, schemas and CDR bytes as a recording, for Foxglove and Lichtblick.

Read-only: the server advertises no capability (no client publishing, services, parameters or
playback control), so a connected client can only watch. foxglove-sdk 0.30 offers no hook to
check a token, Origin or Host header, so the API's token rule cannot be enforced on this server:
it binds loopback only and refuses any other address (use an SSH tunnel; docs/recording.md).
"""

from __future__ import annotations

import ipaddress
import signal
import socket
import sys
import threading
from typing import Any

import foxglove

from host.api.client import ApiError, connect
from interop import ros2
from interop.live import FeedError, LiveFeed, robot_for
from interop.sinks import Fanout
from interop.topics import LATCHED, RobotTopics


class FoxgloveBindError(ValueError):
    """Refused bind address."""


def check_bind(host: str) -> None:
    """Loopback only: anything else could be read by anyone on the network without a token."""
    try:
        addrs = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except OSError as exc:
        raise FoxgloveBindError(f"cannot resolve {host!r}: {exc}") from None
    for a in addrs:
        if not ipaddress.ip_address(a.split("%")[0]).is_loopback:
            raise FoxgloveBindError(
                f"refusing to serve Foxglove on {host} ({a}): the Foxglove server cannot check a "
                "token, so it listens on loopback only; reach it through an SSH tunnel "
                "(ssh -L 8766:127.0.0.1:8766 pi@robot)"
            )


class FoxgloveSink:
    """A foxglove-sdk WebSocket server in its own context; one channel per topic, created when
    the topic first appears. Latched topics (/robot_description, /tf_static, the U(C)RDF) are
    sent again to each new subscriber."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8766, name: str = "ucr") -> None:
        check_bind(host)
        self._fg = foxglove
        self._ctx = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._latched: dict[str, tuple[bytes, int]] = {}
        self._resend: set[str] = set()
        self._lock = threading.Lock()
        sink = self

        class Listener:
            def on_subscribe(self, client: Any, channel: Any) -> None:
                with sink._lock:
                    if channel.topic in sink._latched:
                        sink._resend.add(channel.topic)

        self._listener = Listener()
        self.server = foxglove.start_server(
            name=name, host=host, port=port, capabilities=[], server_listener=self._listener,
            supported_encodings=[ros2.MESSAGE_ENCODING], context=self._ctx,
        )  # fmt: skip
        self.port = self.server.port
        self.host = host

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _channel(self, topic: str, typename: str, schema: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            fg = self._fg
            ch = fg.Channel(
                topic,
                message_encoding=ros2.MESSAGE_ENCODING,
                schema=fg.Schema(name=typename, encoding=ros2.SCHEMA_ENCODING,
                                 data=schema.encode()),
                context=self._ctx,
            )  # fmt: skip
            self._channels[topic] = ch
        return ch

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        ch = self._channel(topic, typename, schema)
        if topic in LATCHED:
            with self._lock:
                self._latched[topic] = (data, t_ns)
        ch.log(data, log_time=t_ns)

    def tick(self) -> None:
        with self._lock:
            again, self._resend = self._resend, set()
            items = [(t, self._latched[t]) for t in again]
        for topic, (data, t_ns) in items:
            self._channels[topic].log(data, log_time=t_ns)

    def close(self) -> None:
        for ch in self._channels.values():
            ch.close()
        self.server.stop()


def run(args: Any) -> int:
    """The ``ucr foxglove`` command."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        check_bind(args.host)
    except FoxgloveBindError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    try:
        client = connect(args.url, args.token, timeout=args.timeout)
    except ApiError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    sink = None
    try:
        robot, text = robot_for(client, args.robot)
        topics = RobotTopics(robot, text, args.subdivisions)
        try:
            sink = FoxgloveSink(args.host, args.port)
        except RuntimeError as exc:  # foxglove-sdk: port in use, bind failure
            print(f"ucr: cannot serve Foxglove on {args.host}:{args.port}: {exc}", file=sys.stderr)
            return 1
        print(f"ucr: Foxglove WebSocket server on {sink.url} (open it in Foxglove or Lichtblick: "
              "Open connection -> Foxglove WebSocket)", file=sys.stderr, flush=True)  # fmt: skip
        feed = LiveFeed(client, topics, Fanout([sink]), viz_rate=args.viz_rate)
        feed.run(stop, duration=args.duration)
        return 0
    except FeedError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:
        print(f"ucr: Foxglove server stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        if sink is not None:
            sink.close()
        client.close()
