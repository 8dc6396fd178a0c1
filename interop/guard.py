"""The door in front of the Foxglove server: foxglove-sdk's server cannot check a token, an
``Origin`` or a ``Host`` header, so it listens on a private loopback port and this small
WebSocket proxy (``websockets``) takes the public address and checks every opening handshake
with the same rules as the daemon's API (one implementation: :mod:`host.api.guard` for Origin,
Host and path, :mod:`host.api.auth` for tokens and the bind policy):

- ``Origin``: refused (403) unless absent (desktop apps, scripts) or listed (``allowed_origins``,
  e.g. ``https://app.foxglove.dev``): a web page in a local browser cannot read the robot;
- ``Host``: an IP literal or a name of this server (refuses DNS-rebinding pages); path ``/``;
- token: required for any non-loopback bind (which also needs TLS or ``insecure``), and when
  given, required on loopback too; at least 16 characters; presented as
  ``Authorization: Bearer <token>`` or, for viewers that cannot set headers, a ``?token=`` query
  parameter; compared in constant time.

Frames are forwarded unchanged both ways (the Foxglove protocol is the server's business), with
one addition: when a client subscribes to a latched topic (``latched``), the guard sends that
client the topic's kept message on its subscription, so a new subscriber gets it and the other
clients do not get it again.

A malformed handshake (no WebSocket upgrade, e.g. ``curl``; no or a foreign subprotocol; not HTTP)
is refused by ``websockets`` itself; it is logged as one line (``Foxglove: refused ADDR: why``)
like the guard's own refusals, not as a traceback.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import sys
import threading
from collections.abc import Callable
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.http11 import Request, Response

from host.api.auth import AuthConfigError, Token, check_bind, check_token_text, find_token
from host.api.guard import GuardConfigError, WebGuard

log = logging.getLogger(__name__)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the same protocol, two names
MESSAGE_DATA = 0x01  # the protocol's binary opcode: u32 subscription id, u64 log time, payload
Latched = Callable[[str], "tuple[bytes, int] | None"]  # topic -> (data, log time ns) or None


class GuardError(ValueError):
    """A refused configuration (non-loopback without token or TLS, bad token, bad origin)."""


class FoxgloveGuard:
    """Checks handshakes on ``host:port`` and forwards accepted connections to ``upstream``
    (the foxglove-sdk server on loopback). Runs its own event loop in a thread."""

    def __init__(
        self,
        upstream: str,
        host: str,
        port: int,
        token: str | None = None,
        allowed_origins: tuple[str, ...] | list[str] = (),
        insecure: bool = False,
        latched: Latched | None = None,
    ) -> None:
        try:
            tokens = (
                (Token(check_token_text(token, "the Foxglove token"), "read", "foxglove"),)
                if token is not None
                else ()
            )
            check_bind(host, tokens, tls=False, insecure=insecure)
            self.web = WebGuard.build(bind=host, port=port, origins=allowed_origins, path="/")
        except (AuthConfigError, GuardConfigError) as exc:
            msg = (
                str(exc)
                .replace("api.tokens", "--serve-token-file")
                .replace("api.tls (cert, key), or set api.insecure: true", "--insecure")
            )
            raise GuardError(f"Foxglove server: {msg}") from None
        self.upstream = upstream
        self.latched = latched
        self.host = host
        self.requested_port = port
        self.tokens = tokens
        self.port: int | None = None
        self.refused = 0
        self.connections = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="foxglove-guard", daemon=True)

    def start(self) -> FoxgloveGuard:
        self._thread.start()
        self._ready.wait(10)
        if self._error is not None:
            raise self._error
        if self.port is None:
            raise GuardError("the Foxglove guard did not start")
        return self

    def stop(self) -> None:
        """Stop serving (again: nothing)."""
        loop = self._loop
        if loop is not None and self._stop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._stop.set)
            except RuntimeError:  # closed meanwhile: stopped already
                pass
        if self._thread.is_alive():
            self._thread.join(5)

    # -- server --------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        async with serve(
            self._handle, self.host, self.requested_port, subprotocols=SUBPROTOCOLS,
            process_request=self._authorize, max_size=None, compression=None,
            ping_interval=20, ping_timeout=20, server_header="ucr-foxglove",
            logger=_HandshakeLog(self),
        ) as server:  # fmt: skip
            self.port = next(iter(server.sockets)).getsockname()[1]
            self.web = self.web.with_port(self.port)
            self._ready.set()
            await self._stop.wait()
            server.close(close_connections=True)
            await server.wait_closed()

    def _refuse(self, conn: ServerConnection, status: HTTPStatus, why: str) -> Response:
        self.refused += 1
        log.warning("Foxglove: refused %s: %s", conn.remote_address, why)
        return conn.respond(status, why + "\n")

    def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        parts = urlsplit(request.path)
        refusal = self.web.check(parts.path, request.headers)
        if refusal is not None:
            return self._refuse(conn, HTTPStatus(refusal.status), refusal.reason)
        if self.tokens:
            header = request.headers.get("Authorization", "")
            if not header.lower().startswith("bearer "):
                given = (parse_qs(parts.query).get("token") or [""])[0]
                header = f"Bearer {given}"
            if find_token(self.tokens, header) is None:
                return self._refuse(conn, HTTPStatus.UNAUTHORIZED, "missing or wrong token")
        return None

    async def _handle(self, ws: ServerConnection) -> None:
        self.connections += 1
        channels: dict[int, str] = {}  # the server's channel ids on this connection -> topic
        try:
            async with connect(self.upstream, subprotocols=[SUBPROTOCOLS[0]], max_size=None,
                               compression=None, open_timeout=5) as up:  # fmt: skip
                subscribed = lambda m: self._from_client(m, ws, channels)  # noqa: E731
                advertised = lambda m: _from_server(m, channels)  # noqa: E731
                pumps = [asyncio.create_task(_pump(ws, up, subscribed)),
                         asyncio.create_task(_pump(up, ws, advertised))]  # fmt: skip
                _, pending = await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for p in pending:
                    p.cancel()
        except (ConnectionClosed, WebSocketException, OSError, TimeoutError) as exc:
            log.info("Foxglove: connection ended: %s", exc)

    async def _from_client(self, msg: Any, ws: ServerConnection, channels: dict[int, str]) -> None:
        """After a client's ``subscribe`` went to the server: the kept message of each latched
        topic it subscribed to, on its subscription id, to this client only."""
        if self.latched is None or not isinstance(msg, str):
            return
        for sub_id, channel_id in _subscriptions(msg):
            kept = self.latched(channels.get(channel_id, ""))
            if kept is not None:
                data, t_ns = kept
                await ws.send(struct.pack("<BIQ", MESSAGE_DATA, sub_id, t_ns) + data)


def _subscriptions(text: str) -> list[tuple[int, int]]:
    """(subscription id, channel id) of a client's ``subscribe`` message, else []."""
    try:
        msg = json.loads(text)
        if msg.get("op") != "subscribe":
            return []
        return [(int(s["id"]), int(s["channelId"])) for s in msg.get("subscriptions") or ()]
    except (ValueError, TypeError, KeyError, AttributeError):
        return []  # not ours to judge: the server answers it


