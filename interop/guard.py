"""The door in front of the Foxglove server: foxglove-sdk's server cannot check a token, an
``Origin`` or a ``Host`` header, so it listens on a private loopback port and this small
WebSocket proxy (``websockets``) takes the public address and checks every opening handshake:

- ``Origin``: refused (403) unless absent (desktop apps, scripts) or listed (``allowed_origins``,
  e.g. ``https://app.foxglove.dev``): a web page in a local browser cannot read the robot;
- ``Host``: on a loopback bind it must name loopback (refuses DNS-rebinding pages);
- token: the API's rule: required for any non-loopback bind, and when given, required on loopback
  too; presented as ``Authorization: Bearer <token>`` or, for viewers that cannot set headers, a
  ``?token=`` query parameter; compared in constant time.

Frames are forwarded unchanged both ways (the Foxglove protocol is the server's business).
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import logging
import socket
import threading
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.http11 import Request, Response

log = logging.getLogger(__name__)
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # the same protocol, two names
_LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1", "[::1]"}


class GuardError(ValueError):
    """A refused configuration (non-loopback without token, bad token)."""


def is_loopback(host: str) -> bool:
    """True if every address ``host`` resolves to is a loopback address."""
    try:
        addrs = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except OSError as exc:
        raise GuardError(f"cannot resolve {host!r}: {exc}") from None
    return all(ipaddress.ip_address(a.split("%")[0]).is_loopback for a in addrs)


def check_token(token: str | None) -> None:
    """The API's token rule: at least 8 printable characters, no spaces."""
    if token is None:
        return
    if len(token) < 8 or not token.isprintable() or any(c.isspace() for c in token):
        raise GuardError("a token needs at least 8 printable characters and no spaces")


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
    ) -> None:
        check_token(token)
        self.loopback = is_loopback(host)
        if not self.loopback and token is None:
            raise GuardError(
                f"refusing to serve Foxglove on {host} without a token (--serve-token or "
                "$UCR_FOXGLOVE_TOKEN): anyone on the network could watch the robot"
            )
        self.upstream = upstream
        self.host = host
        self.requested_port = port
        self.token = token
        self.origins = {o.rstrip("/") for o in allowed_origins}
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
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
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
        ) as server:  # fmt: skip
            self.port = next(iter(server.sockets)).getsockname()[1]
            self._ready.set()
            await self._stop.wait()
            server.close(close_connections=True)
            await server.wait_closed()

    def _refuse(self, conn: ServerConnection, status: HTTPStatus, why: str) -> Response:
        self.refused += 1
        log.warning("Foxglove: refused %s: %s", conn.remote_address, why)
        return conn.respond(status, why + "\n")

    def _authorize(self, conn: ServerConnection, request: Request) -> Response | None:
        origin = request.headers.get("Origin")
        if origin is not None and origin.rstrip("/") not in self.origins:
            return self._refuse(
                conn, HTTPStatus.FORBIDDEN, f"origin {origin} not allowed (--allow-origin)"
            )
        if self.loopback:
            host = (request.headers.get("Host") or "").rsplit(":", 1)[0].lower()
            if host not in _LOOPBACK_NAMES:
                return self._refuse(conn, HTTPStatus.FORBIDDEN, f"host {host!r} is not loopback")
        if self.token is not None:
            scheme, _, given = request.headers.get("Authorization", "").partition(" ")
            if scheme.lower() != "bearer":
                given = (parse_qs(urlsplit(request.path).query).get("token") or [""])[0]
            if not hmac.compare_digest(given.strip().encode(), self.token.encode()):
                return self._refuse(conn, HTTPStatus.UNAUTHORIZED, "missing or wrong token")
        return None

    async def _handle(self, ws: ServerConnection) -> None:
        self.connections += 1
        try:
            async with connect(self.upstream, subprotocols=[SUBPROTOCOLS[0]], max_size=None,
                               compression=None, open_timeout=5) as up:  # fmt: skip
                pumps = [asyncio.create_task(_pump(ws, up)), asyncio.create_task(_pump(up, ws))]
                _, pending = await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
                for p in pending:
                    p.cancel()
        except (ConnectionClosed, WebSocketException, OSError, TimeoutError) as exc:
            log.info("Foxglove: connection ended: %s", exc)


async def _pump(src: Any, dst: Any) -> None:
    try:
        async for msg in src:
            await dst.send(msg)
    except ConnectionClosed:
        pass
    finally:
        await dst.close()
