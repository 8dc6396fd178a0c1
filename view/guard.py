"""Host/Origin guard for the view's web server: a page that can move hardware is an attack surface.

A web page on another site (cross-site WebSocket hijacking) or a DNS-rebinding name pointing at
127.0.0.1 could otherwise drive the robot through a browser on the same machine. Every HTTP request
must name an allowed ``Host``; a request carrying an ``Origin`` (every browser WebSocket does) must
come from a page served under an allowed host. Anything else gets HTTP 403 before the WebSocket
opens. viser offers no hook for this, so :func:`guarded_viser` wraps the ``process_request`` of the
one ``websockets`` server viser starts (see docs/view.md).
"""

from __future__ import annotations

import http
import ipaddress
import threading
from collections.abc import Callable, Iterable
from typing import Any
from urllib.parse import urlsplit

import websockets.asyncio.server as wss
from websockets.datastructures import Headers
from websockets.http11 import Response

LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def allowed_hosts(bind: str, port: int, extra: Iterable[str] = ()) -> set[str]:
    """``host:port`` values a request's Host header may carry (loopback names always)."""
    names = set(LOOPBACK_NAMES) | {h for h in extra if h}
    if bind not in ("0.0.0.0", "::", ""):
        names.add(f"[{bind}]" if ":" in bind else bind)
    return {f"{n.lower()}:{port}" for n in names}


def refuse_reason(headers: Any, allowed: set[str]) -> str | None:
    """Why a request must be refused (None: allowed). ``headers`` has a ``get(name)``."""
    host = (headers.get("Host") or "").strip().lower()
    if host not in allowed:
        return f"Host {host or '(none)'!r} is not allowed"
    origin = headers.get("Origin")
    if origin is not None:
        parts = urlsplit(origin.strip().lower())
        if parts.scheme not in ("http", "https") or parts.netloc not in allowed:
            return f"Origin {origin!r} is not allowed"
    return None


_patch_lock = threading.Lock()


def guarded_viser(factory: Callable[[], Any], allowed: set[str], log: Callable[[str], None]) -> Any:
    """Build a ViserServer (``factory``) whose web server refuses requests failing the guard.

    ``websockets.asyncio.server.serve`` is wrapped only while the server starts (viser looks it
    up at call time and the constructor returns once it listens); other servers are unaffected.
    """
    original = wss.serve

    def serve(*args: Any, **kwargs: Any) -> Any:
        inner = kwargs.get("process_request")

        def process_request(connection: Any, request: Any) -> Any:
            why = refuse_reason(request.headers, allowed)
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
