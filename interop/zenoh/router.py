"""``ucr zenoh-router``: a Zenoh router as rmw_zenoh's ``rmw_zenohd`` runs one, for a lab network
whose machines have no ROS 2 installed (ROS 2 machines run
``ros2 run rmw_zenoh_cpp rmw_zenohd``)."""

from __future__ import annotations

import sys
import threading
from typing import Any

from host.stopsignals import StopSignals
from interop.zenoh import config


def options(args: Any) -> config.SessionOptions:
    """The router's configuration as rmw_zenohd takes it: its file from ``--zenoh-config`` or
    ``$ZENOH_ROUTER_CONFIG_URI`` (never ``$ZENOH_SESSION_CONFIG_URI``, the nodes' file, which a
    shell set up for ROS 2 exports: a router run as that file's client would route nothing)."""
    return config.SessionOptions(
        mode="router",
        connect=args.connect,
        listen=args.listen,
        config_file=args.zenoh_config,
        multicast=args.multicast_scouting,
        config_env=config.ENV_ROUTER_CONFIG,
    )


def wait_time(duration: float | None) -> float | None:
    """``--duration`` as a timeout ``threading`` takes: a finite duration beyond
    ``threading.TIMEOUT_MAX`` (about 292 years; 1e300 s raised OverflowError, a traceback) waits
    that long instead."""
    return None if duration is None else min(duration, threading.TIMEOUT_MAX)


def run(args: Any) -> int:
    import zenoh  # noqa: PLC0415

    signals = StopSignals().install()
    try:
        conf = config.build(options(args))
    except config.ZenohConfigError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 2
    try:
        session = zenoh.open(conf)
    except Exception as exc:  # noqa: BLE001 - zenoh.ZError (port in use, bad TLS files)
        print(
            f"ucr: cannot start the Zenoh router ({config.describe(conf)}): {exc}", file=sys.stderr
        )
        return 1
    try:
        print(
            f"ucr: Zenoh router {session.info.zid()} ({config.describe(conf)})",
            file=sys.stderr,
            flush=True,
        )
        signals.stop.wait(wait_time(args.duration))
        return signals.exit_code()
    finally:
        session.close()
