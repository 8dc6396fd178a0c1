"""The Zenoh session configuration of ``ucr zenoh``: rmw_zenoh's session defaults (peer, connect to
the local router, multicast scouting off, gossip on), a user's Zenoh configuration file (TLS,
access control, anything Zenoh supports) and the command-line overrides, applied in that order.
Multicast scouting stays off with a file too, unless the file sets ``scouting/multicast/enabled``
itself (or ``--multicast-scouting`` is given): Zenoh's own default for it is on.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

MODES = ("peer", "client", "router")
DEFAULT_CONNECT = ("tcp/localhost:7447",)  # rmw_zenoh: every session connects to the host's router
DEFAULT_LISTEN = {"peer": ("tcp/localhost:0",), "router": ("tcp/[::]:7447",), "client": ()}
ENV_CONFIG = "ZENOH_SESSION_CONFIG_URI"  # the variable rmw_zenoh reads for a session (a node)
# ... and rmw_zenohd for its router: `ucr zenoh-router` stands in for rmw_zenohd, so it reads this
# one (a router given a session's file would run as what that file says, e.g. a client)
ENV_ROUTER_CONFIG = "ZENOH_ROUTER_CONFIG_URI"
ENV_OVERRIDE = "ZENOH_CONFIG_OVERRIDE"  # ``path=json5;path=json5`` (rmw_zenoh's format)


class ZenohConfigError(ValueError):
    """A configuration ucr cannot use (bad file, bad endpoint, bad override)."""


@dataclass
class SessionOptions:
    """What the command line can set; None means: the file's (or rmw_zenoh's default) value."""

    mode: str | None = None
    connect: list[str] | None = None
    listen: list[str] | None = None
    config_file: str | None = None
    multicast: bool = False
    overrides: list[tuple[str, str]] = field(default_factory=list)
    #: the environment variable naming the file when ``config_file`` is None (as rmw_zenoh: the
    #: session's for ``ucr zenoh``, :data:`ENV_ROUTER_CONFIG` for ``ucr zenoh-router``)
    config_env: str = ENV_CONFIG


def parse_overrides(text: str) -> list[tuple[str, str]]:
    """``transport/shared_memory/enabled=true;mode="client"`` -> [(path, json5 value)]."""
    out = []
    for part in text.split(";"):
        part = part.strip()
        if not part:
            continue
        path, sep, value = part.partition("=")
        if not sep or not path.strip() or not value.strip():
            raise ZenohConfigError(f"{ENV_OVERRIDE}: {part!r} is not path=value")
        out.append((path.strip(), value.strip()))
    return out


def _check_endpoint(ep: str) -> str:
    proto, sep, rest = ep.partition("/")
    if not sep or not proto or not rest:
        raise ZenohConfigError(f"bad Zenoh endpoint {ep!r}: expected e.g. tcp/127.0.0.1:7447")
    return ep


def build(opts: SessionOptions, environ: dict[str, str] | None = None) -> Any:
    """A ``zenoh.Config`` from ``opts`` (the file ``$<opts.config_env>`` names when no file is
    given)."""
    import zenoh  # noqa: PLC0415 - optional dependency

    env = os.environ if environ is None else environ
    path = opts.config_file or env.get(opts.config_env) or None
    file_given = path is not None
    if file_given:
        # a file from the environment says so: the user may not know the variable is set
        origin = "" if opts.config_file else f"${opts.config_env}: "
        p = Path(path)
        if not p.is_file():
            raise ZenohConfigError(f"{origin}Zenoh configuration file {path}: no such file")
        try:
            conf = zenoh.Config.from_file(str(p))
        except Exception as exc:  # noqa: BLE001 - zenoh reports parse errors as ZError
            raise ZenohConfigError(f"{origin}Zenoh configuration file {path}: {exc}") from None
    else:
        conf = zenoh.Config()
    mode = opts.mode or (None if file_given else "peer")
    if mode is not None and mode not in MODES:
        raise ZenohConfigError(f"Zenoh mode {mode!r}: one of {', '.join(MODES)}")
    settings: list[tuple[str, Any]] = []
    if mode is not None:
        settings.append(("mode", mode))
    connect = opts.connect
    if connect is None and not file_given:
        connect = () if mode == "router" else DEFAULT_CONNECT
    listen = opts.listen
    if listen is None and not file_given:
        listen = DEFAULT_LISTEN[mode or "peer"]
    if connect is not None:
        settings.append(("connect/endpoints", [_check_endpoint(e) for e in connect]))
    if listen is not None:
        settings.append(("listen/endpoints", [_check_endpoint(e) for e in listen]))
    # multicast scouting: on with the flag; else what the file says, if it says anything; else
    # off, as in rmw_zenoh (Zenoh's own default, which an unset value means, is on)
    if opts.multicast or _get(conf, "scouting/multicast/enabled") is None:
        settings.append(("scouting/multicast/enabled", bool(opts.multicast)))
    for key, value in settings:
        _insert(conf, key, json.dumps(value))
    overrides = list(opts.overrides)
    if env.get(ENV_OVERRIDE):
        overrides = parse_overrides(env[ENV_OVERRIDE]) + overrides
    for key, value in overrides:
        _insert(conf, key, value)
    return conf


def _insert(conf: Any, key: str, value: str) -> None:
    try:
        conf.insert_json5(key, value)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError
        raise ZenohConfigError(f"Zenoh configuration {key}={value}: {exc}") from None


def _get(conf: Any, key: str) -> Any:
    """A configuration value (None: unset, Zenoh's default applies)."""
    try:
        return json.loads(conf.get_json(key))
    except Exception:  # noqa: BLE001
        return None


def describe(conf: Any) -> str:
    """One line: mode, connect and listen endpoints (for the start-up message)."""
    return (
        f"mode {_get(conf, 'mode') or 'peer'}, connect {_get(conf, 'connect/endpoints') or []}, "
        f"listen {_get(conf, 'listen/endpoints') or []}"
    )
