"""API access: bearer tokens with scopes, token files, bind/TLS policy and per-peer back-off.

Scopes: ``read`` may look (status, topology, loop stats, controller list, goal status,
subscriptions); ``control`` may also move the robot and change controllers. Tokens are at least
:data:`MIN_TOKEN_LEN` printable characters, read from files only the owner can read (mode 0600)
or from the environment, never from a command line (every user sees those in /proc).
"""

from __future__ import annotations

import hmac
import os
import stat
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

from host.api.guard import is_loopback
from host.topology import write_atomic

READ = "read"
CONTROL = "control"
SCOPES = (READ, CONTROL)
MIN_TOKEN_LEN = 16

# Ops a read-only client may call; everything else needs ``control``.
READ_OPS = frozenset(
    {
        "ping",
        "status",
        "topology",
        "loop_stats",
        "controllers.list",
        "trajectory.status",
        "subscribe",
        "unsubscribe",
    }
)


class AuthConfigError(ValueError):
    """A token, token file or bind/TLS setting is unacceptable (one-line message)."""


@dataclass(frozen=True)
class Token:
    """An accepted bearer token and its scope; ``label`` names it in logs (never the value)."""

    value: str
    scope: str
    label: str


def check_token_text(token: str, where: str) -> str:
    """The token if it is long and plain enough, else AuthConfigError naming ``where``."""
    token = token.strip()
    if len(token) < MIN_TOKEN_LEN:
        raise AuthConfigError(f"{where}: a token needs at least {MIN_TOKEN_LEN} characters")
    if not token.isprintable() or any(c.isspace() for c in token):
        raise AuthConfigError(f"{where}: a token must be printable characters without spaces")
    return token


def check_private(path: Path, what: str) -> None:
    """Refuse a file others may read or write (mode must be 0600 or stricter, owned by us)."""
    try:
        st = path.stat()
    except OSError as exc:
        raise AuthConfigError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise AuthConfigError(
            f"{path}: {what} is readable by others (mode {stat.S_IMODE(st.st_mode):04o}); "
            f"run: chmod 600 {path}"
        )
    if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
        raise AuthConfigError(f"{path}: {what} belongs to another user")


def read_token_file(path: str | Path) -> str:
    """The token in a 0600 file (first line, surrounding blanks stripped)."""
    p = Path(path)
    check_private(p, "the token file")
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeError) as exc:
        raise AuthConfigError(f"{p}: cannot read the token file: {exc}") from None
    line = text.strip().splitlines()[0] if text.strip() else ""
    return check_token_text(line, str(p))


def write_private(path: str | Path, text: str) -> None:
    """Write ``text`` to a new 0600 file atomically (temp file + rename; never via a symlink)."""
    write_atomic(path, text, mode=0o600)


def check_bind(
    host: str | None, tokens: list[Token] | tuple[Token, ...], *, tls: bool, insecure: bool
) -> None:
    """Policy for a bind address: off loopback a token and TLS are required (TLS may be waived
    only by ``insecure``). Raises AuthConfigError with what to change."""
    if is_loopback(host):
        return
    shown = host or "all interfaces"
    if not tokens:
        raise AuthConfigError(
            f"refusing to listen on {shown} without a token: other machines could move the "
            f"robot. Configure api.tokens (token files, {MIN_TOKEN_LEN}+ characters) or bind "
            "127.0.0.1."
        )
    if not tls and not insecure:
        raise AuthConfigError(
            f"refusing to listen on {shown} without TLS: the token would cross the network in "
            "clear. Configure api.tls (cert, key), or set api.insecure: true on a trusted network."
        )


def find_token(tokens: tuple[Token, ...], header: str) -> Token | None:
    """The token an ``Authorization: Bearer …`` header presents, or None (constant-time compare
    against every configured token)."""
    scheme, _, given = header.partition(" ")
    if scheme.lower() != "bearer":
        return None
    given_b = given.strip().encode()
    found = None
    for t in tokens:
        if hmac.compare_digest(given_b, t.value.encode()):
            found = t
    return found


class Backoff:
    """Per-peer (IP address) back-off after authentication failures.

    After :attr:`free` failures a peer is refused for ``base_s * 2**(n - free)`` seconds (at most
    ``max_s``) before its credentials are even looked at; a success forgets the peer. Bounded
    memory: at most ``max_peers`` peers are remembered (the oldest are forgotten).
    """

    def __init__(
        self, *, free: int = 3, base_s: float = 1.0, max_s: float = 60.0, max_peers: int = 4096
    ) -> None:
        self.free = free
        self.base_s = base_s
        self.max_s = max_s
        self.max_peers = max_peers
        self._peers: OrderedDict[str, tuple[int, float]] = OrderedDict()  # failures, until

    def blocked_for(self, peer: str, now: float | None = None) -> float:
        """Seconds this peer must still wait (0 = may try)."""
        entry = self._peers.get(peer)
        if entry is None:
            return 0.0
        now = time.monotonic() if now is None else now
        return max(0.0, entry[1] - now)

    def failed(self, peer: str, now: float | None = None) -> float:
        """Record a failure; returns the back-off now in force (s)."""
        now = time.monotonic() if now is None else now
        n = self._peers.pop(peer, (0, 0.0))[0] + 1
        wait = 0.0 if n < self.free else min(self.max_s, self.base_s * 2 ** (n - self.free))
        self._peers[peer] = (n, now + wait)
        while len(self._peers) > self.max_peers:
            self._peers.popitem(last=False)
        return wait

    def succeeded(self, peer: str) -> None:
        self._peers.pop(peer, None)
