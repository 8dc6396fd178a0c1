"""Host/Origin guard for the view's web server: a page that can move hardware is an attack surface.

A web page on another site (cross-site WebSocket hijacking) or a DNS-rebinding name pointing at
127.0.0.1 could otherwise drive the robot through a browser on the same machine. Every HTTP request
must name an allowed ``Host``; a request carrying an ``Origin`` (every browser WebSocket does) must
come from the view's own page. The rules are the project's browser guard (``host.api.guard``);
anything refused gets HTTP 403 before the WebSocket opens. viser offers no hook for this, so
:func:`guarded_viser` wraps the ``process_request`` of the one ``websockets`` server viser starts
(see docs/view.md).

The same wrapper bounds what a page client may cost (:data:`MAX_FRAME_BYTES` per message,
:data:`MAX_CONNECTIONS` page WebSockets without the page token, :data:`MAX_PER_ADDRESS` from one
remote address) and carries the page's credential (:class:`PageToken`): a secret made at each
start and printed in the view's URL (``?token=…``, as Jupyter does), exchanged for a path holding
it (``/t/<secret>/``, never a cookie: cookies reach every port of a host) that the page's
WebSocket presents in its own path; only a page client presenting it gets controls.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import hmac
import http
import io
import ipaddress
import secrets
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import parse_qsl, urlencode, urlsplit

import websockets.asyncio.server as wss
from websockets.datastructures import Headers
from websockets.http11 import Response

from host.api.guard import GuardConfigError, WebGuard, is_loopback, normalize_origin

__all__ = [
    "MAX_CONNECTIONS",
    "MAX_FRAME_BYTES",
    "MAX_PER_ADDRESS",
    "GuardError",
    "PageGate",
    "PageToken",
    "guarded_viser",
    "is_loopback",
    "own_origins",
    "page_guard",
    "peer_address",
    "probe_refuses_foreign_host",
    "refuse_reason",
]

#: The Host a probe sends: never an allowed name (not an IP literal, never --allow-host-able).
PROBE_HOST = "ucr-guard-probe.invalid"
#: Largest WebSocket message a page client may send (viser asks for 50 MiB). The page sends its
#: camera pose, slider values, button clicks and gizmo drags: a few hundred bytes each (the
#: largest measured on a page with sliders typed, a checkbox clicked, the camera dragged and the
#: window resized: a 231-byte camera pose). A larger message closes that connection (1009)
#: before its payload is read.
MAX_FRAME_BYTES = 64 * 1024
#: Messages read ahead per connection (so at most MAX_QUEUE * MAX_FRAME_BYTES buffered each).
MAX_QUEUE = 4
#: Page WebSockets without the page token: in total, and from one remote address (loopback
#: peers count only in the total). One more is refused with HTTP 503 before it opens. A page
#: presenting the page token (the operator's) is always admitted.
MAX_CONNECTIONS = 32
MAX_PER_ADDRESS = 8
#: Seconds a client has to complete its opening handshake.
OPEN_TIMEOUT_S = 5.0


class GuardError(RuntimeError):
    """The page server could not be guarded (viser's internals changed): it is not served."""


def page_guard(bind: str, port: int, extra: Iterable[str] = ()) -> WebGuard:
    """The project's browser guard (host/api/guard.py) for the view's page on ``bind:port``:
    its own origins (loopback names, the bind address, ``extra`` names) and those hosts."""
    names = ["127.0.0.1", "localhost", "[::1]", *extra]
    if bind not in ("0.0.0.0", "::", ""):
        names.append(f"[{bind}]" if ":" in bind and not bind.startswith("[") else bind)
    origins = [f"{scheme}://{n}:{port}" for n in names for scheme in ("http", "https")]
    plain = [n for n in extra if n]
    return WebGuard.build(bind=bind, port=port, origins=origins, names=plain)


def _all(headers: Any, name: str) -> list[str]:
    get_all = getattr(headers, "get_all", None)
    if get_all is not None:
        return list(get_all(name))
    value = headers.get(name)
    return [] if value is None else [value]


def own_origins(headers: Any, port: int) -> frozenset[str]:
    """The origin of a page served under this request's ``Host`` (``http(s)://`` + that
    host:port), when that Host names the server's ``port`` (explicitly, or as the scheme's
    default port); empty otherwise. Whether the Host itself is acceptable is the guard's check."""
    hosts = _all(headers, "Host")
    if len(hosts) != 1 or not port:
        return frozenset()
    host = hosts[0].strip()
    try:
        named = urlsplit(f"//{host}").port
    except ValueError:
        return frozenset()
    own = set()
    for scheme, default in (("http", 80), ("https", 443)):
        if (named or default) == port:
            try:
                own.add(normalize_origin(f"{scheme}://{host}"))
            except GuardConfigError:
                pass  # not a host[:port]: the guard's Host check refuses it anyway
    return frozenset(own)


def refuse_reason(headers: Any, guard: WebGuard | None) -> str | None:
    """Why a request must be refused (None: allowed); everything while the guard is not set.

    The page's own origin (the host:port it was served under, i.e. this request's ``Host``) is
    allowed besides the configured ones: a page reached at ``http://192.0.2.2:8080`` opens its
    WebSocket with that Origin and that Host. The Host must still pass the guard's Host check.
    Paths are viser's business (its static files, with its own traversal check), so the guard's
    path rule is not applied here."""
    if guard is None:
        return "the page server is starting"
    own = own_origins(headers, guard.port)
    if own - guard.origins:
        guard = WebGuard(
            guard.origins | own, guard.names, guard.port, guard.path, guard.extra_paths
        )
    refusal = guard.check(guard.path, headers)
    return None if refusal is None else refusal.reason


def peer_address(connection: Any) -> str:
    """``host:port`` of a connection's remote end (``[v6]:port``), ``?`` if unknown."""
    addr = getattr(connection, "remote_address", None)
    if not addr:
        return "?"
    host, port = str(addr[0]), addr[1]
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def _peer_ip(connection: Any) -> str:
    addr = getattr(connection, "remote_address", None)
    return str(addr[0]) if addr else "?"


def _is_loopback_ip(ip: str) -> bool:
    try:
        return ipaddress.ip_address(ip).is_loopback
    except ValueError:
        return False


class PageToken:
    """The page's credential for controls: a random secret made at each start of the view.

    It is printed in the view's URL (``http://127.0.0.1:PORT/?token=…``). A request for the page
    carrying it in its query is redirected to the page under a path that holds it
    (:attr:`page_path`, ``/t/<secret>/``); viser's page opens its WebSocket on the URL it was
    loaded from (``ws://127.0.0.1:PORT/t/<secret>``), so the WebSocket presents it in its request
    path. Never in a cookie: a browser sends a host's cookies to every port of that host (another
    local web server on 127.0.0.1 would receive it), while a path is sent only to the server it
    names. Compared in constant time."""

    QUERY = "token"
    PREFIX = "/t/"

    def __init__(self, secret: str | None = None) -> None:
        self.secret = secret or secrets.token_urlsafe(32)
        self.port = 0  # set once the server is bound

    @property
    def page_path(self) -> str:
        """The page with controls: its WebSocket's path is this without the final ``/``."""
        return f"{self.PREFIX}{self.secret}/"

    def matches(self, value: str) -> bool:
        return hmac.compare_digest(value.encode(), self.secret.encode())

    def split(self, path: str) -> tuple[str, str] | None:
        """``(secret given, rest of the path)`` for a path under :data:`PREFIX` (the query
        dropped; rest ``""`` without a final slash), else None."""
        path = path.partition("?")[0]
        if not path.startswith(self.PREFIX):
            return None
        given, slash, rest = path[len(self.PREFIX) :].partition("/")
        return given, slash + rest

    def presented(self, request: Any) -> bool:
        """Whether a request (the page's WebSocket) carries the token in its path."""
        parts = self.split(str(getattr(request, "path", "") or ""))
        return parts is not None and parts[1] in ("", "/") and self.matches(parts[0])


class PageGate:
    """What the page server admits besides the Host/Origin guard: the page token (in the
    WebSocket's path, see :class:`PageToken`), and a cap on page WebSockets without it
    (:data:`MAX_CONNECTIONS`, :data:`MAX_PER_ADDRESS`). ``guard`` is set once the port is known;
    until then everything is refused."""

    def __init__(
        self,
        token: PageToken | None = None,
        max_connections: int = MAX_CONNECTIONS,
        max_per_address: int = MAX_PER_ADDRESS,
    ) -> None:
        self.guard: WebGuard | None = None
        self.token = token
        self.max_connections = max_connections
        self.max_per_address = max_per_address
        self._open: dict[Any, str] = {}  # page WebSockets without the token -> remote IP
        self._tasks: set[asyncio.Task] = set()

    def arm(self, guard: WebGuard) -> None:
        if self.token is not None:
            self.token.port = guard.port
        self.guard = guard

    def has_token(self, request: Any) -> bool:
        """Whether a page WebSocket's request presents the page token (in its path)."""
        return self.token is not None and self.token.presented(request)

    @property
    def open_without_token(self) -> int:
        return len(self._open)

    def admit(self, connection: Any, request: Any, log: Callable[[str], None]) -> Any:
        """None to go on (viser serves the file or opens the WebSocket), else the Response."""
        headers = request.headers
        if str(headers.get("Upgrade", "")).lower() != "websocket":
            return self._page_request(connection, request, log)
        if self.has_token(request):
            return None  # the operator's page: never locked out by a crowd of viewers
        ip = _peer_ip(connection)
        same = sum(1 for v in self._open.values() if v == ip)
        if len(self._open) >= self.max_connections or (
            same >= self.max_per_address and not _is_loopback_ip(ip)
        ):
            why = (
                f"too many page connections ({len(self._open)} open, {same} from {ip}; "
                f"at most {self.max_connections}, {self.max_per_address} per address)"
            )
            log(f"refused a page connection from {peer_address(connection)}: {why}")
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE, f"{why}\n")
        self._open[connection] = ip
        task = asyncio.get_running_loop().create_task(self._forget(connection))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)
        return None

    async def _forget(self, connection: Any) -> None:
        try:
            await connection.wait_closed()
        finally:
            self._open.pop(connection, None)

    def _page_request(self, connection: Any, request: Any, log: Callable[[str], None]) -> Any:
        """A plain HTTP request. ``?token=`` is answered with a redirect to the page under the
        token's path (a wrong one: to the plain page, view only, logged); a request under that
        path is served as the same path without it (``/t/<secret>/`` is viser's ``/``), with
        ``Referrer-Policy: no-referrer``; a wrong secret there gets 404. Returns the Response,
        ``None`` (viser serves the request as it is) or a rewritten request for viser."""
        if self.token is None:
            return None
        parts = urlsplit(request.path)
        query = parse_qsl(parts.query, keep_blank_values=True)
        given = [v for k, v in query if k == PageToken.QUERY]
        rest = urlencode([(k, v) for k, v in query if k != PageToken.QUERY])
        under = self.token.split(request.path)
        query_kept = parts.query
        if given and under is not None and self.token.matches(under[0]):
            given = []  # already on the page with controls: a stale ?token= does not take it away
            query_kept = rest
        if given:
            right = all(self.token.matches(v) for v in given)
            if not right:
                log(f"a page request from {peer_address(connection)} had a wrong token: view only")
            # always this server's own page: a path such as //evil.example would be another site
            where = self.token.page_path if right else "/"
            return _redirect(connection, where + (f"?{rest}" if rest else ""))
        if under is None:
            return None
        secret, path = under
        if not self.token.matches(secret):
            log(f"a page request from {peer_address(connection)} had a wrong token path: 404")
            return connection.respond(http.HTTPStatus.NOT_FOUND, "NOT FOUND\n")
        tail = f"?{query_kept}" if query_kept else ""
        if not path:  # /t/<secret>: the page's relative URLs need the final slash
            return _redirect(connection, self.token.page_path + tail)
        return _Rewritten(path + tail)


