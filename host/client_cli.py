"""Client commands of ``ucr`` (talk to a running daemon over its API): status, watch, move,
trajectory, controllers, teleop.

Each command connects to ``--url`` (default ``$UCR_URL`` or ws://127.0.0.1:8765) with ``--token``
(default ``$UCR_TOKEN``). Curvature is in 1/m, the bending-plane angle phi in degrees on the command
line and in the output (radians on the wire). Exit codes: 0 done, 1 failed (daemon unreachable,
request refused, trajectory aborted), 2 usage error. Errors are one line, never a traceback.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from host.api import ENV_TOKEN, ENV_URL, default_url

_PROG = "ucr"


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code 1."""


# --------------------------------------------------------------------------- registration
def _common(p: argparse.ArgumentParser, nested: bool = False) -> None:
    """--url/--token/--timeout; ``nested`` parsers must not overwrite the parent's values."""
    kw: dict[str, Any] = {"default": argparse.SUPPRESS} if nested else {}
    p.add_argument(
        "--url",
        help=f"daemon API URL (default ${ENV_URL} or ws://127.0.0.1:8765)",
        **({"default": None} | kw),
    )
    p.add_argument("--token", help=f"API token (default ${ENV_TOKEN})", **({"default": None} | kw))
    p.add_argument(
        "--timeout", type=float, help="reply timeout, s (default 5)", **({"default": 5.0} | kw)
    )


def register(subparsers: Any) -> None:
    """Add the client commands to the ``ucr`` dispatcher."""
    p = subparsers.add_parser("status", help="show the daemon's state and the robot's joints")
    _common(p)
    p.add_argument("--json", action="store_true", help="print the raw status as JSON")
    p.set_defaults(func=cmd_status)

    p = subparsers.add_parser("watch", help="print live joint states, transforms or events")
    _common(p)
    p.add_argument(
        "--kind",
        action="append",
        choices=["joint_states", "transforms", "events", "topology"],
        help="what to watch (repeatable; default joint_states)",
    )
    p.add_argument("--rate", type=float, default=10.0, help="max lines per second per kind (10)")
    p.add_argument("--count", type=int, default=None, help="stop after this many messages")
    p.add_argument("--json", action="store_true", help="print each message as one JSON line")
    p.set_defaults(func=cmd_watch)

    p = subparsers.add_parser(
        "move",
        help="bend one segment to a curvature in a given time (cJTC)",
        description="Move one segment to (kappa, phi) in DURATION seconds; other segments hold.",
    )
    _common(p)
    p.add_argument("--segment", required=True, help="bendable name (see `ucr status`)")
    p.add_argument("--kappa", type=float, required=True, help="curvature K, 1/m (>= 0)")
    p.add_argument("--phi", type=float, default=0.0, help="bending-plane angle P, degrees (0)")
    p.add_argument("--duration", type=float, default=2.0, help="time to get there T, s (2)")
    p.add_argument("--no-wait", action="store_true", help="print the goal id and return at once")
    p.set_defaults(func=cmd_move)

    p = subparsers.add_parser(
        "trajectory",
        help="send a waypoint file (YAML or JSON) to the cJTC",
        description="Send timed waypoints from FILE (format: docs/api.md); shows progress.",
    )
    _common(p)
    p.add_argument("file", help="YAML or JSON waypoint file")
    p.add_argument("--controller", default=None, help="trajectory controller (default: active)")
    p.add_argument("--check", action="store_true", help="only validate the file, do not send")
    p.add_argument("--no-wait", action="store_true", help="print the goal id and return at once")
    p.set_defaults(func=cmd_trajectory)

    p = subparsers.add_parser("controllers", help="list or switch controllers")
    _common(p)
    csub = p.add_subparsers(dest="action", metavar="ACTION")
    p.set_defaults(func=cmd_controllers, action="list")
    lp = csub.add_parser("list", help="list controllers and their state (default)")
    _common(lp, nested=True)
    lp.add_argument("--json", action="store_true")
    sp = csub.add_parser("switch", help="activate --start and deactivate --stop together")
    _common(sp, nested=True)
    sp.add_argument("--start", action="append", default=[], help="controller to activate")
    sp.add_argument("--stop", action="append", default=[], help="controller to deactivate")
    hp = csub.add_parser("hand-back", help="end a manual (cFFC) takeover, restart what it stopped")
    _common(hp, nested=True)
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
    _common(p)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--device", default=None, help="evdev device, e.g. /dev/input/event5")
    src.add_argument("--keyboard", action="store_true", help="use the keyboard in this terminal")
    src.add_argument("--replay", default=None, metavar="FILE", help="play a recorded stream")
    p.add_argument("--record", default=None, metavar="FILE", help="also record the input here")
    p.add_argument("--rate", type=float, default=50.0, help="command rate while moving, Hz (50)")
    p.add_argument("--speed", type=float, default=1.0, help="replay speed factor (1)")
    p.set_defaults(func=cmd_teleop)


