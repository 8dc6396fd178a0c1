"""Browser guard for every HTTP/WebSocket surface of the project: Origin, Host and path checks.

A web page the user visits can open a WebSocket to any address the browser reaches, including
127.0.0.1, and DNS rebinding lets a page's own name resolve to the robot. Browsers always send
``Origin`` on a WebSocket handshake and ``Host`` on every request, so a server that checks both
cannot be reached from a page it did not allow:

- ``Origin``: absent (not a browser: the Python client, ``ucr``, curl) or one of the configured
  origins (exact ``scheme://host[:port]``). None are allowed by default. Two origins are no web
  site's and may be configured as they are: ``file://`` (a page loaded from a local file in a
  desktop app built on Electron, e.g. Lichtblick or Foxglove desktop: no web page can send it)
  and ``null`` (Chromium's opaque origin for such a page, but also what a sandboxed iframe of
  any web site sends: allowed only on a server that requires a token, else refused when the
  guard is configured, :data:`NULL_NEEDS_TOKEN`).
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
import socket
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from urllib.parse import urlsplit


class GuardConfigError(ValueError):
    """An allowed origin or host name in the configuration is malformed."""


@dataclass(frozen=True)
class Refusal:
    """Why a request was refused: HTTP status (403/404/421) and a one-line reason."""

    status: int
    reason: str


#: The origin of a page loaded from a local file, as Electron sends it (no web page can send it).
FILE_ORIGIN = "file://"
#: The opaque origin: a local file's page in Chromium, and a sandboxed iframe of any web site.
NULL_ORIGIN = "null"
#: Why ``null`` is refused on a server without a token (one rule for every surface).
NULL_NEEDS_TOKEN = (
    "origin 'null' is allowed only with a token: a sandboxed iframe of any web site sends it "
    "too. Require a token (clients then present it), or allow 'file://' if the desktop app "
    "sends that"
)


def normalize_origin(origin: str) -> str:
    """``scheme://host[:port]`` lower-cased, default ports dropped; ``file://`` (also written
    ``file:///``) and ``null`` as they are; GuardConfigError for anything else."""
    text = origin.strip()
    if text.lower() == NULL_ORIGIN:
        return NULL_ORIGIN
    if text.lower() in (FILE_ORIGIN, FILE_ORIGIN + "/"):
        return FILE_ORIGIN
    parts = urlsplit(text)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise GuardConfigError(
            f"origin {origin!r}: expected http(s)://host[:port], file:// or null"
        )
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
        token_required: bool = False,
    ) -> WebGuard:
        """A guard for a server bound to ``bind``: configured ``origins`` and extra ``names``.
        ``token_required``: every client of the server must present a token; without it the
        origin ``null`` is refused (:data:`NULL_NEEDS_TOKEN`)."""
        allowed = frozenset(normalize_origin(o) for o in origins)
        if NULL_ORIGIN in allowed and not token_required:
            raise GuardConfigError(NULL_NEEDS_TOKEN)
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
                allowed = False  # garbage, another scheme
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
