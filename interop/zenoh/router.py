"""``ucr zenoh-router``: a Zenoh router as rmw_zenoh's ``rmw_zenohd`` runs one, for a lab network
whose machines have no ROS 2 installed (ROS 2 machines run
``ros2 run rmw_zenoh_cpp rmw_zenohd``)."""

from __future__ import annotations

import sys
from typing import Any

from host.stopsignals import StopSignals


def run(args: Any) -> int:
    import zenoh  # noqa: PLC0415

    from interop.zenoh import config  # noqa: PLC0415

    signals = StopSignals().install()
    try:
        conf = config.build(
            config.SessionOptions(
                mode="router",
                connect=args.connect,
                listen=args.listen,
                config_file=args.zenoh_config,
                multicast=args.multicast_scouting,
            )
        )
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
        signals.stop.wait(args.duration)
        return signals.exit_code()
    finally:
        session.close()
