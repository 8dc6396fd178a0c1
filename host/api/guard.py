"""Browser guard for every HTTP/WebSocket surface of the project: Origin, Host and path checks.

A web page the user visits can open a WebSocket to any address the browser reaches, including
127.0.0.1, and DNS rebinding lets a page's own name resolve to the robot. Browsers always send
``Origin`` on a WebSocket handshake and ``Host`` on every request, so a server that checks both
cannot be reached from a page it did not allow:

- ``Origin``: absent (not a browser: the Python client, ``ucr``, curl) or one of the configured
  origins (exact ``scheme://host[:port]``). None are allowed by default; ``null`` never is.
- ``Host``: an IP literal, ``localhost``, or one of the configured names (what the server is bound
  to and known as), with the server's port if a port is given. A rebinding attacker's name is
  none of these.
- path: exactly the surface's fixed path (and no query).

One :class:`WebGuard` per surface; :meth:`WebGuard.check` returns ``None`` (allowed) or a
:class:`Refusal` (HTTP status and reason) to answer before any upgrade. The live view and the
Foxglove bridge use this module too; docs/api.md describes the rules.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import sys
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit


class GuardConfigError(ValueError):
    """An allowed origin or host name in the configuration is malformed."""


@dataclass(frozen=True)
class Refusal:
    """Why a request was refused: HTTP status (403/404/421) and a one-line reason."""

    status: int
    reason: str


def normalize_origin(origin: str) -> str:
    """``scheme://host[:port]`` lower-cased, default ports dropped; GuardConfigError if not one."""
    parts = urlsplit(origin.strip())
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise GuardConfigError(f"origin {origin!r}: expected http(s)://host[:port]")
    if parts.path not in ("", "/") or parts.query or parts.fragment or parts.username:
        raise GuardConfigError(f"origin {origin!r}: only scheme, host and port are allowed")
    host = parts.hostname.lower()
    if ":" in host:
        host = f"[{host}]"
    try:
        port = parts.port
    except ValueError:
        raise GuardConfigError(f"origin {origin!r}: bad port") from None
    default = 80 if parts.scheme == "http" else 443
    return f"{parts.scheme}://{host}" + (f":{port}" if port and port != default else "")


def _split_host(value: str) -> tuple[str, int | None] | None:
    """``Host`` header -> (lower-case name without brackets, port or None); None if malformed."""
    value = value.strip().lower()
    if not value or any(c in value for c in "/@ \t\\"):
        return None
    if value.startswith("["):
        end = value.find("]")
        if end < 0:
            return None
        name, rest = value[1:end], value[end + 1 :]
        if rest and not rest.startswith(":"):
            return None
        port_text = rest[1:] if rest else ""
    else:
        name, _, port_text = value.partition(":")
    if port_text:
        if not port_text.isdigit() or not 0 < int(port_text) < 65536:
            return None
        return name, int(port_text)
    return name, None


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def is_loopback(host: str | None) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, "localhost")."""
    if not host:
        return False  # "" / None means every interface
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: may resolve to anything


def local_names(bind: str | None) -> set[str]:
    """Names a server bound to ``bind`` is legitimately called by: the bind name itself, and for
    a non-loopback bind this machine's host name (and ``<name>.local`` for mDNS)."""
    names = {"localhost"}
    if bind and not _is_ip(bind.strip("[]")):
        names.add(bind.lower())
    if not is_loopback(bind):
        host = socket.gethostname().lower()
        if host:
            names.update({host, f"{host}.local", socket.getfqdn().lower()})
    return names