async def _from_server(msg: Any, channels: dict[int, str]) -> None:
    """Keep the channel ids the server advertises on this connection (topic names)."""
    if not isinstance(msg, str) or '"advertise"' not in msg and '"unadvertise"' not in msg:
        return
    try:
        m = json.loads(msg)
        if m.get("op") == "advertise":
            channels.update({int(c["id"]): str(c["topic"]) for c in m.get("channels") or ()})
        elif m.get("op") == "unadvertise":
            for cid in m.get("channelIds") or ():
                channels.pop(int(cid), None)
    except (ValueError, TypeError, KeyError, AttributeError):
        pass


async def _pump(src: Any, dst: Any, after: Callable[[Any], Any] | None = None) -> None:
    try:
        async for msg in src:
            await dst.send(msg)
            if after is not None:
                await after(msg)
    except ConnectionClosed:
        pass
    finally:
        await dst.close()


def _why(exc: BaseException | None) -> str:
    """An exception and its causes on one line."""
    parts = []
    while exc is not None and len(parts) < 4:
        text = str(exc).strip().splitlines()
        parts.append(text[0] if text else type(exc).__name__)
        exc = exc.__cause__
    return "; ".join(parts) or "invalid handshake"


class _HandshakeLog(logging.LoggerAdapter):
    """The ``websockets`` server's logger: a handshake it refuses itself (no upgrade, no common
    subprotocol, not HTTP) is logged as one line, as the guard's own refusals, not with a
    traceback; everything else goes to ``websockets.server`` unchanged."""

    def __init__(self, guard: FoxgloveGuard) -> None:
        super().__init__(logging.getLogger("websockets.server"), {})
        self.guard = guard

    def log(self, level: int, msg: object, *args: object, **kwargs: Any) -> None:
        if msg == "opening handshake failed" and kwargs.get("exc_info"):
            conn = (kwargs.get("extra") or {}).get("websocket")
            self.guard.refused += 1
            log.warning("Foxglove: refused %s: %s", getattr(conn, "remote_address", "?"),
                        _why(sys.exc_info()[1]))  # fmt: skip
            return
        super().log(level, msg, *args, **kwargs)

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # keep the connection's own ``extra``
