"""Client commands that move the robot: ``ucr move`` and ``ucr trajectory`` (a goal for the cJTC,
with progress) and ``ucr teleop`` (gamepad, keyboard or a recording streamed to the cFFC).
Registered by :mod:`host.client_cli`; units and exit codes as described there."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from host.client_common import (
    CliError,
    CliUsageError,
    bound_text,
    refusal_is_transient,
    say_error,
    with_client,
)


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
    say_error(f"goal {result.get('id')} {state}: {result.get('reason') or 'no reason given'}")
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
            say_error(f"interrupted: goal {goal} canceled (the robot decelerates and holds)")
        else:  # the request may be on its way: leaving makes the daemon cancel that goal
            c.close()
            say_error(
                "interrupted before the daemon accepted the goal: it cancels the goal, since "
                "no client is left to watch it (docs/api.md)"
            )
        return 130
    progress.end()
    return _finish(result)


def cmd_move(args: argparse.Namespace) -> int:
    if not math.isfinite(args.kappa):
        say_error(f"--kappa must be a finite number of 1/m, got {args.kappa}")
        return 2
    if args.kappa < 0:
        say_error("--kappa must be >= 0 1/m (bend the other way with --phi + 180)")
        return 2
    if not math.isfinite(args.duration) or args.duration <= 0:  # argparse refuses it first
        say_error(f"--duration {bound_text(float, 0.0, False, ' s')}, got {args.duration}")
        return 2
    why = phi_deg_problem(args.phi)
    if why:
        say_error(f"--phi {why}")
        return 2
    phi = math.remainder(math.radians(args.phi), 2 * math.pi)
    points = [
        {
            "time_from_start": args.duration,
            "segments": {args.segment: {"kappa": args.kappa, "phi": phi}},
        }
    ]

    def body(c: Any) -> int:
        _check_segment(c.topology(), args.segment)
        return _send(c, points, None, args.no_wait)

    return with_client(args, body)


def _check_segment(topo: dict, segment: str) -> None:
    """Refuse a segment the robot does not have, naming its bendables, before the daemon would
    (its answer points at "trajectory point 1", a point ``ucr move`` never showed)."""
    known = [n for n in topo.get("expected") or [] if isinstance(n, str)]
    controlled = [n for n in topo.get("controlled") or [] if isinstance(n, str)]
    robot = topo.get("robot") or "the robot"
    if known and segment not in known:
        raise CliError(f"unknown segment {segment!r}: {robot}'s bendables are {', '.join(known)}")
    if segment in known and segment not in controlled:
        raise CliError(
            f"segment {segment!r} is not controlled now (controlled: "
            f"{', '.join(controlled) or 'none'}; `ucr status` shows why)"
        )


#: the largest bending-plane angle in degrees a command takes: one turn either way (the API
#: refuses beyond ±2π rad the same way); 1e308 degrees names no plane a float can tell
MAX_PHI_DEG = 360.0


def phi_deg_problem(v: object) -> str | None:
    """Why ``v`` cannot be a bending-plane angle in degrees, or None."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return "must be a number of degrees"
    if not math.isfinite(v) or abs(v) > MAX_PHI_DEG:
        return f"must be a number of degrees within ±{MAX_PHI_DEG:g}, got {v:g}"
    return None