@dataclass(frozen=True)
class WebGuard:
    """Origin/Host/path policy of one HTTP or WebSocket surface (see module docstring).

    ``origins``: allowed browser origins (normalized by :func:`normalize_origin`); ``names``:
    host names accepted in ``Host`` besides IP literals; ``port``: the server's port (a ``Host``
    naming another port is refused; 0 = not known yet, any); ``path``: the one path served.
    """

    origins: frozenset[str] = frozenset()
    names: frozenset[str] = frozenset({"localhost"})
    port: int = 0
    path: str = "/"
    extra_paths: frozenset[str] = field(default_factory=frozenset)

    @classmethod
    def build(
        cls,
        *,
        bind: str | None,
        port: int = 0,
        origins: Iterable[str] = (),
        names: Iterable[str] = (),
        path: str = "/",
    ) -> WebGuard:
        """A guard for a server bound to ``bind``: configured ``origins`` and extra ``names``."""
        allowed = frozenset(normalize_origin(o) for o in origins)
        if "null" in allowed:  # pragma: no cover - normalize_origin refuses it
            raise GuardConfigError("origin 'null' cannot be allowed")
        extra = set()
        for n in names:
            parsed = _split_host(n)
            if parsed is None or parsed[1] is not None:
                raise GuardConfigError(f"host name {n!r}: expected a bare name (no port)")
            extra.add(parsed[0])
        if not path.startswith("/"):
            raise GuardConfigError(f"path {path!r} must start with '/'")
        return cls(
            origins=allowed, names=frozenset(local_names(bind) | extra), port=port, path=path
        )

    def with_port(self, port: int) -> WebGuard:
        """The same policy once the real port is known (after binding port 0)."""
        return WebGuard(self.origins, self.names, port, self.path, self.extra_paths)

    def check(self, path: str, headers: Mapping[str, str]) -> Refusal | None:
        """None if this request may proceed, else the refusal to answer with."""
        origins = _all(headers, "Origin")
        if len(origins) > 1:
            return Refusal(403, "more than one Origin header")
        if origins:
            origin = origins[0].strip()
            try:
                allowed = normalize_origin(origin) in self.origins
            except GuardConfigError:
                allowed = False  # "null", a file:// page, garbage
            if not allowed:
                return Refusal(403, f"origin {origin[:100]!r} is not allowed")
        hosts = _all(headers, "Host")
        if len(hosts) != 1:
            return Refusal(400, "exactly one Host header is required")
        parsed = _split_host(hosts[0])
        if parsed is None:
            return Refusal(400, "malformed Host header")
        name, port = parsed
        if not (_is_ip(name) or name in self.names):
            return Refusal(421, f"host {name[:100]!r} is not a name of this server")
        if port is not None and self.port and port != self.port:
            return Refusal(421, f"host port {port} is not this server's port")
        if path != self.path and path not in self.extra_paths:
            return Refusal(404, f"nothing at {path[:100]!r} (this server serves {self.path!r})")
        return None


def _all(headers: Mapping[str, str], name: str) -> list[str]:
    get_all = getattr(headers, "get_all", None)
    if get_all is not None:
        return list(get_all(name))
    value = headers.get(name)
    return [] if value is None else [value]


class TcpCounts:
    """TCP connections open per peer address and in all, for the caps a server applies the
    moment a connection is made, before any work on it (the API server, the Foxglove door).
    Loopback peers count only in the total: every local client shares 127.0.0.1."""

    def __init__(self) -> None:
        self.total = 0
        self.by_ip: dict[str, int] = {}

    def admit(self, ip: str, max_total: int, max_per_peer: int) -> bool:
        """Count a new connection from ``ip``; False (nothing counted) above either cap."""
        n = self.by_ip.get(ip, 0)
        if self.total >= max_total or (n >= max_per_peer and not is_loopback(ip)):
            return False
        self.total += 1
        self.by_ip[ip] = n + 1
        return True

    def release(self, ip: str) -> None:
        """A connection :meth:`admit` counted has gone."""
        self.total -= 1
        left = self.by_ip.get(ip, 1) - 1
        if left > 0:
            self.by_ip[ip] = left
        else:
            self.by_ip.pop(ip, None)


#: how far a pending connection got with its opening handshake (see :class:`Admission`)
#: (in the order they are evicted in; :data:`REFUSING`: its token was found wrong, it only waits
#: out the back-off's hold before its refusal)
REFUSING, SILENT, TALKING, AUTHORIZING, VERIFIED = 0, 1, 2, 3, 4