# --------------------------------------------------------------------------- helpers
def _err(message: str) -> None:
    print(f"{_PROG}: {message}", file=sys.stderr)


def _connect(args: argparse.Namespace) -> Any:
    from host.api.client import ApiAuthError, ApiConnectionError, connect  # noqa: PLC0415

    url = args.url or default_url()
    try:
        return connect(url, token=args.token, timeout=args.timeout)
    except ApiAuthError as exc:
        raise CliError(exc.message) from None
    except ApiConnectionError as exc:
        if exc.code == "bad_url":
            raise CliError(exc.message) from None
        raise CliError(f"cannot reach the daemon at {url}: is `ucr daemon` running?") from None


def _run(args: argparse.Namespace, body: Any) -> int:
    """Connect, run ``body(client)``, turn every API failure into one line and exit code 1."""
    from host.api.client import ApiConnectionError, ApiError  # noqa: PLC0415

    try:
        client = _connect(args)
    except CliError as exc:
        _err(str(exc))
        return 1
    try:
        return int(body(client) or 0)
    except CliError as exc:
        _err(str(exc))
        return 1
    except ApiConnectionError as exc:
        _err(f"{exc.message}")
        return 1
    except ApiError as exc:
        _err(f"{exc.code}: {exc.message}")
        return 1
    finally:
        client.close()


def deg(rad: float | None) -> str:
    return "  n/a" if rad is None else f"{math.degrees(rad):6.1f}°"


def kap(k: float | None) -> str:
    return "  n/a" if k is None else f"{k:6.3f}"


# --------------------------------------------------------------------------- status
def format_status(st: dict) -> list[str]:
    """Human lines for a daemon status."""
    lines = [
        (
            f"daemon: {st.get('state')}  robot: {st.get('robot')}  port: {st.get('port')}  "
            f"loop: {st.get('rate_hz', 0):g} Hz  up {st.get('uptime_s', 0):.0f} s"
        ),
    ]
    if st.get("error"):
        lines.append(f"  error: {st['error']}")
    lines.append(
        f"hardware interface: {st.get('hwi')}  controllers: "
        f"{', '.join(st.get('active_controllers') or []) or 'none'}"
    )
    if st.get("manual_control"):
        lines.append(
            f"manual control: {', '.join(st['manual_control'])} (`ucr controllers "
            "hand-back` to return to trajectories)"
        )
    if st.get("running_goals"):
        lines.append(f"running goals: {', '.join(map(str, st['running_goals']))}")
    js = st.get("joint_states") or {}
    lines.append(f"segments ({len(js)}):")
    for name, j in js.items():
        flag = "" if j.get("valid", True) else "  (no answer)"
        lines.append(
            f"  {name:<16} kappa {kap(j.get('kappa'))} 1/m   phi {deg(j.get('phi'))}{flag}"
        )
    return lines


def cmd_status(args: argparse.Namespace) -> int:
    def body(c: Any) -> int:
        st = c.status()
        if args.json:
            print(json.dumps(st, indent=2))
        else:
            print("\n".join(format_status(st)))
        return 0

    return _run(args, body)


# --------------------------------------------------------------------------- watch
def format_message(msg: dict) -> str:
    """One human line per published message (kappa 1/m, phi degrees, positions m)."""
    kind = msg.get("kind")
    t = msg.get("t")
    head = f"{t:10.3f} " if isinstance(t, int | float) else ""
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
        return head + f"TOPOLOGY {msg.get('reason', '')}: controlled {ctl}"
    return head + json.dumps(msg)


def cmd_watch(args: argparse.Namespace) -> int:
    kinds = args.kind or ["joint_states"]
    if not (0 < args.rate <= 1000):
        _err("--rate must be in (0, 1000] Hz")
        return 2
    if args.count is not None and args.count < 1:
        _err("--count must be >= 1")
        return 2

    def body(c: Any) -> int:
        n = 0
        sub = c.subscribe(kinds, max_rate=args.rate)
        try:
            for msg in sub:
                print(json.dumps(msg) if args.json else format_message(msg), flush=True)
                n += 1
                if args.count is not None and n >= args.count:
                    break
        except KeyboardInterrupt:
            pass
        finally:
            if not c.closed:
                sub.close()
        if sub.dropped_server or sub.dropped_local:
            _err(f"watch: {sub.dropped_server + sub.dropped_local} messages dropped (slow output)")
        return 0

    return _run(args, body)


