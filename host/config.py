"""Daemon configuration: a small YAML file (controllers, port, loop rate, API, watchdog) with
defaults. The per-bendable interface limits read from the U(C)RDF ``<ros2_control>`` block live in
:mod:`host.limits` (controllers import them too); they are re-exported here.

Bad input raises :class:`ConfigError`, whose one-line message names the file and the key, so the
CLI can print it and exit 1 without a traceback. That includes every configured controller's type
and parameters (checked by the controllers' own ``parse_params`` while the file is read) and,
once the daemon has its robot, ``joints`` naming a bendable it lacks
(:func:`check_controller_joints`): all before the chain port is opened.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from host.controllers import controller_class, known_types
from host.controllers.base import ControllerError
from host.errors import ConfigError, not_utf8
from host.limits import DEFAULT_KAPPA_RATE_MAX, BendableLimits, bendable_limits
from host.yamlload import safe_load

__all__ = [
    "ApiConfig",
    "BendableLimits",
    "ConfigError",
    "DEFAULT_KAPPA_RATE_MAX",
    "DaemonConfig",
    "WatchdogConfig",
    "bendable_limits",
    "check_controller_joints",
    "load_config",
    "parse_config",
]

DEFAULT_CONTROLLERS: dict[str, dict[str, Any]] = {
    "jtc": {"type": "jtc", "params": {}},
    "ffc": {"type": "ffc", "params": {}},
    "jsb": {"type": "jsb", "params": {"rate_hz": 50.0}},
    "rsp": {"type": "rsp", "params": {"rate_hz": 20.0}},
}
DEFAULT_ACTIVE = ["jtc", "jsb", "rsp"]


@dataclass
class ApiConfig:
    """Network API (docs/api.md): bind address, TCP port, tokens with scopes (token files, or an
    inline ``token`` in a 0600 config), TLS, allowed browser origins and host names."""

    bind: str = "127.0.0.1"
    port: int = 8765
    token: str | None = None
    enabled: bool = True
    tokens: list[Any] = field(default_factory=list)  # host.api.auth.Token
    tls_cert: str | None = None
    tls_key: str | None = None
    insecure: bool = False
    origins: list[str] = field(default_factory=list)
    hosts: list[str] = field(default_factory=list)

    def server_options(self) -> dict[str, Any]:
        """Keyword options for ``host.api.server.ApiServer`` / ``host.api.process.ApiProcess``."""
        return {
            "tokens": tuple(self.tokens),
            "tls_cert": self.tls_cert,
            "tls_key": self.tls_key,
            "insecure": self.insecure,
            "origins": tuple(self.origins),
            "names": tuple(self.hosts),
        }


#: watchdog key -> (lowest, highest) value accepted (s, or cycles for ``missed_cycles``). The
#: upper bounds keep a typo from disabling supervision: a segment silent for longer than these
#: is long held by its own watchdog (200 ms), and a discovery or reconnect waiting longer only
#: delays getting the chain back.
WATCHDOG_BOUNDS: dict[str, tuple[float, float | None]] = {
    "reply_timeout_s": (0.0005, None),  # capped at 0.8 x the loop period anyway
    "missed_cycles": (1, 100),
    "silence_s": (0.0005, 5.0),
    "reconnect_min_s": (0.0005, 60.0),
    "reconnect_max_s": (0.0005, 60.0),
    "discover_timeout_s": (0.0005, 10.0),
}


@dataclass
class WatchdogConfig:
    """Link supervision. ``reply_timeout_s``: how long one SYNC/HEARTBEAT waits for the states;
    ``missed_cycles`` and ``silence_s``: a segment silent for at least that many consecutive
    cycles *and* that long (s) counts as gone (the time bound keeps fast loops from reacting to
    one late reply); reconnect back-off bounds for a vanished adapter; discovery timeout."""

    reply_timeout_s: float = 0.02
    missed_cycles: int = 3
    silence_s: float = 0.08
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 2.0
    discover_timeout_s: float = 0.3


@dataclass
class DaemonConfig:
    """Everything the daemon needs besides the robot description. SI units (s, Hz)."""

    port: str | None = None
    #: bit/s; None: the U(C)RDF's ``<hardware>`` param ``baudrate``, else 921600
    #: (:func:`link_baudrate`; the daemon resolves it), as ``port`` falls back to the file's
    baudrate: int | None = None
    rate_hz: float = 100.0
    #: SCHED_FIFO priority of the control loop and link reader threads; 0: normal scheduling
    #: (host/realtime.py, docs/daemon.md "Real-time scheduling")
    realtime_priority: int = 0
    #: collect each SYNC's STATEs one cycle later (host/hwi.py, docs/daemon.md "Pipelining")
    pipeline: bool = False
    controllers: dict[str, dict[str, Any]] = field(
        default_factory=lambda: {
            k: {"type": v["type"], "params": dict(v["params"])}
            for k, v in DEFAULT_CONTROLLERS.items()
        }
    )
    active: list[str] = field(default_factory=lambda: list(DEFAULT_ACTIVE))
    api: ApiConfig = field(default_factory=ApiConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    source: str = "<defaults>"


def _num(
    source: str,
    key: str,
    value: Any,
    *,
    lo: float | None = None,
    hi: float | None = None,
    integer: bool = False,
) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(source, key, f"expected a number, got {value!r}")
    if integer and not isinstance(value, int):
        raise ConfigError(source, key, f"expected an integer, got {value!r}")
    if not math.isfinite(value):
        raise ConfigError(source, key, f"must be finite, got {value!r}")
    if lo is not None and value < lo:
        raise ConfigError(source, key, f"must be >= {lo}, got {value!r}")
    if hi is not None and value > hi:
        raise ConfigError(source, key, f"must be <= {hi}, got {value!r}")
    return value


def _check_keys(source: str, prefix: str, data: dict, allowed: set[str]) -> None:
    for k in data:
        if k not in allowed:
            raise ConfigError(
                source, f"{prefix}{k}", f"unknown key (allowed: {', '.join(sorted(allowed))})"
            )


def parse_config(data: Any, source: str = "<config>") -> DaemonConfig:
    """Validate a decoded YAML mapping and build a :class:`DaemonConfig` (defaults fill gaps)."""
    cfg = DaemonConfig(source=source)
    if data is None:
        return cfg
    if not isinstance(data, dict):
        raise ConfigError(source, "", "top level must be a mapping")
    _check_keys(
        source,
        "",
        data,
        {
            "port",
            "baudrate",
            "rate_hz",
            "realtime_priority",
            "pipeline",
            "controllers",
            "active",
            "api",
            "watchdog",
        },
    )
    if "port" in data:
        if data["port"] is not None and not isinstance(data["port"], str):
            raise ConfigError(
                source, "port", f"expected a pyserial URL or path, got {data['port']!r}"
            )
        cfg.port = data["port"]
    if "baudrate" in data:
        cfg.baudrate = int(_num(source, "baudrate", data["baudrate"], lo=1200, integer=True))
    if "rate_hz" in data:
        cfg.rate_hz = float(_num(source, "rate_hz", data["rate_hz"], lo=1.0, hi=2000.0))
    if "realtime_priority" in data:
        cfg.realtime_priority = int(
            _num(source, "realtime_priority", data["realtime_priority"], lo=0, hi=98, integer=True)
        )
    if "pipeline" in data:
        if not isinstance(data["pipeline"], bool):
            raise ConfigError(
                source, "pipeline", f"expected true or false, got {data['pipeline']!r}"
            )
        cfg.pipeline = data["pipeline"]
    if "controllers" in data:
        ctrls = data["controllers"]
        if not isinstance(ctrls, dict) or not ctrls:
            raise ConfigError(
                source, "controllers", "expected a non-empty mapping name -> {type, params}"
            )
        cfg.controllers = {}
        types = known_types()
        for name, spec in ctrls.items():
            key = f"controllers.{name}"
            if not isinstance(name, str) or not name:
                raise ConfigError(source, key, "controller names must be non-empty strings")
            if not isinstance(spec, dict):
                raise ConfigError(source, key, "expected a mapping with 'type' (and 'params')")
            _check_keys(source, key + ".", spec, {"type", "params"})
            ctype = spec.get("type")
            if ctype not in types:
                raise ConfigError(
                    source,
                    key + ".type",
                    f"unknown controller type {ctype!r} (known: {', '.join(types)})",
                )
            params = spec.get("params") or {}
            if not isinstance(params, dict):
                raise ConfigError(source, key + ".params", "expected a mapping")
            _check_controller(source, name, ctype, params)
            cfg.controllers[name] = {"type": ctype, "params": dict(params)}
        if "active" not in data:
            cfg.active = [n for n in cfg.controllers if n in DEFAULT_ACTIVE]
    if "active" in data:
        act = data["active"]
        if not isinstance(act, list) or not all(isinstance(a, str) for a in act):
            raise ConfigError(source, "active", "expected a list of controller names")
        for a in act:
            if a not in cfg.controllers:
                raise ConfigError(source, "active", f"{a!r} is not a configured controller")
        cfg.active = list(act)
    if "api" in data:
        api = data["api"]
        if not isinstance(api, dict):
            raise ConfigError(source, "api", "expected a mapping")
        _parse_api_security(source, api, cfg.api)
        _check_keys(
            source,
            "api.",
            api,
            {"bind", "port", "token", "enabled", "tokens", "tls", "insecure", "origins", "hosts"},
        )
        if "bind" in api:
            if not isinstance(api["bind"], str):
                raise ConfigError(source, "api.bind", "expected an address string")
            cfg.api.bind = api["bind"]
        if "port" in api:
            cfg.api.port = int(_num(source, "api.port", api["port"], lo=0, hi=65535, integer=True))
        if "token" in api:
            if api["token"] is not None and not isinstance(api["token"], str):
                raise ConfigError(source, "api.token", "expected a string")
            cfg.api.token = api["token"]
            if api["token"] is not None:
                _check_inline_token(source, api["token"])
        if "enabled" in api:
            if not isinstance(api["enabled"], bool):
                raise ConfigError(source, "api.enabled", "expected true or false")
            cfg.api.enabled = api["enabled"]
    if "watchdog" in data:
        wd = data["watchdog"]
        if not isinstance(wd, dict):
            raise ConfigError(source, "watchdog", "expected a mapping")
        _check_keys(source, "watchdog.", wd, set(WatchdogConfig.__dataclass_fields__))
        for k, v in wd.items():
            integer = k == "missed_cycles"
            lo, hi = WATCHDOG_BOUNDS.get(k, (0.0005, None))
            val = _num(source, f"watchdog.{k}", v, lo=lo, hi=hi, integer=integer)
            setattr(cfg.watchdog, k, int(val) if integer else float(val))
        lo_s, hi_s = cfg.watchdog.reconnect_min_s, cfg.watchdog.reconnect_max_s
        if lo_s > hi_s:
            # the back-off starts at the minimum and doubles up to the maximum: a minimum above
            # it made the first reconnect wait the minimum, however small the maximum. The key
            # named is the one the file gives (the other may be a default).
            if "reconnect_min_s" in wd:
                key, why = "reconnect_min_s", f"must be <= reconnect_max_s ({hi_s:g} s)"
            else:
                key, why = "reconnect_max_s", f"must be >= reconnect_min_s ({lo_s:g} s)"
            got = lo_s if key == "reconnect_min_s" else hi_s
            raise ConfigError(source, f"watchdog.{key}", f"{why}, got {got:g} s")
    return cfg


def _check_controller(source: str, name: str, ctype: str, params: dict[str, Any]) -> None:
    """Refuse a controller the daemon could not load, while the file is read: its type must
    import and its parameters pass the controller's own checks (``parse_params``, which the
    controller runs again when it is built). Controllers are built only once the chain is
    found, after the port is opened; a typo found then left the daemon running without that
    controller. What needs the robot (``joints`` naming its bendables) is
    :func:`check_controller_joints`."""
    try:
        cls = controller_class(ctype)
    except ControllerError as exc:
        raise ConfigError(source, f"controllers.{name}.type", str(exc)) from None
    try:
        cls.parse_params(name, params)
    except ControllerError as exc:
        raise ConfigError(source, f"controllers.{name}.params", str(exc)) from None


def check_controller_joints(cfg: DaemonConfig, robot: Any) -> None:
    """Refuse a controller whose ``joints`` name a bendable ``robot`` does not have: the
    controller would silently command fewer segments than configured (a bendable that goes
    away while the daemon runs is dropped on purpose; one never there is a typo). Called by
    the daemon when it is constructed with its robot, before the chain port is opened; not
    with ``--adopt``, whose robot takes its bendables from the chain (``robot`` None)."""
    if robot is None:
        return
    bendables = list(getattr(robot, "bendables", None) or {})
    for name, spec in cfg.controllers.items():
        joints = (spec.get("params") or {}).get("joints")
        if not isinstance(joints, list):
            continue
        unknown = [j for j in joints if j not in bendables]
        if unknown:
            raise ConfigError(
                cfg.source,
                f"controllers.{name}.params",
                f"joints: {', '.join(map(repr, unknown))} "
                f"{'is not a bendable' if len(unknown) == 1 else 'are not bendables'} of "
                f"{getattr(robot, 'name', 'the robot')} (its bendables: "
                f"{', '.join(bendables) or 'none'})",
            )


def _str_list(source: str, key: str, value: Any) -> list[str]:
    if not isinstance(value, list) or not all(isinstance(v, str) and v for v in value):
        raise ConfigError(source, key, "expected a list of strings")
    return list(value)


def _check_inline_token(source: str, token: str) -> None:
    """An inline token: long enough, and only in a config file nobody else can read."""
    from host.api.auth import AuthConfigError, check_private, check_token_text  # noqa: PLC0415

    try:
        check_token_text(token, "api.token")
        if not source.startswith("<"):
            check_private(Path(source), "a config file holding api.token")
    except AuthConfigError as exc:
        raise ConfigError(source, "api.token", str(exc)) from None


def _parse_api_security(source: str, api: dict, out: ApiConfig) -> None:
    """api.tokens (files with scopes), api.tls, api.insecure, api.origins, api.hosts."""
    from host.api.auth import SCOPES, AuthConfigError, Token, read_token_file  # noqa: PLC0415
    from host.api.guard import GuardConfigError, WebGuard  # noqa: PLC0415

    for i, entry in enumerate(api.get("tokens") or []):
        key = f"api.tokens[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(source, key, "expected {file: PATH, scope: read|control}")
        _check_keys(source, key + ".", entry, {"file", "scope"})
        scope = entry.get("scope", "control")
        if scope not in SCOPES:
            raise ConfigError(source, key + ".scope", f"expected one of {', '.join(SCOPES)}")
        path = entry.get("file")
        if not isinstance(path, str) or not path:
            raise ConfigError(source, key + ".file", "expected the path of a token file")
        try:
            value = read_token_file(path)
        except AuthConfigError as exc:
            raise ConfigError(source, key + ".file", str(exc)) from None
        out.tokens.append(Token(value, scope, Path(path).name))
    tls = api.get("tls")
    if tls is not None:
        if not isinstance(tls, dict) or set(tls) != {"cert", "key"}:
            raise ConfigError(source, "api.tls", "expected {cert: PATH, key: PATH}")
        for k in ("cert", "key"):
            if not isinstance(tls[k], str) or not Path(tls[k]).is_file():
                raise ConfigError(source, f"api.tls.{k}", f"no such file: {tls[k]!r}")
        out.tls_cert, out.tls_key = tls["cert"], tls["key"]
    if "insecure" in api:
        if not isinstance(api["insecure"], bool):
            raise ConfigError(source, "api.insecure", "expected true or false")
        out.insecure = api["insecure"]
    if "origins" in api:
        out.origins = _str_list(source, "api.origins", api["origins"])
    if "hosts" in api:
        out.hosts = _str_list(source, "api.hosts", api["hosts"])
    try:
        WebGuard.build(bind=None, origins=out.origins, names=out.hosts)
    except GuardConfigError as exc:
        raise ConfigError(source, "api", str(exc)) from None
    except AuthConfigError as exc:  # pragma: no cover - defensive
        raise ConfigError(source, "api", str(exc)) from None


def load_config(path: str | Path | None) -> DaemonConfig:
    """Read a YAML daemon config (``None`` → defaults). Raises :class:`ConfigError`."""
    if path is None:
        return parse_config(None)
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(p), "", f"cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(str(p), "", not_utf8(exc)) from None
    try:
        data = safe_load(text)  # (a key given twice is an error: host/yamlload.py)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else "YAML"
        raise ConfigError(str(p), where, f"invalid YAML: {getattr(exc, 'problem', exc)}") from None
    return parse_config(data, str(p))


DEFAULT_BAUDRATE = 921600  # bit/s, the chain's contract (docs/architecture.md)


def link_baudrate(cfg: DaemonConfig, robot: Any) -> int:
    """The chain's bit rate: the configuration's ``baudrate`` when it gives one, else the
    U(C)RDF's ``<ros2_control><hardware><param name="baudrate">`` (``ucr check`` validated it),
    else 921600."""
    if cfg.baudrate is not None:
        return cfg.baudrate
    value = robot.hardware_params().get("baudrate")
    return DEFAULT_BAUDRATE if value is None else int(value)
