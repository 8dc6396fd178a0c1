"""Opening a connection to the daemon API: the token (``--token-file``, ``$UCR_TOKEN_FILE`` or
``$UCR_TOKEN``: :func:`read_token`, the one place every client reads it), the rule that a
token never travels in clear off loopback, TLS verification, and the WebSocket handshake with
each refusal turned into a clear :mod:`host.api.client_errors` error.

The request/reply protocol on an open connection is :class:`host.api.client.Client`.
"""

from __future__ import annotations

import os
import ssl
from urllib.parse import urlsplit

from websockets.exceptions import InvalidStatus, InvalidURI, WebSocketException
from websockets.sync.client import ClientConnection
from websockets.sync.client import connect as ws_connect

from host.api import ENV_CA, ENV_TOKEN, ENV_TOKEN_FILE
from host.api.auth import AuthConfigError, check_token_text, read_token_file
from host.api.client_errors import ApiAuthError, ApiConnectionError
from host.api.guard import is_loopback

#: where a client may take its token from, as messages name it
TOKEN_SOURCES = f"--token-file FILE, ${ENV_TOKEN_FILE} or ${ENV_TOKEN}"
MAX_MESSAGE_BYTES = 16 * 1024 * 1024  # largest message the client accepts from the daemon
#: the User-Agent a client sends unless told (the daemon writes it into its audit lines)
DEFAULT_AGENT = "ucr python client"


def read_token(token_file: str | None = None) -> str | None:
    """The API token every client uses: from ``token_file`` (``--token-file``), else the file
    ``$UCR_TOKEN_FILE`` names, else ``$UCR_TOKEN`` itself; None if none is set. A file must be
    the reader's own, mode 0600 (host.api.auth.read_token_file); a bad one is an
    :class:`ApiAuthError` naming where its path came from."""
    env_file = os.environ.get(ENV_TOKEN_FILE) or None
    path = token_file or env_file
    if path:
        try:
            return read_token_file(path)
        except AuthConfigError as exc:
            where = "" if token_file else f" (from ${ENV_TOKEN_FILE})"
            raise ApiAuthError(f"{exc}{where}") from None
    text = os.environ.get(ENV_TOKEN) or None
    if text is None:
        return None
    try:  # the same rule as a token file's (a short or blank-holding one is a typo, not a token)
        return check_token_text(text, f"${ENV_TOKEN}")
    except AuthConfigError as exc:
        raise ApiAuthError(str(exc)) from None


def token_may_travel(url: str) -> None:
    """Refuse to send a token in clear to another machine (``ws://`` off loopback)."""
    parts = urlsplit(url)
    if parts.scheme == "ws" and not is_loopback(parts.hostname or ""):
        raise ApiAuthError(
            f"refusing to send the API token over plain ws:// to {parts.hostname}: anyone on "
            "the network could read it; use wss:// (api.tls on the daemon)"
        )


def check_url(url: str, cafile: str | None = None) -> None:
    """Refuse, before any connection, a URL that cannot name a daemon (code ``bad_url``): not
    ``ws://`` or ``wss://``, no host, a port that is not a number in 1..65535, broken IPv6
    brackets; and a ``cafile`` given for a ``ws://`` URL (it would be ignored)."""
    try:
        parts = urlsplit(url)
        port = parts.port  # ValueError: not a number, or out of 0..65535
    except ValueError as exc:
        raise ApiConnectionError(f"bad URL {url!r}: {exc}", code="bad_url") from None
    if parts.scheme not in ("ws", "wss"):
        raise ApiConnectionError(
            f"bad URL {url!r}: give ws://HOST:PORT or wss://HOST:PORT", code="bad_url"
        )
    if not parts.hostname:
        raise ApiConnectionError(f"bad URL {url!r}: no host", code="bad_url")
    if port == 0:
        raise ApiConnectionError(f"bad URL {url!r}: port 0 names no server", code="bad_url")
    if cafile and parts.scheme == "ws":
        raise ApiConnectionError(
            f"a CA file ({cafile}) verifies a wss:// daemon; {url} is plain ws://: use wss:// "
            "or leave the CA file out",
            code="bad_url",
        )


