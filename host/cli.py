"""``ucr daemon``: run the host daemon on a chain. (``ucr demo``, which needs the emulator from
tools/, lives in :mod:`tools.demo`: host/ never imports tools/.)

Errors a user can fix (bad U(C)RDF, bad config, port, topology mismatch) are printed as lines and
exit 1, never as a traceback. SIGTERM/SIGINT stop the motion into HOLD and exit 0.
"""

from __future__ import annotations

import argparse
import faulthandler
import logging
import sys
from typing import Any

from host.client_common import number_arg, port_arg
from host.stopsignals import StopSignals


def register(subparsers: Any) -> None:
    p = subparsers.add_parser(
        "daemon",
        help="run the host daemon on a segment chain",
        description="Discover the chain, compare it with the U(C)RDF, and run the controllers "
        "(cJTC, cFFC, cJSB, cRSP) with the network API. Stop with SIGTERM or Ctrl-C (HOLD).",
    )
    p.add_argument("--robot", required=True, help="U(C)RDF file of the robot")
    p.add_argument("--config", help="daemon YAML config (controllers, port, rate, api, watchdog)")
    p.add_argument("--port", help="chain port: a path or any pyserial URL (overrides config)")
    p.add_argument(
        "--adopt",
        action="store_true",
        help="if the chain differs from the U(C)RDF, compose the robot from the "
        "segments' descriptors and write it out (path printed)",
    )
    p.add_argument("--adopt-out", help="where --adopt writes (default <robot>.adopted.ucrdf)")
    p.add_argument(
        "--rate",
        type=number_arg(float, 1.0, True, " Hz", high=2000.0),
        metavar="HZ",
        help="control loop rate, 1..2000 Hz (overrides config rate_hz)",
    )
    p.add_argument(
        "--rt-priority",
        type=number_arg(int, 0, True, high=98),  # host.realtime.MAX_PRIORITY
        metavar="N",
        help="run the control loop and link reader threads SCHED_FIFO at priority N (1-98; "
        "0: normal scheduling; overrides config realtime_priority; needs root or RLIMIT_RTPRIO)",
    )
    p.add_argument(
        "--pipeline",
        action="store_true",
        default=None,
        help="collect each SYNC's states one cycle later, for a chain whose exchange is longer "
        "than the reply window (overrides config pipeline; docs/daemon.md 'Pipelining')",
    )
    p.add_argument("--no-api", action="store_true", help="do not start the network API")
    p.add_argument(
        "--api-port",
        type=port_arg,
        metavar="N",
        help="TCP port of the API, 0..65535 (overrides the config's api.port, default 8765; "
        "0: a free port the OS chooses, printed at start)",
    )
    p.add_argument(
        "--log-level",
        default="INFO",
        type=str.upper,
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="DEBUG, INFO, WARNING or ERROR (default INFO)",
    )
    p.set_defaults(func=cmd_daemon)