class Admission:
    """Who may hold a connection to a server that authenticates in its opening handshake.

    A connection is *pending* from its TCP accept until its handshake is accepted (the guard and
    the token passed: :meth:`promote`), then *open*. The two are capped apart:

    - pending: ``max_pending``. A new connection is never refused for it: when it is full, the
      oldest pending connection that got least far is evicted (closed) instead: first those
      whose token was found wrong and that only wait out the token back-off's hold before their
      refusal (:data:`REFUSING`), then those that sent nothing yet, then those that sent part of
      a request, then those whose request is being authorized, last those whose token was found
      valid and that wait out the hold (:data:`VERIFIED`): a flood of wrong tokens, each held,
      evicts only itself. A real client sends its request at once and finishes in
      milliseconds; an idle or trickling socket never does, so a flood of them only evicts
      itself.
    - open: ``max_open`` in all; the last ``reserve`` of them only for control
      (``promote(conn, control=True)``). Connections that have not authenticated never count
      here, so they cannot use up the slots kept for control.
    - per remote address (pending and open together): ``max_per_peer``; loopback peers count
      only in the totals, every local client sharing 127.0.0.1.
    """

    def __init__(self, max_open: int, max_pending: int, max_per_peer: int, reserve: int = 0):
        self.max_open, self.max_pending = max_open, max(1, max_pending)
        self.max_per_peer, self.reserve = max_per_peer, reserve
        self.tcp = TcpCounts()
        self._pending: tuple[OrderedDict, ...] = tuple(OrderedDict() for _ in range(VERIFIED + 1))
        self._stage: dict[object, int] = {}
        self.opened: set[object] = set()

    @property
    def pending(self) -> int:
        return len(self._stage)

    def arrive(self, conn: object, ip: str) -> tuple[bool, object | None]:
        """A TCP connection was accepted: (admitted, the pending connection to evict or None).
        Refused (nothing counted) only above the per-peer cap."""
        if not self.tcp.admit(ip, sys.maxsize, self.max_per_peer):
            return False, None
        victim = None
        if len(self._stage) >= self.max_pending:
            for stage in self._pending:
                if stage:
                    victim, _ = stage.popitem(last=False)
                    del self._stage[victim]
                    break
        self._stage[conn] = SILENT
        self._pending[SILENT][conn] = None
        return True, victim

    def advance(self, conn: object, stage: int) -> None:
        """A pending connection got further (:data:`TALKING`, :data:`AUTHORIZING`), or its token
        was checked (:data:`VERIFIED`, :data:`REFUSING`: set whatever the stage was)."""
        now = self._stage.get(conn)
        if now is not None and (stage > now or stage in (REFUSING, VERIFIED)) and stage != now:
            del self._pending[now][conn]
            self._pending[stage][conn] = None
            self._stage[conn] = stage

    def is_pending(self, conn: object) -> bool:
        return conn in self._stage

    def promote(self, conn: object, control: bool) -> bool:
        """Its handshake is accepted: count it open if there is room (for ``control``, up to
        ``max_open``; else up to ``max_open - reserve``). False: no room, or it is no longer
        pending (evicted or gone meanwhile); it stays pending until it closes."""
        limit = self.max_open if control else self.max_open - self.reserve
        stage = self._stage.get(conn)
        if stage is None or len(self.opened) >= limit:
            return False
        del self._stage[conn]
        del self._pending[stage][conn]
        self.opened.add(conn)
        return True

    def leave(self, conn: object, ip: str) -> None:
        """A connection :meth:`arrive` admitted has closed."""
        self.tcp.release(ip)
        stage = self._stage.pop(conn, None)
        if stage is not None:
            del self._pending[stage][conn]
        self.opened.discard(conn)


class _Quiet(logging.LoggerAdapter):
    """The logger of an evicted connection: its failed handshake is counted, not logged."""

    def log(self, level: int, msg: object, *args: object, **kwargs: object) -> None:
        pass


#: the ``logger`` an :class:`Admission` server gives a connection it evicts (API, Foxglove door)
QUIET_LOG = _Quiet(logging.getLogger("websockets.server"), {})


def peer_ip(addr: Any) -> str:
    """The IP of a peer address (``(host, port, …)``); "?" for unknown transports, which then
    share one bucket."""
    try:
        return str(addr[0])
    except Exception:  # noqa: BLE001
        return "?"


def admitted_connections(
    base: type, admission: Admission, refused: Callable[[str], None], evicted: Callable[[], None]
) -> type:
    """``base`` (a websockets ``ServerConnection`` class) admitted by ``admission`` before any
    work, as every listener of the project admits them (the API server, the Foxglove door): above
    the per-peer cap the TCP connection is aborted (``refused(ip)``); a connection that makes room
    evicts the oldest pending one that got least far (``evicted()`` counts it); bytes received
    move a pending connection to :data:`TALKING`. Subclasses add their own bookkeeping in
    :meth:`ucr_admitted` and :meth:`ucr_gone`; ``ucr_ip`` is None for a connection not (or no
    longer) admitted."""

    class Admitted(base):  # type: ignore[misc, valid-type]
        ucr_ip: str | None = None

        def connection_made(self, transport: Any) -> None:
            ip = peer_ip(transport.get_extra_info("peername"))
            admitted, victim = admission.arrive(self, ip)
            if victim is not None:  # the oldest pending one that got least far
                victim.ucr_evict()
            if not admitted:
                refused(ip)
                transport.abort()
                return
            self.ucr_ip = ip
            self.ucr_admitted()
            super().connection_made(transport)

        def connection_lost(self, exc: Exception | None) -> None:
            ip = self.ucr_ip
            if ip is None:
                return  # refused in connection_made: nothing was set up
            self.ucr_ip = None
            admission.leave(self, ip)
            self.ucr_gone()
            super().connection_lost(exc)

        def ucr_admitted(self) -> None:
            """Admitted, before the handshake starts (a subclass's bookkeeping)."""

        def ucr_gone(self) -> None:
            """Closed after it was admitted (a subclass's bookkeeping)."""

        def ucr_evict(self) -> None:
            """Close this pending connection now. Its handshake task ends as for any connection
            lost in its handshake (so it unregisters itself: cancelling it before its first step
            leaked it in the server's handlers), but without the error and traceback websockets
            logs for that: one per evicted socket."""
            evicted()
            self.logger = QUIET_LOG
            self.transport.abort()

        def data_received(self, data: bytes) -> None:
            admission.advance(self, TALKING)
            super().data_received(data)

    return Admitted