def load_trajectory_file(path: str) -> tuple[list[dict], str | None]:
    """Read a YAML/JSON waypoint file into API points (phi in rad); raises CliError naming the
    file, the line (YAML) and the waypoint (from 1) of every problem (the first 20 in full).
    Format: docs/api.md "Trajectory files"."""
    from host.api.schema import (  # noqa: PLC0415
        MAX_POINTS,
        RequestError,
        unique_keys,
        validate_points,
    )
    from host.limits import Problems  # noqa: PLC0415

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise CliError(f"cannot read {p}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        from host.errors import not_utf8  # noqa: PLC0415

        raise CliError(f"{p}: {not_utf8(exc)}: a trajectory file is YAML or JSON text") from None
    try:
        if p.suffix.lower() == ".json":
            doc = json.loads(text, object_pairs_hook=unique_keys)
        else:
            from host.yamlload import safe_load  # noqa: PLC0415

            doc = safe_load(text)
    except Exception as exc:  # noqa: BLE001 - YAML/JSON syntax errors of any kind
        raise CliError(_syntax_error(p, exc)) from None
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
    if not doc or len(doc) > MAX_POINTS:
        raise CliError(f"{p}: {len(doc)} waypoints; 1 to {MAX_POINTS} are accepted")
    lines = _waypoint_lines(text) if p.suffix.lower() != ".json" else []

    def at(i: int) -> str:  # counted from 1, as the daemon counts a goal's points
        line = f":{lines[i]}" if i < len(lines) else ""
        return f"{p}{line}: waypoint {i + 1}"

    problems = Problems()  # every bad waypoint in one go, not one per run
    points = []
    last_t = 0.0
    for i, wp in enumerate(doc):
        if problems.full:
            break  # enough to say (Problems.text): the rest is not checked
        if not isinstance(wp, dict):
            problems.add(f"{at(i)}: expected a mapping with t and segments")
            continue
        wp = dict(wp)
        if "t" in wp and "time_from_start" not in wp:
            wp["time_from_start"] = wp.pop("t")
        segs = wp.get("segments")
        found = problems.count
        if isinstance(segs, dict):
            conv = {}
            for name, target in segs.items():
                if isinstance(target, dict) and "phi_deg" in target:
                    target = dict(target)
                    v = target.pop("phi_deg")
                    if "phi" in target:
                        problems.add(f"{at(i)}: {name}: give phi (rad) or phi_deg, not both")
                    elif why := phi_deg_problem(v):
                        problems.add(f"{at(i)}: {name}: phi_deg {why}")
                    else:
                        target["phi"] = math.remainder(math.radians(v), 2 * math.pi)
                conv[str(name)] = target
            wp["segments"] = conv
        bad = problems.count > found  # its times are still checked (against the one before)
        try:
            (point,) = validate_points([wp], "waypoint", last_t=last_t)
        except RequestError as exc:  # "waypoint[0].segments.s1.kappa: ..." -> this waypoint
            problems.add(at(i) + exc.message.removeprefix("waypoint[0]"))
            t = wp.get("time_from_start")
            if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
                last_t = t  # each waypoint against the one before it: one typo, one problem
            continue
        last_t = point["time_from_start"]
        if not bad:
            points.append(point)
    if problems:
        raise CliError(problems.kept[0] if problems.count == 1 else problems.text(str(p)))
    return points, controller


def _syntax_error(p: Path, exc: Exception) -> str:
    """``path:line:column: not valid YAML/JSON: what`` (where the parser stopped, when it says)."""
    kind = "JSON" if p.suffix.lower() == ".json" else "YAML"
    if isinstance(exc, json.JSONDecodeError):
        return f"{p}:{exc.lineno}:{exc.colno}: not valid JSON: {exc.msg}"
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    what = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    if context and getattr(exc, "problem", None):
        what = f"{what} ({context})"
    if mark is not None:
        return f"{p}:{mark.line + 1}:{mark.column + 1}: not valid {kind}: {what}"
    return f"{p}: not valid {kind}: {what}"


def _waypoint_lines(text: str) -> list[int]:
    """The line (from 1) each waypoint of a YAML trajectory file starts on; [] if unknown."""
    import yaml  # noqa: PLC0415

    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return []
    if isinstance(node, yaml.MappingNode):
        node = next((v for k, v in node.value if k.value == "waypoints"), None)
    if not isinstance(node, yaml.SequenceNode):
        return []
    return [item.start_mark.line + 1 for item in node.value]


def cmd_trajectory(args: argparse.Namespace) -> int:
    try:
        points, controller = load_trajectory_file(args.file)
    except CliError as exc:
        say_error(str(exc))
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

    return with_client(args, body)


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
        say_error("--rate must be in (0, 500] Hz")
        return 2
    if args.speed is not None and not args.replay:  # it would change nothing, silently
        say_error("--speed is the speed of a replay: give it with --replay FILE")
        return 2
    if not (args.keyboard or args.replay) and sys.platform.startswith("linux"):
        from host.extras import require  # noqa: PLC0415

        require("evdev", extra="gamepad")  # say what to install before connecting

    def body(c: Any) -> int:
        ffc, names, deadman = teleop_segments(c)
        if deadman is not None and 1.0 / args.rate > deadman / 2:
            raise CliUsageError(
                f"--rate {args.rate:g} Hz sends a command every {1000 / args.rate:.0f} ms, more "
                f"than half the cFFC {ffc!r}'s deadman ({deadman * 1000:.0f} ms): the segments "
                f"would stop between commands; use --rate {math.ceil(2 / deadman)} or more"
            )
        driven = "controlled by the daemon" + (f"'s cFFC {ffc!r}" if ffc else "")
        try:
            if args.replay:
                speed = 1.0 if args.speed is None else args.speed
                source: Any = ReplaySource(args.replay, speed=speed)
                unknown = sorted(set(source.names) - set(names))
                if unknown:
                    raise CliError(
                        f"{args.replay}: segment(s) {', '.join(unknown)} not "
                        f"{driven} ({', '.join(names) or 'none'})"
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

        interrupted = False
        try:
            teleop = Teleop(
                c.ffc_input,
                rate_hz=args.rate,
                on_event=on_event,
                transient=refusal_is_transient,  # ride through "unavailable"; re-arm after it
                on_note=lambda text: print(f"  {text}", flush=True),
            )
            result = teleop.run(source)
        except KeyboardInterrupt:
            result, interrupted = None, True
            try:  # stop now, not only when the cFFC's deadman runs out
                c.ffc_input({n: (0.0, 0.0) for n in names})
                say_error("interrupted: zero input sent, the segments stop where they are")
            except Exception:  # noqa: BLE001 - the deadman still stops them
                say_error("interrupted: the cFFC's deadman stops the segments")
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
                f"{', '.join(manual)} keeps control: `ucr controllers hand-back` ends it and "
                "restarts the controllers it took over from, if any (`ucr controllers` shows "
                "what is active then)"
            )
        if interrupted:
            return 130
        if result is not None and result.reason == "lost":  # cut off, not ended by the person
            say_error(f"teleop cut off: {result.note} (the cFFC's deadman stops the segments)")
            return 1
        return 0 if result is None or result.reason in ("quit", "end") else 1

    return with_client(args, body)


def teleop_segments(c: Any) -> tuple[str | None, list[str], float | None]:
    """The cFFC ``ffc.input`` reaches, the segments it commands, in chain order, and its deadman
    (s; None if not said): the active one, else the first configured (as host/motion.py picks
    it), from ``controllers.list``.
    Teleop sends every segment it drives (zeros for the unselected ones, and at Ctrl-C), and a
    cFFC configured with a ``joints`` subset refuses a name it does not command: the segments
    are its joints, not every controlled one. A daemon that lists no cFFC with its joints:
    (None, the controlled segments, None), and the daemon words the refusal of the input."""
    from host.controllers import ALIASES  # noqa: PLC0415 - the type a config may spell long

    listed = c.controllers()
    ffcs = [
        d
        for d in (listed if isinstance(listed, list) else [])
        if isinstance(d, dict)
        and isinstance(t := d.get("type"), str)
        and ALIASES.get(t, t) == "ffc"
    ]
    usable = [d for d in ffcs if d.get("state") != "failed" and isinstance(d.get("joints"), list)]
    if usable:
        pick = next((d for d in usable if d.get("state") == "active"), usable[0])
        joints = [j for j in pick["joints"] if isinstance(j, str)]
        if not joints:
            raise CliError(f"the cFFC {pick.get('name')!r} commands no segment now (`ucr status`)")
        deadman = pick.get("deadman_timeout_s")
        ok = isinstance(deadman, (int, float)) and not isinstance(deadman, bool) and deadman > 0
        return str(pick.get("name")), joints, float(deadman) if ok else None
    if ffcs:  # configured, but none loaded: the daemon would only say "no cFFC"
        d = ffcs[0]
        raise CliError(f"the cFFC {d.get('name')!r} failed to load: {d.get('error') or '?'}")
    return None, list(c.topology().get("controlled") or []), None