def setup_logging(level: str) -> None:
    """Log lines to stdout at ``level`` (DEBUG, INFO, WARNING)."""
    logging.basicConfig(
        stream=sys.stdout,
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


def print_error(msg: str) -> int:
    """Print ``ucr: error: msg`` to stderr; returns the exit code 1."""
    print(f"ucr: error: {msg}", file=sys.stderr)
    return 1


def api_start_error(exc: BaseException, bind: str, port: int, where: str) -> str:
    """One actionable line for an API that did not start. A port in use (another daemon or demo)
    or not ours to bind says how to choose another; ``where``: how this command sets the port
    (e.g. "--api-port N or api.port in daemon.yaml")."""
    text = str(exc)
    low = text.lower()
    if "in use" in low or "errno 98" in low or "errno 48" in low:
        return (
            f"the API port {port} on {bind} is already in use (another `ucr daemon` or "
            f"`ucr demo`?): stop that, or choose another port with {where} (0: any free port)"
        )
    if "permission denied" in low or "errno 13" in low:
        return (
            f"the API may not listen on {bind}:{port} (ports below 1024 need privileges): "
            f"choose a port from 1024 with {where}"
        )
    return f"api: {text}"


def resolve_port(arg: str | None, cfg_port: str | None, robot: Any) -> str:
    """Port precedence: --port, config ``port``, the U(C)RDF ``<hardware>`` param ``port``;
    "auto" (or nothing) picks the first USB serial adapter."""
    port = arg or cfg_port or robot.hardware_params().get("port")
    if port and port != "auto":
        return str(port)
    from serial.tools import list_ports  # noqa: PLC0415 - only when auto-detecting

    for info in sorted(list_ports.comports(), key=lambda i: i.device):
        if "USB" in info.device or "ACM" in info.device:
            return info.device
    raise ValueError(
        "no chain port: give --port (e.g. /dev/ttyUSB0) or 'port:' in the config; "
        "no USB serial adapter found for 'auto'"
    )


def _load(robot_path: str, config_path: str | None) -> tuple[Any, Any]:
    from host.config import load_config  # noqa: PLC0415 - keep `ucr --help` fast
    from ucrdf.parser import load  # noqa: PLC0415

    return load(robot_path), load_config(config_path)


def start_api(
    daemon: Any,
    bind: str,
    port: int,
    token: str | None,
    *,
    log_level: str = "info",
    options: dict[str, Any] | None = None,
) -> Any:
    """Start the API server in its own process (host.api.process); None if it is absent.
    ``options``: ``ApiConfig.server_options()`` (tokens, TLS, origins, host names)."""
    try:
        from host.api.process import start_api_process  # noqa: PLC0415 - optional part
    except ModuleNotFoundError:
        logging.getLogger("ucr").warning("host.api.server not available: running without API")
        return None
    return start_api_process(daemon, bind, port, token, log_level=log_level, **(options or {}))


def _api_error_line(exc: BaseException, cfg: Any) -> str:
    """The daemon's API start failure, naming where its port came from."""
    has_file = not str(cfg.source).startswith("<")  # "<defaults>": no --config given
    where = "--api-port N" + (f" or api.port in {cfg.source}" if has_file else "")
    line = api_start_error(exc, cfg.api.bind, cfg.api.port, where)
    if line.startswith("api: ") and has_file:
        return f"{cfg.source}: {line}"  # a token or TLS setting of that file
    return line


STOP_DUMP_S = 6.0  # s: a stop taking longer dumps every thread's stack to stderr


def cmd_daemon(args: argparse.Namespace) -> int:
    from host.config import ConfigError  # noqa: PLC0415
    from host.daemon import Daemon, DaemonError  # noqa: PLC0415
    from ucrdf.errors import UcrdfError  # noqa: PLC0415

    if args.adopt_out is not None and not args.adopt:  # it would change nothing, silently
        print(
            "ucr: error: --adopt-out needs --adopt (it says where --adopt writes)", file=sys.stderr
        )
        return 2
    setup_logging(args.log_level)
    try:
        robot, cfg = _load(args.robot, args.config)
        if args.pipeline:
            cfg.pipeline = True
        if args.api_port is not None:
            cfg.api.port = args.api_port
        port = resolve_port(args.port, cfg.port, robot)
        daemon = Daemon(
            robot,
            cfg,
            port=port,
            rate_hz=args.rate,
            realtime_priority=args.rt_priority,
            adopt=args.adopt,
            adopt_path=args.adopt_out,
        )
    except UcrdfError as exc:
        for d in exc.diagnostics:
            print(str(d), file=sys.stderr)
        return 1
    except (ConfigError, DaemonError, ValueError) as exc:
        return print_error(str(exc))
    signals = StopSignals().install()
    # The API first: its errors (bind, token) are configuration errors, reported before the
    # chain port is opened. Until the chain runs, its requests answer "daemon is not running".
    api = None
    if cfg.api.enabled and not args.no_api:
        try:
            api = start_api(
                daemon,
                cfg.api.bind,
                cfg.api.port,
                cfg.api.token,
                log_level=args.log_level,
                options=cfg.api.server_options(),
            )
        except Exception as exc:  # noqa: BLE001 - bind/token errors are user errors
            return print_error(_api_error_line(exc, cfg))
        if api is not None and cfg.api.port == 0:
            print(f"API on {api.url} (port 0: chosen by the OS)", flush=True)
    try:
        daemon.start()
    except (DaemonError, ConfigError) as exc:
        if api is not None:
            api.stop()
        return print_error(str(exc))
    while not signals.stop.wait(0.5):
        pass
    logging.getLogger("ucr").info("signal received: holding and stopping")
    # A stop that hangs is killed by systemd (TimeoutStopSec=10); before that, every thread's
    # stack goes to stderr (the journal), so the hang can be found.
    faulthandler.dump_traceback_later(STOP_DUMP_S, exit=False)
    try:
        if api is not None:
            api.stop()
        daemon.stop(hold=True)
    finally:
        faulthandler.cancel_dump_traceback_later()
    return signals.exit_code()
