"""``ucr foxglove``: the live robot on the Foxglove WebSocket protocol, with the same topics,
schemas and CDR bytes as a recording, for Foxglove and Lichtblick.

Read-only: the server advertises no capability (no client publishing, services, parameters or
playback control), so a connected client can only watch. The server is
:class:`~interop.guard.FoxgloveGuard`: one listener that checks every handshake with the API's
token rule, ``Origin`` and ``Host`` checks and speaks the protocol itself
(:mod:`interop.foxglove_protocol`); no other server runs behind it (docs/recording.md, security).
"""

from __future__ import annotations

import os
import sys
from typing import Any

from host.api.auth import AuthConfigError, read_token_file
from host.api.client import ApiError
from host.client_common import CliError, connect_daemon
from host.listen import ListenError, listen_failure
from host.stopsignals import StopSignals
from interop.guard import FoxgloveGuard, GuardError
from interop.live import DaemonLink, FeedError, LiveFeed, robot_for, run_reconnecting
from interop.sinks import Fanout
from interop.topics import LATCHED, RobotTopics

ENV_SERVE_TOKEN = "UCR_FOXGLOVE_TOKEN"


class FoxgloveSink:
    """The Foxglove server as a sink: one channel per topic, advertised before its first message
    (:meth:`advertise`: the live feed and a replay announce every topic they will write, so a
    client can subscribe before data flows; a topic never announced is advertised with its first
    message, which then reaches no client). Latched topics (/robot_description, /tf_static, the
    U(C)RDF) are sent again to each new subscriber of theirs, and to it only."""

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8766,
        name: str = "ucr",
        token: str | None = None,
        allowed_origins: tuple[str, ...] | list[str] = (),
        insecure: bool = False,
        tls_cert: str | None = None,
        tls_key: str | None = None,
    ) -> None:
        self.guard = FoxgloveGuard(
            host, port, token, allowed_origins, insecure=insecure, name=name, latched=LATCHED,
            tls_cert=tls_cert, tls_key=tls_key,
        ).start()  # fmt: skip
        self.tls = tls_cert is not None
        self._closed = False
        self.port = self.guard.port
        self.host = host

    @property
    def url(self) -> str:
        host = self.host if ":" not in self.host else f"[{self.host}]"
        return f"{'wss' if self.tls else 'ws'}://{host}:{self.port}"

    def latched(self, topic: str) -> tuple[bytes, int] | None:
        """The last message (CDR bytes, log time ns) of a latched topic, else None."""
        return self.guard.latched(topic)

    def advertise(self, channels: list[tuple[str, str, str]]) -> None:
        """Advertise ``(topic, typename, schema)`` channels now, before their messages."""
        self.guard.advertise(channels)

    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        self.guard.write(topic, typename, schema, data, t_ns)

    def tick(self) -> None:
        """Nothing to do: latched messages go out as clients subscribe."""

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self.guard.stop()


def sink_from_args(host: str, port: int, args: Any, option: str = "--port") -> FoxgloveSink:
    """A FoxgloveSink with the token of ``--serve-token-file`` (or $UCR_FOXGLOVE_TOKEN), the
    allowed origins, ``--tls-cert``/``--tls-key`` and ``--insecure``. GuardError for a token
    given on the command line; ListenError (an OSError, naming the address) for an address that
    cannot be bound (``option``: its port's option, in the advice)."""
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
    try:
        return FoxgloveSink(
            host,
            port,
            token=token,
            allowed_origins=args.allow_origin or (),
            insecure=getattr(args, "insecure", False),
            tls_cert=getattr(args, "tls_cert", None),
            tls_key=getattr(args, "tls_key", None),
        )
    except OSError as exc:
        if exc.errno is None or isinstance(exc, FileNotFoundError | PermissionError):
            raise  # not the bind (a certificate file): the caller's message
        raise ListenError(exc.errno, listen_failure(host, port, exc, option)) from None


def run(args: Any) -> int:
    """The ``ucr foxglove`` command."""
    signals = StopSignals().install()
    try:
        link = DaemonLink(connect_daemon(args))  # the client of the moment: a restart replaces it
    except CliError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return exc.exit_code
    sink = None
    try:
        robot, text = robot_for(link, args.robot)
        topics = RobotTopics(robot, text, args.subdivisions)
        try:
            sink = sink_from_args(args.host, args.port, args)
        except ListenError as exc:  # it names the address
            print(f"ucr: cannot serve Foxglove: {exc}", file=sys.stderr)
            return 1
        except (GuardError, OSError, RuntimeError) as exc:
            print(f"ucr: cannot serve Foxglove on {args.host}:{args.port}: {exc}", file=sys.stderr)
            return 1
        print(f"ucr: Foxglove WebSocket server on {sink.url} (open it in Foxglove or Lichtblick: "
              "Open connection -> Foxglove WebSocket)", file=sys.stderr, flush=True)  # fmt: skip
        out = Fanout([sink])
        # a daemon restart: the server and its clients stay, the gap marked by two events
        run_reconnecting(
            link, lambda client: LiveFeed(client, topics, out, viz_rate=args.viz_rate),
            signals.stop, lambda: connect_daemon(args), robot_text=text, robot_path=args.robot,
            duration=args.duration, say=lambda line: print(f"ucr: {line}", file=sys.stderr),
        )  # fmt: skip
        return signals.exit_code()
    except FeedError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    except ApiError as exc:
        print(f"ucr: Foxglove server stopped: {exc}", file=sys.stderr)
        return 1
    finally:
        if sink is not None:
            sink.close()
        link.close()
