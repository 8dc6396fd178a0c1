"""Can a server listen on HOST:PORT? One check and one sentence for the servers ``ucr`` starts
(the view, ``ucr replay --view``, Foxglove), checked before a server starts: viser's server
thread fails to bind in the background and its constructor waits for ever."""

from __future__ import annotations

import errno
import os
import socket


class ListenError(OSError):
    """``host:port`` cannot be listened on; ``str()`` is the sentence (``errno`` kept)."""

    def __str__(self) -> str:
        return self.strerror or super().__str__()


def listen_failure(host: str, port: int, exc: OSError, option: str = "--port") -> str:
    """One sentence for a server that cannot bind ``host:port`` (asyncio's own text repeats the
    address and the errno), with a hint naming ``option`` where one helps."""
    why = os.strerror(exc.errno).lower() if exc.errno else str(exc)
    hint = {
        errno.EADDRINUSE: f" (another program uses the port: {option} P, or 0 for any free port)",
        errno.EADDRNOTAVAIL: " (not an address of this machine)",
        errno.EACCES: " (ports below 1024 need privileges)",
    }.get(exc.errno or 0, "")
    return f"cannot listen on {host}:{port}: {why}{hint}"


def check_listen(host: str, port: int, option: str = "--port") -> None:
    """ListenError unless a server can listen on ``host``:``port``: on every address ``host``
    names, as asyncio binds them (``option``: the port's option, in the advice)."""
    if not 0 <= port <= 65535:  # (getaddrinfo wraps it modulo 65536)
        raise ListenError(f"port must be 0..65535, got {port}")
    try:
        infos = socket.getaddrinfo(
            host or None, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE
        )
    except socket.gaierror as exc:
        raise ListenError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
    for family, kind, proto, _, addr in infos:
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as asyncio's server
            if family == socket.AF_INET6:
                s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
            try:
                s.bind(addr)
            except OSError as exc:
                raise ListenError(exc.errno, listen_failure(host, port, exc, option)) from None
