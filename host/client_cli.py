"""Client commands of ``ucr`` (talk to a running daemon over its API): status, watch, move,
trajectory, controllers, teleop. This module registers them all and runs status, watch and
controllers; the commands that move the robot live in :mod:`host.client_motion`, the connection
and error helpers in :mod:`host.client_common`, the status's lines in :mod:`host.client_status`.

Each command connects to ``--url`` (default ``$UCR_URL`` or ws://127.0.0.1:8765) with the token
from ``--token-file`` (a 0600 file; default ``$UCR_TOKEN_FILE``, else ``$UCR_TOKEN``). Curvature
is in 1/m, the bending-plane angle phi in degrees on the command line and in the output (radians
on the wire).
Exit codes: 0 done, 1 failed (daemon unreachable, request refused, trajectory aborted), 2 usage
error. Errors are one line, never a traceback. ``ucr token FILE`` writes a new token file.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from host.api.client_behalf import sender_words
from host.client_common import (
    add_connection_args,
    deg,
    format_missing,
    kap,
    number_arg,
    say_error,
    topology_or_none,
    with_client,
)
from host.client_motion import cmd_move, cmd_teleop, cmd_trajectory
from host.client_status import format_status, manual_senders

SECONDS = number_arg(float, 0.0, False, " s")  # a finite number of s > 0


# --------------------------------------------------------------------------- registration
def register(subparsers: Any) -> None:
    """Add the client commands to the ``ucr`` dispatcher."""
    t = subparsers.add_parser(
        "token",
        help="write a new random API token to a file only you can read (mode 0600)",
        description="Writes a new random API token (43 characters) to FILE, mode 0600, "
        "atomically. Point api.tokens in the daemon config at it (scope read or control) and "
        "give clients the same file (--token-file or $UCR_TOKEN_FILE) or its content "
        "($UCR_TOKEN).",
    )
    t.add_argument("file", help="where to write the token (must not exist, unless --force)")
    t.add_argument("--force", action="store_true", help="replace an existing file")
    t.set_defaults(func=cmd_token)
    p = subparsers.add_parser(
        "status",
        help="show the daemon's state and the robot's joints",
        description="The daemon's state, its controllers and goals, kappa (1/m) and phi (degrees) "
        "per segment, and the description's segments that are missing now, with where the "
        "chain is cut.",
    )
    add_connection_args(p)
    p.add_argument(
        "--json",
        action="store_true",
        help="print the raw status as JSON (with the daemon's topology under 'topology')",
    )
    p.set_defaults(func=cmd_status)

    p = subparsers.add_parser(
        "clear-fault", help="clear a segment's FAULT (it then holds until resumed)"
    )
    add_connection_args(p)
    p.add_argument("segment", nargs="?", help="bendable name (default: every segment)")
    p.set_defaults(func=cmd_clear_fault)

    p = subparsers.add_parser(
        "goal",
        help="show a trajectory goal's status, or cancel it (--cancel)",
        description="Status of GOAL (the id `ucr move/trajectory --no-wait` prints), or of every "
        "running goal when none is given; --cancel stops it (the robot decelerates and holds).",
    )
    add_connection_args(p)
    p.add_argument("goal", nargs="?", help="goal id (default: every running goal)")
    p.add_argument("--cancel", action="store_true", help="cancel the goal(s)")
    p.add_argument("--json", action="store_true", help="print each status as one JSON line")
    p.set_defaults(func=cmd_goal)

    p = subparsers.add_parser(
        "watch",
        help="print live joint states, transforms, events or the topology",
        description="One line per message: t is the daemon's clock in s, kappa in 1/m, phi in "
        "degrees, positions in m. --kind topology prints the current topology first, then "
        "each change.",
    )
    add_connection_args(p)
    p.add_argument(
        "--kind",
        action="append",
        choices=["joint_states", "transforms", "events", "topology"],
        help="what to watch (repeatable; default joint_states)",
    )
    p.add_argument("--rate", type=float, default=10.0, help="max lines per second per kind (10)")
    p.add_argument(
        "--count",
        type=int,
        default=None,
        help="stop after this many messages from the daemon (the current topology that "
        "--kind topology prints first is not counted: --count 0 prints only that)",
    )
    p.add_argument("--json", action="store_true", help="print each message as one JSON line")
    p.set_defaults(func=cmd_watch)

    p = subparsers.add_parser(
        "move",
        help="bend one segment to a curvature in a given time (cJTC)",
        description="Move one segment to (kappa, phi) in DURATION seconds; other segments hold.",
    )
    add_connection_args(p)
    p.add_argument("--segment", required=True, help="bendable name (see `ucr status`)")
    p.add_argument("--kappa", type=float, required=True, help="curvature K, 1/m (>= 0)")
    p.add_argument(
        "--phi", type=float, default=0.0, help="bending-plane angle P, degrees (0; within ±360)"
    )
    p.add_argument(
        "--duration",
        type=number_arg(float, 0.0, False, " s", high=604_800.0),  # schema.MAX_TIME_S: a week
        default=2.0,
        help="time to get there T, s (2; > 0, at most a week)",
    )
    p.add_argument("--no-wait", action="store_true", help="print the goal id and return at once")
    p.set_defaults(func=cmd_move)

    p = subparsers.add_parser(
        "trajectory",
        help="send a waypoint file (YAML or JSON) to the cJTC",
        description="Send timed waypoints from FILE (format: docs/api.md); shows progress.",
    )
    add_connection_args(p)
    p.add_argument("file", help="YAML or JSON waypoint file")
    p.add_argument("--controller", default=None, help="trajectory controller (default: active)")
    p.add_argument("--check", action="store_true", help="only validate the file, do not send")
    p.add_argument("--no-wait", action="store_true", help="print the goal id and return at once")
    p.set_defaults(func=cmd_trajectory)

    p = subparsers.add_parser("controllers", help="list or switch controllers")
    add_connection_args(p)
    csub = p.add_subparsers(dest="action", metavar="ACTION")
    p.set_defaults(func=cmd_controllers, action="list")
    lp = csub.add_parser("list", help="list controllers and their state (default)")
    add_connection_args(lp, nested=True)
    lp.add_argument("--json", action="store_true")
    sp = csub.add_parser("switch", help="activate --start and deactivate --stop together")
    add_connection_args(sp, nested=True)
    sp.add_argument("--start", action="append", default=[], help="controller to activate")
    sp.add_argument("--stop", action="append", default=[], help="controller to deactivate")
    hp = csub.add_parser("hand-back", help="end a manual (cFFC) takeover, restart what it stopped")
    add_connection_args(hp, nested=True)
    hp.add_argument("--manual", default=None, help="manual controller (default: the one active)")
    for q in (lp, sp, hp):
        q.set_defaults(func=cmd_controllers)
    p.set_defaults(json=False)

    p = subparsers.add_parser(
        "teleop",
        help="drive segments by hand (gamepad, keyboard or a recording) through the cFFC",
        description="Stick deflection sets the rate of curvature change (cFFC). Default input: "
        "the first gamepad with two sticks. Stops when you let go; if input stops the "
        "daemon's deadman stops the robot.",
    )
    add_connection_args(p)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--device", default=None, help="evdev device, e.g. /dev/input/event5")
    src.add_argument("--keyboard", action="store_true", help="use the keyboard in this terminal")
    src.add_argument("--replay", default=None, metavar="FILE", help="play a recorded stream")
    p.add_argument("--record", default=None, metavar="FILE", help="also record the input here")
    p.add_argument(
        "--rate",
        type=number_arg(float, 0.0, False, " Hz"),
        default=50.0,
        help="command rate while moving, Hz (50)",
    )
    p.add_argument(
        "--speed",
        type=number_arg(float, 0.0, False),
        default=None,  # None: not given (1, as recorded); given without --replay: refused
        help="replay speed factor, > 0 (default 1: as recorded); only with --replay",
    )
    p.set_defaults(func=cmd_teleop)


# --------------------------------------------------------------------------- status
def cmd_status(args: argparse.Namespace) -> int:
    def body(c: Any) -> int:
        st = c.status()
        topo = topology_or_none(c)
        if args.json:
            print(json.dumps(st if topo is None else {**st, "topology": topo}, indent=2))
        else:
            print("\n".join(format_status(st, topo, manual_senders(c, st))))
        return 0

    return with_client(args, body)


def cmd_clear_fault(args: argparse.Namespace) -> int:
    def body(c: Any) -> int:
        res = c.clear_fault(args.segment)
        had = res.get("faults") or {}
        sent = res.get("sent_to") or []
        print(f"CLEAR_FAULT sent to {', '.join(sent) or 'no segment'}")
        for name in sent:
            if name in had:
                print(f"  {name}: was in FAULT {had[name].get('name')}: {had[name].get('text')}")
        return 0

    return with_client(args, body)


def cmd_goal(args: argparse.Namespace) -> int:
    def body(c: Any) -> int:
        goals = [args.goal] if args.goal else list(c.status().get("running_goals") or [])
        if not goals:  # --json: no line (one JSON object per goal), the words to stderr
            print("no running goal", file=sys.stderr if args.json else sys.stdout)
            return 0
        for goal in goals:
            st = c.cancel(goal) if args.cancel else c.trajectory_status(goal)
            if args.json:
                print(json.dumps(st))
                continue
            line = f"goal {goal}: {st.get('state')}"
            if st.get("progress") is not None:
                line += f", {100 * float(st['progress']):.0f} %"
            if st.get("reason"):
                line += f" ({st['reason']})"
            if sender_words(st.get("from")):
                line += f"; sent by {sender_words(st.get('from'))}"
            if args.cancel:
                done = "; canceled: decelerating to rest" if st.get("canceled") else "; not running"
                line += done
            print(line)
        return 0

    return with_client(args, body)


# --------------------------------------------------------------------------- watch
def format_message(msg: dict) -> str:
    """One human line per published message: ``t=`` the daemon's clock in s, kappa in 1/m, phi
    in degrees, positions in m."""
    kind = msg.get("kind")
    t = msg.get("t")
    head = f"t={t:.3f} s  " if isinstance(t, int | float) else ""
    if kind == "joint_states":
        parts = []
        valid = msg.get("valid") or []
        for i, name in enumerate(msg.get("names") or []):
            k = (msg.get("kappa") or [None])[i] if i < len(msg.get("kappa") or []) else None
            p = (msg.get("phi") or [None])[i] if i < len(msg.get("phi") or []) else None
            mark = "" if i >= len(valid) or valid[i] else "?"
            parts.append(f"{name} κ={kap(k)} 1/m φ={deg(p)}{mark}")
        return head + "  ".join(parts)
    if kind == "transforms":
        tip = msg.get("tip") or {}
        xyz = tip.get("xyz") or []
        pos = ", ".join(f"{v:+.4f}" for v in xyz)
        return head + f"tip {tip.get('link')} at ({pos}) m; {len(msg.get('frames') or {})} frames"
    if kind in ("event", "events"):
        text = msg.get("message") or ""
        return head + f"EVENT {msg.get('event')}" + (f": {text}" if text else "")
    if kind == "topology":
        ctl = ", ".join(msg.get("controlled") or []) or "none"
        missing = "".join(f"; {ln.strip()}" for ln in format_missing(msg))
        return head + f"TOPOLOGY {msg.get('reason', '')}: controlled {ctl}{missing}"
    return head + json.dumps(msg)


def cmd_watch(args: argparse.Namespace) -> int:
    from host.api.schema import MAX_RATE_HZ, MIN_RATE_HZ  # noqa: PLC0415

    kinds = args.kind or ["joint_states"]
    if not (MIN_RATE_HZ <= args.rate <= MAX_RATE_HZ):  # (NaN too) the daemon's own bounds
        say_error(
            f"--rate must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] lines/s per kind, "
            f"got {args.rate:g}"
        )
        return 2
    if args.count is not None and (args.count < 0 or args.count == 0 and "topology" not in kinds):
        say_error("--count must be >= 1 (0 only with --kind topology: the current one alone)")
        return 2

    def body(c: Any) -> int:
        n = 0
        rc = 0
        sub = c.subscribe(kinds, max_rate=args.rate)
        if "topology" in kinds:  # subscribed first: a change meanwhile is printed after it
            topo = topology_or_none(c)
            if topo is not None:  # (not counted by --count: a script waits for a change)
                msg = {"kind": "topology", "reason": "current", **topo}
                print(json.dumps(msg) if args.json else format_message(msg), flush=True)
        try:
            for msg in sub if args.count is None or args.count > 0 else ():
                print(json.dumps(msg) if args.json else format_message(msg), flush=True)
                n += 1
                if args.count is not None and n >= args.count:
                    break
        except KeyboardInterrupt:
            rc = 130  # interrupted, as every command (docs/api.md "Client CLI")
        finally:
            if not c.closed:
                sub.close()
        if sub.dropped_server or sub.dropped_local:
            say_error(
                f"watch: {sub.dropped_server + sub.dropped_local} messages dropped (slow output)"
            )
        return rc

    return with_client(args, body)


# --------------------------------------------------------------------------- controllers
def cmd_controllers(args: argparse.Namespace) -> int:
    action = getattr(args, "action", None) or "list"
    if action == "switch" and not (args.start or args.stop):
        say_error("controllers switch: give --start and/or --stop")
        return 2

    def body(c: Any) -> int:
        if action == "switch":
            res = c.switch(start=args.start, stop=args.stop)
            print(
                f"started: {', '.join(res.get('started') or []) or '-'}; "
                f"stopped: {', '.join(res.get('stopped') or []) or '-'}"
            )
            return 0
        if action == "hand-back":
            res = c.hand_back(args.manual)
            print(f"handed back; restarted: {', '.join(res.get('restarted') or []) or '-'}")
            return 0
        ctrls = c.controllers()
        if getattr(args, "json", False):
            print(json.dumps(ctrls, indent=2))
            return 0
        print(f"{'name':<12} {'type':<6} {'state':<10} {'joints':<30} claimed")
        for ctl in ctrls:
            claims = ctl.get("claimed_interfaces") or []
            joints = ", ".join(map(str, ctl.get("joints") or [])) or "-"
            line = (
                f"{str(ctl.get('name')):<12} {str(ctl.get('type')):<6} "
                f"{str(ctl.get('state')):<10} {joints:<30} {', '.join(map(str, claims)) or '-'}"
            )
            if ctl.get("error"):
                line += f"  error: {ctl['error']}"
            print(line)
            if sender_words(ctl.get("input_from")):  # a cFFC: who sent its latest input
                age = ctl.get("input_age_s")
                when = f"{age:.2f} s ago" if isinstance(age, int | float) else "none in force"
                print(f"{'':<12} latest input from {sender_words(ctl['input_from'])} ({when})")
            if isinstance(ctl.get("setpoint"), dict):  # an active cFFC: where it commands
                print(f"{'':<12} setpoint {_setpoint_words(ctl['setpoint'])}")
        return 0

    return with_client(args, body)


def _setpoint_words(setpoint: dict) -> str:
    """A cFFC's setpoint ``{segment: [kx, ky]}`` as κ (1/m) and φ (degrees) per segment."""
    out = []
    for name, v in setpoint.items():
        try:
            kx, ky = float(v[0]), float(v[1])
        except (TypeError, ValueError, IndexError):
            continue
        phi = math.degrees(math.atan2(ky, kx))
        out.append(f"{name} κ {math.hypot(kx, ky):.3f} 1/m φ {phi:.1f}°")
    return "; ".join(out) or "-"


def cmd_token(args: argparse.Namespace) -> int:
    """``ucr token FILE``: a fresh 256-bit token in a new 0600 file."""
    import secrets  # noqa: PLC0415

    from host.api.auth import write_private  # noqa: PLC0415

    path = Path(args.file)
    if (path.exists() or path.is_symlink()) and not args.force:
        say_error(f"{path} exists (use --force to replace it)")
        return 1
    try:
        write_private(path, secrets.token_urlsafe(32) + "\n")
    except OSError as exc:
        say_error(f"cannot write {path}: {exc.strerror or exc}")
        return 1
    print(f"wrote a new API token to {path} (mode 0600)")
    return 0