class _Rewritten(str):
    """The path viser is to serve instead of the request's (under the page token's path)."""


def _redirect(connection: Any, location: str) -> Any:
    """302 to ``location`` (this server's own path), with :func:`_secret_page_headers`."""
    response = connection.respond(http.HTTPStatus.FOUND, "")
    response.headers["Location"] = location
    return _secret_page_headers(response)


def _secret_page_headers(response: Any) -> Any:
    """The page under the token's path: never cached, never named in a Referer."""
    headers = getattr(response, "headers", None)
    if headers is not None:
        headers["Cache-Control"] = "no-store"
        headers["Referrer-Policy"] = "no-referrer"
    return response


_patch_lock = threading.Lock()


def guarded_viser(factory: Callable[[], Any], gate: PageGate, log: Callable[[str], None]) -> Any:
    """Build a ViserServer (``factory``) whose web server refuses requests failing the guard
    (``gate.guard`` once set: the port is known only after binding), admits them through
    ``gate`` (page token, connection cap) and reads page messages of at most MAX_FRAME_BYTES.

    ``websockets.asyncio.server.serve`` is wrapped only while the server starts (viser looks it
    up at call time and the constructor returns once it listens); other servers are unaffected.
    viser's start-up banner (a URL without the page token) is not printed: the view prints the
    URL that works.
    """
    original = wss.serve
    calls: list[Any] = []  # the port of each serve() call

    def serve(*args: Any, **kwargs: Any) -> Any:
        calls.append(kwargs.get("port", args[2] if len(args) > 2 else None))
        inner = kwargs.get("process_request")

        def process_request(connection: Any, request: Any) -> Any:
            why = refuse_reason(request.headers, gate.guard)
            if why is not None:
                if not str(request.headers.get("Host", "")).startswith(PROBE_HOST):
                    log(f"refused a request: {why}")  # (our own start-up probe: not news)
                body = f"403 Forbidden: {why}\n".encode()
                return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", Headers(), body)
            answer = gate.admit(connection, request, log)
            if isinstance(answer, _Rewritten):  # the page under the token's path
                rewritten = dataclasses.replace(request, path=str(answer))
                served = inner(connection, rewritten) if inner is not None else None
                return _secret_page_headers(served)
            if answer is not None:
                return answer
            return inner(connection, request) if inner is not None else None

        kwargs["process_request"] = process_request
        kwargs["max_size"] = MAX_FRAME_BYTES  # viser asks for 50 MiB
        kwargs["max_queue"] = MAX_QUEUE
        kwargs["open_timeout"] = OPEN_TIMEOUT_S
        return original(*args, **kwargs)

    with _patch_lock:
        wss.serve = serve
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: a URL, no token
                server = factory()
        finally:
            wss.serve = original
    if len(calls) > 1 and _moved_on(calls):  # the port was taken: viser tried the next ones
        _stop_quietly(server)
        raise OSError(f"port {calls[0]} already in use")
    if len(calls) != 1:  # viser no longer starts one websockets server through serve(): fail closed
        _stop_quietly(server)
        raise GuardError(
            f"viser started {len(calls)} guarded web servers instead of 1 (its internals changed; "
            "view/guard.py supports the pinned viser): the page is not served"
        )
    return server


def _moved_on(ports: list[Any]) -> bool:
    """Whether the serve() calls are viser's walk past a port in use: P, P+1, P+2, ..."""
    return (
        isinstance(ports[0], int)
        and ports[0] > 0
        and ports == list(range(ports[0], ports[0] + len(ports)))
    )


def probe_refuses_foreign_host(host: str, port: int, timeout: float = 10.0) -> str | None:
    """Ask the running page server for ``/`` with a foreign ``Host``; None if it answers 403 as
    the guard does, else why not (the guard is not in the path: fail closed)."""
    addr = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
    try:
        with socket.create_connection((addr, port), timeout=timeout) as s:
            s.sendall(f"GET / HTTP/1.1\r\nHost: {PROBE_HOST}:{port}\r\n\r\n".encode())
            head = s.recv(64)
    except OSError as exc:
        return f"probe failed: {exc}"
    status = head.split(b"\r\n", 1)[0].decode("latin-1", "replace")
    return None if status.split()[1:2] == ["403"] else f"a foreign Host got {status!r}, not 403"


def _stop_quietly(server: Any) -> None:
    try:
        server.stop()
    except Exception:  # noqa: BLE001, S110 - refusing to serve anyway
        pass