# --------------------------------------------------------------------------- trajectories
class _Progress:
    """Prints goal progress: a rewritten line on a terminal, a line per 10 % otherwise."""

    def __init__(self, stream: Any = None) -> None:
        self.stream = stream or sys.stdout
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.last_decile = -1

    def __call__(self, st: dict) -> None:
        p = st.get("progress")
        if not isinstance(p, int | float):
            return
        state = st.get("state", "")
        if self.tty:
            bar = "#" * int(p * 30)
            self.stream.write(f"\r  [{bar:<30}] {p * 100:5.1f} % {state:<10}")
            self.stream.flush()
        elif int(p * 10) > self.last_decile:
            self.last_decile = int(p * 10)
            print(f"  progress {p * 100:5.1f} % ({state})", file=self.stream, flush=True)

    def end(self) -> None:
        if self.tty:
            self.stream.write("\n")


def _finish(result: dict) -> int:
    state = result.get("state")
    if state in ("succeeded", "success"):
        err = result.get("final_error") or {}
        worst = max((v for v in err.values() if isinstance(v, int | float)), default=None)
        extra = f"; final error {worst:.4f} 1/m" if worst is not None else ""
        retimed = " (slowed down to respect rate limits)" if result.get("retimed") else ""
        print(f"goal {result.get('id')} succeeded{extra}{retimed}")
        return 0
    _err(f"goal {result.get('id')} {state}: {result.get('reason') or 'no reason given'}")
    return 1


def _send(c: Any, points: list[dict], controller: str | None, no_wait: bool) -> int:
    if no_wait:
        goal = c.send_trajectory(points, wait=False, controller=controller)
        print(goal)
        return 0
    progress = _Progress()
    goal = None
    try:
        goal = c.send_trajectory(points, wait=False, controller=controller, progress=progress)
        print(f"goal {goal} accepted")
        result = c.wait_trajectory(goal)
    except KeyboardInterrupt:
        progress.end()
        if goal is not None and not c.closed:
            c.cancel(goal)
            _err(f"interrupted: goal {goal} canceled (the robot decelerates and holds)")
        return 130
    progress.end()
    return _finish(result)


def cmd_move(args: argparse.Namespace) -> int:
    if not math.isfinite(args.kappa) or args.kappa < 0:
        _err("--kappa must be >= 0 1/m (bend the other way with --phi + 180)")
        return 2
    if not math.isfinite(args.duration) or args.duration <= 0:
        _err("--duration must be > 0 s")
        return 2
    if not math.isfinite(args.phi):
        _err("--phi must be a number of degrees")
        return 2
    phi = math.remainder(math.radians(args.phi), 2 * math.pi)
    points = [
        {
            "time_from_start": args.duration,
            "segments": {args.segment: {"kappa": args.kappa, "phi": phi}},
        }
    ]
    return _run(args, lambda c: _send(c, points, None, args.no_wait))


def load_trajectory_file(path: str) -> tuple[list[dict], str | None]:
    """Read a YAML/JSON waypoint file into API points (phi in rad); raises CliError with the
    file and the waypoint on any problem. Format: docs/api.md "Trajectory files"."""
    from host.api.schema import RequestError, validate_points  # noqa: PLC0415

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CliError(f"cannot read {p}: {exc.strerror or exc}") from None
    try:
        if p.suffix.lower() == ".json":
            doc = json.loads(text)
        else:
            import yaml  # noqa: PLC0415

            doc = yaml.safe_load(text)
    except Exception as exc:  # noqa: BLE001 - YAML/JSON syntax errors of any kind
        raise CliError(
            f"{p}: not valid {'JSON' if p.suffix == '.json' else 'YAML'}: "
            f"{str(exc).splitlines()[0]}"
        ) from None
    controller = None
    if isinstance(doc, dict):
        unknown = sorted(set(doc) - {"waypoints", "controller"})
        if unknown:
            raise CliError(
                f"{p}: unknown top-level key(s) {', '.join(map(str, unknown))} "
                "(expected: waypoints, controller)"
            )
        controller = doc.get("controller")
        if controller is not None and not isinstance(controller, str):
            raise CliError(f"{p}: controller must be a name")
        doc = doc.get("waypoints")
    if not isinstance(doc, list):
        raise CliError(f"{p}: expected a list of waypoints (or a mapping with 'waypoints')")
    points = []
    for i, wp in enumerate(doc):
        if not isinstance(wp, dict):
            raise CliError(f"{p}: waypoint {i}: expected a mapping with t and segments")
        wp = dict(wp)
        if "t" in wp and "time_from_start" not in wp:
            wp["time_from_start"] = wp.pop("t")
        segs = wp.get("segments")
        if isinstance(segs, dict):
            conv = {}
            for name, target in segs.items():
                if isinstance(target, dict) and "phi_deg" in target:
                    target = dict(target)
                    if "phi" in target:
                        raise CliError(
                            f"{p}: waypoint {i}: {name}: give phi (rad) or phi_deg, not both"
                        )
                    v = target.pop("phi_deg")
                    if isinstance(v, bool) or not isinstance(v, int | float):
                        raise CliError(f"{p}: waypoint {i}: {name}: phi_deg must be a number")
                    target["phi"] = math.remainder(math.radians(v), 2 * math.pi)
                conv[str(name)] = target
            wp["segments"] = conv
        points.append(wp)
    try:
        return validate_points(points, "waypoint"), controller
    except RequestError as exc:
        raise CliError(f"{p}: {exc.message}") from None


