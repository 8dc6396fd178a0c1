"""API access: bearer tokens with scopes, token files, bind/TLS policy and the back-off that
slows token guessing.

Scopes: ``read`` may look (status, topology, the robot description, loop stats, controller
list, goal status, subscriptions, its own session's scope); ``control`` may also move the robot
and change controllers. Tokens are at least :data:`MIN_TOKEN_LEN` printable characters, read from
files only the owner can read (mode 0600) or from the environment, never from a command line
(every user sees those in /proc).
"""

from __future__ import annotations

import hmac
import os
import ssl
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
        "session",
        "status",
        "topology",
        "robot.description",
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


def _user_name(uid: int) -> str:
    try:
        import pwd  # noqa: PLC0415 - POSIX only

        return pwd.getpwuid(uid).pw_name
    except (ImportError, KeyError, OSError):
        return str(uid)


def check_private(path: Path, what: str) -> None:
    """Refuse a file others may read or write (mode must be 0600 or stricter, owned by us).

    The message says what to run: ``chmod 600``, and ``chown`` to the user reading it when the
    file belongs to someone else (a file made with ``sudo`` belongs to root, but the daemon
    runs as ``ucr``)."""
    try:
        st = path.stat()
    except OSError as exc:
        raise AuthConfigError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None
    me = os.geteuid() if hasattr(os, "geteuid") else st.st_uid
    chown = ""
    if st.st_uid != me:
        chown = f"sudo chown {_user_name(me)} {path} && "
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise AuthConfigError(
            f"{path}: {what} is readable by others (mode {stat.S_IMODE(st.st_mode):04o}); "
            f"run: {chown}{'sudo ' if chown else ''}chmod 600 {path}"
        )
    if chown:
        raise AuthConfigError(
            f"{path}: {what} belongs to {_user_name(st.st_uid)}, not to {_user_name(me)} who "
            f"reads it (a secret must be the reader's own file, mode 0600); run: "
            f"{chown}sudo chmod 600 {path}"
        )


def server_tls_context(cert: str | Path, key: str | Path) -> ssl.SSLContext:
    """The TLS server context of every listener of the project (the API, the Foxglove server):
    TLS 1.2 or later, the PEM certificate chain ``cert`` and its private ``key``, which must be
    private to the reader (:func:`check_private`). :class:`AuthConfigError` otherwise."""
    cert, key = Path(cert), Path(key)
    check_private(key, "the TLS key")
    ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    ctx.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        ctx.load_cert_chain(cert, key)
    except (OSError, ssl.SSLError) as exc:
        raise AuthConfigError(f"TLS: cannot load {cert} / {key}: {exc}") from None
    return ctx


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
    """Back-off after authentication failures, per source (IP address) and for all together.

    It slows guessing without ever locking out a valid token: the server looks at the token
    first, and a valid one is let in whatever the back-off (every local process shares
    127.0.0.1, so keying a refusal on the address alone let any of them lock out the rest).
    Only a *wrong* token meets the back-off: after :attr:`free` failures from one source, or
    :attr:`global_free` from all sources together (many addresses), the next failures are
    refused for ``base_s * 2**(n - free)`` seconds (at most ``max_s``), answered late (the
    server holds the refusal) and without being counted again. Failures are forgotten
    ``forget_s`` after the last one; a success forgets nothing (the guesser may share the
    address). Bounded memory: at most ``max_peers`` sources are remembered (the oldest go).
    """

    GLOBAL = "*"  # the key of all sources together

    def __init__(
        self,
        *,
        free: int = 3,
        global_free: int = 30,
        base_s: float = 1.0,
        max_s: float = 60.0,
        forget_s: float = 600.0,
        max_peers: int = 4096,
    ) -> None:
        self.free = free
        self.global_free = global_free
        self.base_s = base_s
        self.max_s = max_s
        self.forget_s = forget_s
        self.max_peers = max_peers
        self._peers: OrderedDict[str, tuple[int, float, float]] = OrderedDict()  # n, last, until

    def _entry(self, key: str, now: float) -> tuple[int, float, float]:
        entry = self._peers.get(key)
        if entry is None or now - entry[1] > self.forget_s:
            return (0, now, 0.0)
        return entry

    def blocked_for(self, peer: str, now: float | None = None) -> float:
        """Seconds a wrong token from ``peer`` is still refused without counting (0 = counts)."""
        now = time.monotonic() if now is None else now
        return max(0.0, self._entry(peer, now)[2] - now, self._entry(self.GLOBAL, now)[2] - now)

    def failed(self, peer: str, now: float | None = None) -> float:
        """Count a failure of ``peer`` (and of all sources); the back-off now in force (s)."""
        now = time.monotonic() if now is None else now
        wait = 0.0
        for key, free in ((peer, self.free), (self.GLOBAL, self.global_free)):
            n = self._entry(key, now)[0] + 1
            this = 0.0 if n < free else min(self.max_s, self.base_s * 2 ** (n - free))
            self._peers.pop(key, None)
            self._peers[key] = (n, now, now + this)
            wait = max(wait, this)
        while len(self._peers) > self.max_peers:
            oldest = next(iter(self._peers))
            if oldest == self.GLOBAL:
                self._peers.move_to_end(oldest)
                oldest = next(iter(self._peers))
            del self._peers[oldest]
        return wait
