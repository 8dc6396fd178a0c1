"""``ucr zenoh`` (the robot as a ROS 2 node over rmw_zenoh's protocol) and ``ucr zenoh-router``
(a Zenoh router with rmw_zenoh's router defaults, for a network with no ROS 2 machine running
``rmw_zenohd``). Without the optional ``ros2`` dependencies each says so in one line."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from typing import Any

from host.extras import install_command

NEEDS = ("zenoh", "mcap_ros2", "rosbags")


def missing_dependency() -> str | None:
    for mod in NEEDS:
        try:
            importlib.import_module(mod)
        except ImportError:
            return mod
    return None


def _guard(fn: Any) -> Any:
    def run(args: argparse.Namespace) -> int:
        from host.stopsignals import stop_while_starting  # noqa: PLC0415 - light

        stop_while_starting()  # SIGTERM during the imports below: exit 0, not 143
        mod = missing_dependency()
        if mod:
            print(
                f"ucr: `ucr {args.command}` needs the optional ROS 2 dependencies (module "
                f"{mod!r} is missing): {install_command('ros2')}",
                file=sys.stderr,
            )
            return 1
        return int(fn(args) or 0)

    return run


def domain_id(text: str) -> int:
    """An argparse ``type``: a ROS 2 domain id (0..232); anything else is a usage error."""
    from interop.zenoh.rmw import DOMAIN_ID_MAX  # noqa: PLC0415 - no zenoh import there

    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= DOMAIN_ID_MAX:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a ROS 2 domain id (an integer 0..{DOMAIN_ID_MAX})"
        )
    return value


def _bridge(args: argparse.Namespace) -> int:
    if args.domain_id is None:  # read here: a bad $ROS_DOMAIN_ID concerns `ucr zenoh` only
        env = os.environ.get("ROS_DOMAIN_ID", "").strip()
        try:
            args.domain_id = domain_id(env) if env else 0
        except argparse.ArgumentTypeError as exc:
            print(
                f"ucr: $ROS_DOMAIN_ID: {exc}; set it to one, unset it, or pass --domain-id",
                file=sys.stderr,
            )
            return 2
    from interop.zenoh.bridge import run  # noqa: PLC0415 - after the dependency check

    return run(args)


def _router(args: argparse.Namespace) -> int:
    from interop.zenoh.router import run  # noqa: PLC0415

    return run(args)


def _zenoh_options(p: argparse.ArgumentParser, *, router: bool) -> None:
    from interop.zenoh.config import ENV_CONFIG as SESSION_ENV  # noqa: PLC0415 - no zenoh import
    from interop.zenoh.config import ENV_ROUTER_CONFIG as ROUTER_ENV  # noqa: PLC0415

    p.add_argument(
        "--listen",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on, repeatable (peer: tcp/localhost:0; "
        "router: tcp/[::]:7447)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        metavar="ENDPOINT",
        help="Zenoh endpoint to connect to, repeatable (peer/client: "
        "tcp/localhost:7447, the host's router)",
    )
    p.add_argument(
        "--zenoh-config",
        default=None,
        metavar="FILE",
        # rmw_zenoh reads a session's file from $ZENOH_SESSION_CONFIG_URI and rmw_zenohd's from
        # $ZENOH_ROUTER_CONFIG_URI: each command reads the variable of what it is
        help="Zenoh JSON5 configuration (TLS, access control; default "
        f"${ROUTER_ENV if router else SESSION_ENV}); the flags above override it",
    )
    p.add_argument(
        "--multicast-scouting",
        action="store_true",
        help="enable UDP multicast scouting (off, as in rmw_zenoh)",
    )


def register(subparsers: Any) -> None:
    # the bounds `ucr record` and `ucr foxglove` use: a value no run could mean is a usage error
    # (exit 2) before anything opens; plain floats took -1, nan and 1e300 (tracebacks, silent
    # exits, /tf off for good) and --subdivisions had no upper bound (a ConfigError traceback)
    from host.client_common import add_connection_args  # noqa: PLC0415 - fast --help
    from interop.cli import POSITIVE_HZ, POSITIVE_S, SUBDIVISIONS  # noqa: PLC0415
    from interop.zenoh.rmw import DISTROS  # noqa: PLC0415 - fast --help (no numpy, no zenoh)

    p = subparsers.add_parser(
        "zenoh",
        help="the robot as a ROS 2 node on Zenoh (rmw_zenoh protocol; no ROS install)",
        description="Publish the live robot in rmw_zenoh's wire format: /joint_states, /tf, "
        "/tf_static, /robot_description (transient local), /ucr/arcs, /ucr/segments, "
        "/ucr/loop_stats, /rosout, … under the robot's namespace. ROS 2 users set "
        "RMW_IMPLEMENTATION=rmw_zenoh_cpp (docs/ros2.md). Commands from ROS 2 only with "
        "--enable-commands.",
    )
    p.add_argument(
        "--namespace", default=None, help="ROS namespace (default: /<robot name> from the U(C)RDF)"
    )
    p.add_argument(
        "--domain-id",
        type=domain_id,
        default=None,  # $ROS_DOMAIN_ID, read when `ucr zenoh` runs (_bridge)
        help="ROS domain id, 0..232 (default $ROS_DOMAIN_ID or 0)",
    )
    p.add_argument(
        "--distro",
        choices=DISTROS,
        default="jazzy",
        help="ROS 2 distribution of the peers (jazzy; all listed share the message "
        "definitions ucr ships)",
    )
    p.add_argument("--node-name", default="ucr_bridge", help="ROS node name (ucr_bridge)")
    p.add_argument(
        "--mode",
        choices=("peer", "client"),
        default=None,
        help="Zenoh mode (peer, as rmw_zenoh sessions; client: through a router only)",
    )
    _zenoh_options(p, router=False)
    p.add_argument(
        "--enable-commands",
        action="store_true",
        help="accept trajectory_msgs/JointTrajectory on <namespace>/<controller>/"
        "joint_trajectory, serve the FollowJointTrajectory action <controller>/"
        "follow_joint_trajectory and the ucr/stop service (off: the robot ignores ROS 2)",
    )
    p.add_argument(
        "--controller",
        default="jtc",
        help="daemon trajectory controller, also the prefix of the command topic and action "
        "inside the namespace: letters, digits, '_' (jtc)",
    )
    p.add_argument("--duration", type=POSITIVE_S, default=None, help="stop after this many s")
    p.add_argument(
        "--subdivisions",
        type=SUBDIVISIONS,
        default=10,
        help="pseudo-rigid links per bendable in /robot_description and /tf, 1..1000 (10)",
    )
    p.add_argument(
        "--viz-rate", type=POSITIVE_HZ, default=20.0, help="max rate of /tf and /ucr/arcs, Hz (20)"
    )
    add_connection_args(p)  # --url, --token-file, --ca, --timeout: as every API client
    p.add_argument(
        "--robot", default=None, help="U(C)RDF file (default: the file the daemon reports)"
    )
    p.set_defaults(func=_guard(_bridge))

    p = subparsers.add_parser(
        "zenoh-router",
        help="a Zenoh router with rmw_zenoh's defaults (when no rmw_zenohd runs)",
        description="Run a Zenoh router as `ros2 run rmw_zenoh_cpp rmw_zenohd` does (listen "
        "tcp/[::]:7447, gossip scouting, multicast off) for a network without ROS 2 installed.",
    )
    _zenoh_options(p, router=True)
    p.add_argument("--duration", type=POSITIVE_S, default=None, help="stop after this many s")
    p.set_defaults(func=_guard(_router))