def cmd_trajectory(args: argparse.Namespace) -> int:
    try:
        points, controller = load_trajectory_file(args.file)
    except CliError as exc:
        _err(str(exc))
        return 1
    controller = args.controller or controller
    if args.check:
        names = sorted({n for pt in points for n in pt["segments"]})
        print(
            f"{args.file}: {len(points)} waypoints over {points[-1]['time_from_start']:g} s "
            f"for {', '.join(names)}: ok"
        )
        return 0

    def body(c: Any) -> int:
        topo = c.topology()
        controlled = set(topo.get("controlled") or [])
        unknown = sorted({n for pt in points for n in pt["segments"]} - controlled)
        if unknown:
            raise CliError(
                f"{args.file}: segment(s) {', '.join(unknown)} not controlled by the "
                f"daemon (controlled: {', '.join(sorted(controlled)) or 'none'})"
            )
        return _send(c, points, controller, args.no_wait)

    return _run(args, body)


# --------------------------------------------------------------------------- controllers
def cmd_controllers(args: argparse.Namespace) -> int:
    action = getattr(args, "action", None) or "list"
    if action == "switch" and not (args.start or args.stop):
        _err("controllers switch: give --start and/or --stop")
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
        return 0

    return _run(args, body)


# --------------------------------------------------------------------------- teleop
def cmd_teleop(args: argparse.Namespace) -> int:
    from host.teleop import (  # noqa: PLC0415 - lazy: keeps `ucr --help` fast
        KEY_HELP,
        GamepadSource,
        KeyboardSource,
        Recorder,
        ReplaySource,
        Teleop,
        TeleopError,
    )

    if not (0 < args.rate <= 500):
        _err("--rate must be in (0, 500] Hz")
        return 2

    def body(c: Any) -> int:
        names = list(c.topology().get("controlled") or [])
        try:
            if args.replay:
                source: Any = ReplaySource(args.replay, speed=args.speed)
                unknown = sorted(set(source.names) - set(names))
                if unknown:
                    raise CliError(
                        f"{args.replay}: segment(s) {', '.join(unknown)} not "
                        f"controlled by the daemon ({', '.join(names) or 'none'})"
                    )
                print(f"replaying {args.replay} ({len(source.events)} events)")
            elif args.keyboard:
                if not sys.stdin.isatty():
                    raise CliError("--keyboard needs a terminal")
                source = KeyboardSource(names)
                print(f"segments: {', '.join(f'{i + 1}={n}' for i, n in enumerate(names))}")
                print(KEY_HELP)
            else:
                source = GamepadSource(names, path=args.device)
                print(
                    f"gamepad {source.device_name}: left stick -> selected segment, right "
                    "stick -> next; LB/RB select, hold A = stop, START quits"
                )
        except TeleopError as exc:
            raise CliError(str(exc)) from None
        record = None
        if args.record:
            try:
                record = open(args.record, "w", encoding="utf-8")  # noqa: SIM115
            except OSError as exc:
                source.close()
                raise CliError(f"cannot write {args.record}: {exc.strerror or exc}") from None
            source = Recorder(source, record)

        def on_event(ev: Any) -> None:
            if ev.note:
                print(f"  {ev.note}", flush=True)

        try:
            result = Teleop(c.ffc_input, rate_hz=args.rate, on_event=on_event).run(source)
        except KeyboardInterrupt:
            result = None
        finally:
            source.close()
            if record is not None:
                record.close()
        if result is not None:
            print(result.summary())
        try:
            manual = c.status().get("manual_control") or []
        except Exception:  # noqa: BLE001 - only a hint
            manual = []
        if manual:
            print(
                f"{', '.join(manual)} keeps control: `ucr controllers hand-back` returns it "
                "to the trajectory controller"
            )
        return 0 if result is None or result.reason in ("quit", "end") else 1

    return _run(args, body)
