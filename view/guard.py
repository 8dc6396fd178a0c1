"""Host/Origin guard for the view's web server: a page that can move hardware is an attack surface.

A web page on another site (cross-site WebSocket hijacking) or a DNS-rebinding name pointing at
127.0.0.1 could otherwise drive the robot through a browser on the same machine. Every HTTP request
must name an allowed ``Host``; a request carrying an ``Origin`` (every browser WebSocket does) must
come from the view's own page. The rules are the project's browser guard (``host.api.guard``);
anything refused gets HTTP 403 before the WebSocket opens. viser offers no hook for this, so
:func:`guarded_viser` wraps the ``process_request`` of the one ``websockets`` server viser starts
(see docs/view.md).
"""

from __future__ import annotations

import http
import socket
import threading
from collections.abc import Callable, Iterable
from typing import Any

import websockets.asyncio.server as wss
from websockets.datastructures import Headers
from websockets.http11 import Response

from host.api.guard import WebGuard, is_loopback

__all__ = [
    "GuardError",
    "guarded_viser",
    "is_loopback",
    "page_guard",
    "probe_refuses_foreign_host",
    "refuse_reason",
]

#: The Host a probe sends: never an allowed name (not an IP literal, never --allow-host-able).
PROBE_HOST = "ucr-guard-probe.invalid"


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


def refuse_reason(headers: Any, guard: WebGuard | None) -> str | None:
    """Why a request must be refused (None: allowed); everything while the guard is not set.

    Paths are viser's business (its static files, with its own traversal check), so the guard's
    path rule is not applied here."""
    if guard is None:
        return "the page server is starting"
    refusal = guard.check(guard.path, headers)
    return None if refusal is None else refusal.reason


_patch_lock = threading.Lock()


def guarded_viser(
    factory: Callable[[], Any], guard: list[WebGuard], log: Callable[[str], None]
) -> Any:
    """Build a ViserServer (``factory``) whose web server refuses requests failing the guard
    (``guard[0]`` once set: the port is known only after binding).

    ``websockets.asyncio.server.serve`` is wrapped only while the server starts (viser looks it
    up at call time and the constructor returns once it listens); other servers are unaffected.
    """
    original = wss.serve
    calls: list[Any] = []  # the port of each serve() call

    def serve(*args: Any, **kwargs: Any) -> Any:
        calls.append(kwargs.get("port", args[2] if len(args) > 2 else None))
        inner = kwargs.get("process_request")

        def process_request(connection: Any, request: Any) -> Any:
            why = refuse_reason(request.headers, guard[0] if guard else None)
            if why is not None:
                if not str(request.headers.get("Host", "")).startswith(PROBE_HOST):
                    log(f"refused a request: {why}")  # (our own start-up probe: not news)
                body = f"403 Forbidden: {why}\n".encode()
                return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", Headers(), body)
            return inner(connection, request) if inner is not None else None

        kwargs["process_request"] = process_request
        return original(*args, **kwargs)

    with _patch_lock:
        wss.serve = serve
        try:
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
