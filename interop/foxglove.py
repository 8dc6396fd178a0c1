"""``ucr foxglove``: the live robot on the Foxglove WebSocket protocol (foxglove-sdk's server), with
the same topics, schemas and CDR bytes as a recording, for Foxglove and Lichtblick.

Read-only: the server advertises no capability (no client publishing, services, parameters or
playback control), so a connected client can only watch. foxglove-sdk cannot check a token,
``Origin`` or ``Host``, so its server listens on a private loopback port and
:class:`~interop.guard.FoxgloveGuard` takes the public address and checks every handshake with the
API's token rule (docs/recording.md, security).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any

import foxglove
from foxglove.websocket import ServerListener

from host.api.auth import AuthConfigError, read_token_file
from host.api.client import ApiError
from host.client_common import CliError, connect_daemon
from interop import ros2
from interop.guard import FoxgloveGuard, GuardError
from interop.live import FeedError, LiveFeed, robot_for
from interop.sinks import Fanout
from interop.topics import LATCHED, RobotTopics

ENV_SERVE_TOKEN = "UCR_FOXGLOVE_TOKEN"
FoxgloveBindError = GuardError  # a refused address or token


class FoxgloveSink:
    """A foxglove-sdk WebSocket server in its own context; one channel per topic, created when
    the topic first appears. Latched topics (/robot_description, /tf_static, the U(C)RDF) are
    sent again to each new subscriber of theirs, and to it only: foxglove-sdk's Python binding
    cannot address one client (its ``Client`` carries no sink id), so the guard in front of the
    server sends the kept message on the subscribing connection itself
    (:class:`~interop.guard.FoxgloveGuard`, ``latched``)."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8766,
        name: str = "ucr",
        token: str | None = None,
        allowed_origins: tuple[str, ...] | list[str] = (),
        insecure: bool = False,
    ) -> None:
        self.guard = FoxgloveGuard(
            "ws://127.0.0.1:0", host, port, token, allowed_origins, insecure=insecure,
            latched=self.latched,
        )  # fmt: skip
        self._fg = foxglove
        self._ctx = foxglove.Context()
        self._channels: dict[str, Any] = {}
        self._latched: dict[str, tuple[bytes, int]] = {}
        self._lock = threading.Lock()
        self._closed = False
        self._listener = _Listener()
        self.server = foxglove.start_server(
            name=name, host="127.0.0.1", port=0, capabilities=[], server_listener=self._listener,
            supported_encodings=[ros2.MESSAGE_ENCODING], context=self._ctx,
        )  # fmt: skip
        self.guard.upstream = f"ws://127.0.0.1:{self.server.port}"
        try:
            self.guard.start()
        except BaseException:
            self.server.stop()
            raise
        self.port = self.guard.port
        self.host = host

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def latched(self, topic: str) -> tuple[bytes, int] | None:
        """The last message (CDR bytes, log time ns) of a latched topic, else None."""
        with self._lock:
            return self._latched.get(topic)

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
        """Nothing to do: the guard re-sends latched messages as clients subscribe."""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.guard.stop()
        for ch in self._channels.values():
            ch.close()
        self.server.stop()


class _Listener(ServerListener):
    """foxglove-sdk's server listener: it calls every method of
    :class:`foxglove.websocket.ServerListener` that applies (a missing one is logged as
    ``Callback failed`` at each event), so all are inherited, each a no-op: subscriptions need
    no action here (latched messages: the guard), the rest cannot happen on a server without
    capabilities."""


def sink_from_args(host: str, port: int, args: Any) -> FoxgloveSink:
    """A FoxgloveSink with the token of ``--serve-token-file`` (or $UCR_FOXGLOVE_TOKEN), the
    allowed origins and ``--insecure``. GuardError for a token given on the command line."""
    if getattr(args, "serve_token", None):
        raise GuardError(
            "--serve-token is refused: a token on the command line is visible to every user in "
            f"/proc; use --serve-token-file FILE (mode 0600) or ${ENV_SERVE_TOKEN}"
        )
    token = os.environ.get(ENV_SERVE_TOKEN) or None
    if getattr(args, "serve_token_file", None):
        try:
            token = read_token_file(args.serve_token_file)
        except AuthConfigError as exc:
            raise GuardError(str(exc)) from None
    return FoxgloveSink(
        host,
        port,
        token=token,
        allowed_origins=args.allow_origin or (),
        insecure=getattr(args, "insecure", False),
    )


def run(args: Any) -> int:
    """The ``ucr foxglove`` command."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    try:
        client = connect_daemon(args)
    except CliError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    sink = None
    try:
        robot, text = robot_for(client, args.robot)
        topics = RobotTopics(robot, text, args.subdivisions)
        try:
            sink = sink_from_args(args.host, args.port, args)
        except (GuardError, OSError, RuntimeError) as exc:
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