def open_websocket(
    url: str, token: str | None, timeout: float, cafile: str | None, agent: str | None = None
) -> ClientConnection:
    """The WebSocket to ``url`` (``token`` as a Bearer header; ``cafile`` or ``$UCR_CA`` to
    verify ``wss://``; ``agent``: the User-Agent, the program's name in the daemon's audit
    lines). Raises :class:`ApiAuthError` / :class:`ApiConnectionError` (``code``: ``bad_url``
    for a URL or CA file that cannot work, ``tls``, ``timeout`` when the daemon did not answer
    the handshake within ``timeout`` s, ``busy``, ``not_daemon`` for an HTTP server that refuses
    without the reason a daemon always gives, ``wrong_path`` for a path the daemon does not
    serve, else ``connection``)."""
    check_url(url, cafile)
    headers = {"Authorization": f"Bearer {token}"} if token else None
    if token:
        token_may_travel(url)
    ssl_ctx = None
    cafile = cafile or os.environ.get(ENV_CA) or None
    if url.startswith("wss:"):
        try:
            ssl_ctx = ssl.create_default_context(cafile=cafile)
        except (OSError, ssl.SSLError) as exc:
            why = getattr(exc, "strerror", None) or exc
            raise ApiConnectionError(
                f"cannot load the CA file {cafile!r}: {why}", code="tls"
            ) from None
    try:
        return ws_connect(
            url,
            additional_headers=headers,
            user_agent_header=agent or DEFAULT_AGENT,
            ssl=ssl_ctx,
            open_timeout=timeout,
            max_size=MAX_MESSAGE_BYTES,
            ping_interval=20,
            close_timeout=2,
        )
    except InvalidStatus as exc:
        status = exc.response.status_code
        reason = exc.response.body.decode(errors="replace").strip()[:200]  # the server's why
        if status == 401:
            what = "wrong token" if token else f"a token is required ({TOKEN_SOURCES})"
            raise ApiAuthError(f"the daemon at {url} refused the connection: {what}") from None
        if status == 429:
            raise ApiAuthError(
                f"the daemon at {url} refused the connection: too many failed attempts, "
                f"retry in {exc.response.headers.get('Retry-After', '?')} s"
            ) from None
        if status == 503:  # full: e.g. the connections kept for control tokens
            retry = exc.response.headers.get("Retry-After", "?")
            raise ApiConnectionError(
                f"the daemon at {url} refused the connection: {reason}; retry in {retry} s",
                code="busy",
            ) from None
        if status in (400, 403, 404, 421):
            if not reason:  # the daemon always says why: this is some other HTTP server
                raise ApiConnectionError(
                    f"the server at {url} answered HTTP {status} with no reason: not a ucr "
                    "daemon's API (check --url / $UCR_URL)",
                    code="not_daemon",
                ) from None
            if status == 404:  # a path the daemon does not serve: the URL is wrong, not who asks
                raise ApiConnectionError(
                    f"the daemon at {url} serves no API there: {reason} (check --url / $UCR_URL)",
                    code="wrong_path",
                ) from None
            raise ApiAuthError(f"the daemon at {url} refused the connection: {reason}") from None
        raise ApiConnectionError(f"the daemon at {url} answered HTTP {status}") from None
    except InvalidURI as exc:
        raise ApiConnectionError(f"bad URL {url!r}: {exc}", code="bad_url") from None
    except ssl.SSLError as exc:  # reached something, but no TLS agreed: not "is it running?"
        why = exc.reason or exc.strerror or str(exc)
        raise ApiConnectionError(
            f"TLS with the daemon at {url} failed ({why}): a daemon without TLS takes ws://, "
            "a certificate from another authority needs --ca FILE",
            code="tls",
        ) from None
    except TimeoutError:
        raise ApiConnectionError(
            f"no answer from {url} within {timeout:g} s (the reply timeout, --timeout): the "
            "host is unreachable, the daemon is overloaded, or that port is not a ucr daemon",
            code="timeout",
        ) from None
    except (OSError, WebSocketException) as exc:
        raise ApiConnectionError(f"cannot reach the daemon at {url}: {exc}") from None
