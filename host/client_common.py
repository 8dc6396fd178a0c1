"""Shared pieces of the client commands (host/client_cli.py, host/client_motion.py): connecting
to the daemon's API, turning every failure into one line and an exit code, unit formatting,
the segments missing from the chain."""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import Any

from host.api import ENV_TOKEN, ENV_TOKEN_FILE, ENV_URL, default_url
from host.positions import label

_PROG = "ucr"


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code 1."""

    exit_code = 1


class CliUsageError(CliError):
    """A command line that cannot work (a malformed URL, a refused option): one line, exit 2,
    as argparse's own usage errors."""

    exit_code = 2


def say_error(message: str) -> None:
    """One error line on stderr, prefixed ``ucr:``."""
    print(f"{_PROG}: {message}", file=sys.stderr)


def add_connection_args(p: argparse.ArgumentParser, nested: bool = False) -> None:
    """--url, --token-file, --ca, --timeout of every API client command; ``nested`` parsers must
    not overwrite the parent's values. A ``--token`` is parsed only to be refused with advice."""
    kw: dict[str, Any] = {"default": argparse.SUPPRESS} if nested else {}
    p.add_argument(
        "--url",
        help=f"daemon API URL (default ${ENV_URL} or ws://127.0.0.1:8765)",
        **({"default": None} | kw),
    )
    p.add_argument(
        "--token-file",
        help=f"file (mode 0600) holding the API token (default ${ENV_TOKEN_FILE}; without "
        f"either, ${ENV_TOKEN} holds the token itself)",
        **({"default": None} | kw),
    )
    # A token on a command line is visible to every user (/proc/PID/cmdline): refused with advice.
    p.add_argument("--token", help=argparse.SUPPRESS, **({"default": None} | kw))
    p.add_argument(
        "--ca", help="CA file to verify a wss:// daemon ($UCR_CA)", **({"default": None} | kw)
    )
    p.add_argument(
        "--timeout", type=_seconds, help="reply timeout, s (default 5)", **({"default": 5.0} | kw)
    )


def bound_text(kind: type, low: float, low_ok: bool, unit: str = "") -> str:
    """What ``number_arg`` accepts, as its message says it: ``must be a finite number of s > 0``
    (infinity is > 0, so a float bound names finiteness too); an int: ``must be >= 1``."""
    bound = f"{'>=' if low_ok else '>'} {low:g}"
    if kind is int:
        return f"must be {bound}{unit}"
    return f"must be a finite number{' of' + unit if unit else ''} {bound}"


def number_arg(
    kind: type, low: float, low_ok: bool, unit: str = "", high: float | None = None
) -> Any:
    """An argparse ``type``: a finite number above ``low`` (or equal to it if ``low_ok``) and at
    most ``high``; an impossible value is a usage error (exit 2) naming the bound."""

    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        if not math.isfinite(v) or v < low or (v == low and not low_ok):
            raise argparse.ArgumentTypeError(f"{bound_text(kind, low, low_ok, unit)}, got {text}")
        if high is not None and v > high:
            raise argparse.ArgumentTypeError(f"must be <= {high:g}{unit}, got {text}")
        return v

    parse.__name__ = kind.__name__  # argparse names the type in its own messages
    return parse


# a timeout of 0 or less made every call time out at once, reported as "is ucr daemon running?";
# one beyond a day overflowed the socket's timeout (OverflowError: a traceback)
MAX_TIMEOUT_S = 86400.0
_seconds = number_arg(float, 0.0, False, " s", high=MAX_TIMEOUT_S)


