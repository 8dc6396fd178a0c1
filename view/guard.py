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
import threading
from collections.abc import Callable, Iterable
from typing import Any

import websockets.asyncio.server as wss
from websockets.datastructures import Headers
from websockets.http11 import Response

from host.api.guard import WebGuard, is_loopback

__all__ = ["guarded_viser", "is_loopback", "page_guard", "refuse_reason"]


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

    def serve(*args: Any, **kwargs: Any) -> Any:
        inner = kwargs.get("process_request")

        def process_request(connection: Any, request: Any) -> Any:
            why = refuse_reason(request.headers, guard[0] if guard else None)
            if why is not None:
                log(f"refused a request: {why}")
                body = f"403 Forbidden: {why}\n".encode()
                return Response(http.HTTPStatus.FORBIDDEN, "Forbidden", Headers(), body)
            return inner(connection, request) if inner is not None else None

        kwargs["process_request"] = process_request
        return original(*args, **kwargs)

    with _patch_lock:
        wss.serve = serve
        try:
            return factory()
        finally:
            wss.serve = original