def port_arg(text: str) -> int:
    """An argparse ``type``: a TCP port 0..65535 (0: the OS chooses a free one)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a port number: {text!r}") from None
    if not 0 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port 0..65535 (0: any free port), got {text}")
    return v


def unreachable_message(url: str, given: str | None) -> str:
    """Why a client found no daemon, where its URL came from and how to point it elsewhere."""
    if given:
        origin = "--url"
    elif os.environ.get(ENV_URL):
        origin = f"${ENV_URL}"
    else:
        origin = "the default"
    return (
        f"cannot reach the daemon at {url} ({origin}): is `ucr daemon` running? Another "
        f"daemon: --url URL or ${ENV_URL}; its token: --token-file FILE, ${ENV_TOKEN_FILE} "
        f"or ${ENV_TOKEN}"
    )


def connect_daemon(args: argparse.Namespace) -> Any:
    """Connect with ``--url``, the token (``--token-file``, ``$UCR_TOKEN_FILE`` or
    ``$UCR_TOKEN``: host.api.client_open.read_token), ``--ca``."""
    from host.api.client import (  # noqa: PLC0415
        ApiAuthError,
        ApiConnectionError,
        connect,
        read_token,
    )

    if args.url is not None and not args.url.strip():
        raise CliUsageError("--url is empty: give ws://HOST:PORT (or leave --url out)")
    url = args.url or default_url()
    try:
        if getattr(args, "token", None):
            raise CliUsageError(
                "--token is refused: a token on the command line is visible to every user in "
                f"/proc; use --token-file FILE (mode 0600), ${ENV_TOKEN_FILE} or ${ENV_TOKEN}"
            )
        token = read_token(getattr(args, "token_file", None))
        return connect(
            url,
            token=token,
            timeout=args.timeout,
            cafile=getattr(args, "ca", None),
            agent=f"ucr {getattr(args, 'command', None) or 'client'}",
        )
    except ApiAuthError as exc:
        raise CliError(exc.message) from None
    except ApiConnectionError as exc:
        if exc.code == "bad_url":
            raise CliUsageError(exc.message) from None
        if exc.code in ("tls", "busy", "timeout", "not_daemon", "wrong_path"):
            raise CliError(exc.message) from None
        raise CliError(unreachable_message(url, args.url)) from None


def with_client(args: argparse.Namespace, body: Any) -> int:
    """Connect, run ``body(client)``, turn every API failure into one line and exit code 1."""
    from host.api.client import ApiConnectionError, ApiError  # noqa: PLC0415

    try:
        client = connect_daemon(args)
    except CliError as exc:
        say_error(str(exc))
        return exc.exit_code
    try:
        return int(body(client) or 0)
    except CliError as exc:
        say_error(str(exc))
        return exc.exit_code
    except ApiConnectionError as exc:
        say_error(f"{exc.message}")
        return 1
    except ApiError as exc:
        say_error(f"{exc.code}: {exc.message}")
        return 1
    finally:
        client.close()


def topology_or_none(c: Any) -> dict | None:
    """The daemon's topology, or None when it cannot give one (a daemon without the op, or
    one that cannot answer now): status then shows what it has. Any other refusal (a token
    without the scope, the request budget used up, ...) is raised: hiding it would show a
    robot without its missing segments as if it were whole."""
    from host.api.client import ApiConnectionError, ApiError  # noqa: PLC0415
    from host.api.schema import UNAVAILABLE, UNKNOWN_OP  # noqa: PLC0415

    try:
        topo = c.topology()
    except ApiConnectionError:
        raise
    except ApiError as e:
        if e.code in (UNKNOWN_OP, UNAVAILABLE):
            return None
        raise
    return topo if isinstance(topo, dict) else None


def _names(value: object) -> list[str]:
    """The names in a list from the daemon (anything else, or a non-name in it, left out)."""
    return [n for n in value if isinstance(n, str)] if isinstance(value, list) else []


def format_missing(topo: dict | None) -> list[str]:
    """The description's segments not under control now, and where the chain is cut (after a
    hot-unplug, a refused segment or a broken link): ``missing: segment_3 (chain cut after
    position 2, segment_2)``; shown by ``ucr status``, ``ucr watch`` and ``ucr demo``. Positions
    count from 1, as the daemon reports them."""
    if not isinstance(topo, dict):
        return []
    expected, controlled = _names(topo.get("expected")), set(_names(topo.get("controlled")))
    missing = [n for n in expected if n not in controlled]
    if not missing:
        return []
    cut = topo.get("cut") if isinstance(topo.get("cut"), dict) else {}
    pos = cut.get("after_position")
    if isinstance(pos, bool):
        pos = None
    if isinstance(pos, int) and pos > 0:
        after = f", {cut['after']}" if cut.get("after") else ""
        where = f" (chain cut after {label(pos - 1)}{after})"  # after_position counts from 1
    elif pos == 0:
        where = " (chain cut before position 1: no segment answers)"
    else:
        where = ""
    lines = [f"missing: {', '.join(missing)}{where}"]
    if topo.get("refused"):
        lines.append(f"  {topo['refused']}")
    return lines


def deg(rad: float | None) -> str:
    """An angle in rad as degrees for people (``n/a`` if unknown)."""
    return "  n/a" if rad is None else f"{math.degrees(rad):6.1f}°"


def kap(k: float | None) -> str:
    """A curvature in 1/m, fixed width (``n/a`` if unknown)."""
    return "  n/a" if k is None else f"{k:6.3f}"


def refusal_is_transient(exc: BaseException) -> bool:
    """Whether ``ucr teleop`` rides through a refusal of its input: the daemon cannot act *now*
    (``unavailable``: the chain lost or being rebuilt). A broken connection, a timeout and every
    other refusal end the session: ``rate_limited`` too (the stream itself is too fast for the
    token's budget: a re-arm after each refusal would only make the sticks stutter)."""
    from host.api.client import ApiConnectionError, ApiError  # noqa: PLC0415
    from host.api.schema import UNAVAILABLE  # noqa: PLC0415

    return (
        isinstance(exc, ApiError)
        and not isinstance(exc, ApiConnectionError)
        and exc.code == UNAVAILABLE
    )
