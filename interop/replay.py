"""``ucr replay``: plays a recording (MCAP, ROS 2 CDR) back into sinks at 1x or another rate, and
with ``--execute`` runs the recorded commanded trajectory on the robot again (a dry run unless
``--go``).

Output seam: :func:`play` writes every message, still encoded, to any :class:`~interop.sinks.Sink`
(the Foxglove server, the 3D view's :class:`view.replay.ReplaySource`). ``--execute`` re-sends
the goals recorded on /ucr/trajectory/commanded (the daemon's ``goal_accepted`` waypoints) at
their recorded offsets; without them (or with ``--measured``) the recorded /joint_states,
resampled as timed waypoints in the curvature vector (κx, κy), as one cJTC goal. Every waypoint
is checked against the robot file first.
"""

from __future__ import annotations

import bisect
import json
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2._dynamic import generate_dynamic

from host.api.client import ApiError
from host.client_common import CliError, connect_daemon
from host.errors import ConfigError
from host.limits import KAPPA_EPS, BendableLimits, Problems, bendable_limits, kappa_exceeds
from host.stopsignals import INTERRUPTED, StopSignals
from interop import ros2
from interop.live import FeedError, robot_for, robot_mismatch
from interop.sinks import Fanout
from interop.topics import CommandedGoals
from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string

MAGIC = b"\x89MCAP0\r\n"  # MCAP files start (and, when complete, end) with it


class RecordingError(ValueError):
    """The file cannot be replayed (not MCAP, no joint states, limits exceeded)."""


@dataclass
class RecordedMessage:
    topic: str
    typename: str
    schema: str
    data: bytes
    t_ns: int


@dataclass
class ReadReport:
    """What :func:`read_recording` found besides the messages: where a cut-short or damaged
    file ended, and the messages it skipped (channels not in CDR, or without a schema)."""

    messages: int = 0
    t_first: int | None = None
    t_last: int | None = None
    damage: str | None = None  # why the file ends early, None if read to its end
    skipped: dict[tuple[str, str], int] = field(default_factory=dict)  # (topic, why) -> count

    def _seen(self, t_ns: int) -> None:
        self.messages += 1
        self.t_first = t_ns if self.t_first is None else min(self.t_first, t_ns)
        self.t_last = t_ns if self.t_last is None else max(self.t_last, t_ns)

    def warnings(self, path: str | Path) -> list[str]:
        """One line per thing a user should know: the file ends early, messages skipped."""
        out = []
        if self.damage is not None:
            span = (self.t_last - self.t_first) / 1e9 if self.t_first is not None else 0.0
            out.append(
                f"{path} ends early (cut short or damaged: {self.damage}): read up to "
                f"{span:.2f} s after its first message ({self.messages} messages); the rest "
                "is lost"
            )
        by_why: dict[str, list[tuple[str, int]]] = {}
        for (topic, why), n in sorted(self.skipped.items()):
            by_why.setdefault(why, []).append((topic, n))
        for why, counts in by_why.items():
            total = sum(n for _, n in counts)
            where = (f"on {counts[0][0]}" if len(counts) == 1
                     else "(" + ", ".join(f"{n} on {t}" for t, n in counts) + ")")  # fmt: skip
            out.append(f"{path}: skipped {total} messages {where}: {why}")
        return out


def read_recording(path: str | Path, report: ReadReport | None = None) -> Iterator[RecordedMessage]:
    """Every message of an MCAP file in log-time order. A file without a summary (recorder
    killed, file cut short) is read as a stream up to its damage, which ``report.damage`` then
    names; a file with a summary that cannot be read, or of which nothing can be read, is a
    RecordingError. Only CDR messages (what ``ucr record`` writes) are delivered; the others are
    counted in ``report.skipped``."""
    p = Path(path)
    report = report if report is not None else ReadReport()
    try:
        f = open(p, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise RecordingError(f"{p}: {exc.strerror}") from None
    with f:
        try:
            head = f.read(len(MAGIC))
        except OSError as exc:  # e.g. a directory
            raise RecordingError(f"{p}: {exc.strerror}") from None
        if head != MAGIC:
            raise RecordingError(f"{p}: not an MCAP file")
        f.seek(0)
        try:
            reader = make_reader(f)
            summary_ok = reader.get_summary() is not None
        except Exception:  # noqa: BLE001 - any damage (McapError, OSError, ...): read as a stream
            summary_ok = False
        if summary_ok:
            it = reader.iter_messages(log_time_order=True)
        else:  # no summary: a killed recording, read as a stream until it ends
            f.seek(0)
            it = NonSeekingReader(f).iter_messages(log_time_order=False)  # written in order
        try:
            for schema, channel, message in it:
                why = _unplayable(schema, channel)
                if why is not None:
                    key = (channel.topic, why)
                    report.skipped[key] = report.skipped.get(key, 0) + 1
                    continue
                report._seen(message.log_time)
                yield RecordedMessage(channel.topic, schema.name, schema.data.decode(),
                                      message.data, message.log_time)  # fmt: skip
        except Exception as exc:  # noqa: BLE001 - McapError, ZstdError, OSError, struct.error, ...
            why = _describe(exc)
            if summary_ok or report.messages == 0 and not report.skipped:
                raise RecordingError(f"{p}: not a readable MCAP file: {why}") from None
            report.damage = why  # a killed recording: everything before the damage was delivered


def recorded_channels(path: str | Path) -> list[tuple[str, str, str]]:
    """(topic, typename, schema text) of every channel :func:`read_recording` would deliver
    messages of, in the file's channel order: from the summary, or for a file without one (a
    killed recorder) by reading its records up to the end or the first damage. Empty for a file
    that cannot be read (:func:`read_recording` says why)."""
    try:
        with open(path, "rb") as f:
            if f.read(len(MAGIC)) != MAGIC:
                return []
            f.seek(0)
            try:
                summary = make_reader(f).get_summary()
            except Exception:  # noqa: BLE001 - damaged: read as a stream below
                summary = None
            if summary is not None:
                chans = [(c, summary.schemas.get(c.schema_id)) for c in summary.channels.values()]
            else:
                f.seek(0)
                chans = _streamed_channels(f)
    except OSError:
        return []
    out: list[tuple[str, str, str]] = []
    for channel, schema in sorted(chans, key=lambda cs: cs[0].id):
        if _unplayable(schema, channel) is None and all(channel.topic != o[0] for o in out):
            out.append((channel.topic, schema.name, schema.data.decode(errors="replace")))
    return out


def _streamed_channels(f: Any) -> list[tuple[Channel, Schema | None]]:
    schemas: dict[int, Schema] = {}
    chans: list[tuple[Channel, Schema | None]] = []
    try:
        for rec in StreamReader(f).records:
            if isinstance(rec, Schema):
                schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                chans.append((rec, schemas.get(rec.schema_id)))
    except Exception:  # noqa: BLE001, S110 - the damage ends the file: what came before counts
        pass
    return chans


def _unplayable(schema: Any, channel: Any) -> str | None:
    """Why a message cannot be replayed as recorded ROS 2 data, else None."""
    enc = channel.message_encoding
    if enc != ros2.MESSAGE_ENCODING:
        return f"message encoding {enc!r}, not {ros2.MESSAGE_ENCODING!r} (ROS 2), not replayed"
    if schema is None:
        return "no schema, not replayed"
    return None


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    if not text:  # e.g. mcap's EndOfFile
        return "unexpected end of file" if "EndOfFile" in type(exc).__name__ else type(exc).__name__
    return f"{text[0]} ({type(exc).__name__})"


def play(
    path: str | Path,
    sinks: list[Any],
    rate: float = 1.0,
    stop: threading.Event | None = None,
    report: ReadReport | None = None,
    advertise: bool = True,
) -> int:
    """Write every message to ``sinks`` at ``rate`` x recorded speed (0: as fast as possible).
    Returns the number of messages; ``report`` says whether the file ended early and what was
    skipped. First (``advertise``) the recording's channels are advertised to the sinks that
    advertise (:func:`advertise_recording`). A negative or non-finite ``rate`` is a ValueError."""
    if not (math.isfinite(rate) and rate >= 0):
        raise ValueError(f"rate must be a finite number >= 0 (0: as fast as possible), got {rate}")
    out = Fanout(sinks)
    if advertise:
        advertise_recording(path, sinks)
    stop = stop or threading.Event()
    t_rec0: int | None = None
    t_wall0 = time.monotonic()
    n = 0
    for m in read_recording(path, report):
        if stop.is_set():
            break
        if t_rec0 is None:
            t_rec0 = m.t_ns
        if rate > 0:
            due = t_wall0 + (m.t_ns - t_rec0) / 1e9 / rate
            while not stop.is_set():
                wait = due - time.monotonic()
                if wait <= 0:
                    break
                out.tick()
                stop.wait(min(wait, 0.05))
        out.write(m.topic, m.typename, m.schema, m.data, m.t_ns)
        n += 1
    out.tick()
    return n


def advertise_recording(path: str | Path, sinks: list[Any]) -> None:
    """Advertise every channel of the recording to the sinks that advertise (the Foxglove
    server), before any message: a client subscribes to what it has seen advertised, so a topic
    advertised with its first message would lose that message (a one-shot topic: all of it)."""
    if any(hasattr(s, "advertise") for s in sinks):
        Fanout(sinks).advertise(recorded_channels(path))


# -- re-executing the recorded motion ----------------------------------------------------------
@dataclass
class Plan:
    """Timed waypoints (s from start, per bendable (kx, ky) in 1/m) and what the check found."""

    points: list[dict] = field(default_factory=list)
    segments: list[str] = field(default_factory=list)
    duration: float = 0.0
    lead_in: float = 0.0
    kappa_range: dict[str, tuple[float, float]] = field(default_factory=dict)
    start: dict[str, tuple[float, float]] = field(default_factory=dict)
    end: dict[str, tuple[float, float]] = field(default_factory=dict)
    fastest: dict[str, float] = field(default_factory=dict)  # 1/m/s
    notes: list[str] = field(default_factory=list)
    source: str = "measured"  # "commanded": the recorded goals; "measured": /joint_states
    goals: list[tuple[float, list[dict]]] = field(default_factory=list)  # (start s, points)
    # where the robot is now (the lead-in's start): bendable -> (kappa, phi), for those measured
    now: dict[str, tuple[float, float]] | None = None
    now_unknown: str = ""  # why ``now`` is None (or lacks a bendable), for the dry run to say


def recorded_joint_states(
    path: str | Path, report: ReadReport | None = None
) -> list[tuple[float, dict[str, tuple[float, float]]]]:
    """(t s, {bendable: (kappa, phi)}) of every /joint_states message."""
    dec = None
    out = []
    for m in read_recording(path, report):
        if m.topic != "/joint_states":
            continue
        if dec is None:
            dec = generate_dynamic(m.typename, m.schema)[m.typename]
        msg = dec(m.data)
        vals: dict[str, dict[str, float]] = {}
        for name, pos in zip(msg.name, msg.position, strict=False):
            seg, _, var = name.rpartition("/")
            if var in ("kappa", "phi") and seg and math.isfinite(pos):
                vals.setdefault(seg, {})[var] = pos
        states = {k: (v["kappa"], v["phi"]) for k, v in vals.items() if len(v) == 2}
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        out.append((t, states))
    return out


def recorded_goals(
    path: str | Path, report: ReadReport | None = None
) -> list[tuple[float, list[dict]]]:
    """(t s, waypoints for ``trajectory.send``) of every /ucr/trajectory/commanded message: the
    goals the daemon accepted while recording, as they were sent (before retiming)."""
    dec = None
    out = []
    parts = CommandedGoals()  # the goals' waypoint events, to find one the recording lost
    for m in read_recording(path, report):
        if m.topic == "/ucr/events" and b"goal_" in m.data:
            ev = json.loads(ros2.codec(m.typename).decode(m.data).data)
            if ev.get("event") == "goal_accepted" and ev.get("waypoints_omitted"):
                raise RecordingError(
                    f"goal {ev.get('goal')} had {ev['waypoints_omitted']} waypoints, more than "
                    "the daemon's event carried then: its commanded trajectory is not in the "
                    "recording (use --measured to re-run the measured motion)"
                )
            if ev.get("event") == "goal_waypoints_incomplete":
                _incomplete(ev)
            for lost in parts.feed(ev)[1]:
                _incomplete(lost)
        if m.topic != "/ucr/trajectory/commanded":
            continue
        if dec is None:
            dec = generate_dynamic(m.typename, m.schema)[m.typename]
        msg = dec(m.data)
        slots: dict[str, dict[str, int]] = {}
        for i, name in enumerate(msg.joint_names):
            seg, _, var = name.rpartition("/")
            if seg and var in ("kappa", "phi"):
                slots.setdefault(seg, {})[var] = i
        points = []
        for pt in msg.points:
            pos = list(pt.positions)
            d = pt.time_from_start
            segs = {b: {"kappa": pos[a["kappa"]], "phi": pos[a["phi"]]}
                    for b, a in slots.items() if len(a) == 2}  # fmt: skip
            points.append({"time_from_start": d.sec + d.nanosec * 1e-9, "segments": segs})
        if points:
            out.append((msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9, points))
    for lost in parts.finish():  # e.g. the recorder was killed while a long goal's parts came
        _incomplete(lost)
    return out


def _incomplete(ev: dict) -> None:
    raise RecordingError(
        f"{ev.get('message') or 'a goal is incomplete in the recording'} "
        "(use --measured to re-run the measured motion)"
    )


def _limits(robot: Any) -> dict[str, BendableLimits]:
    """The limits the daemon enforces for ``robot`` (model limits ∩ ``<ros2_control>``)."""
    try:
        return bendable_limits(robot)
    except ConfigError as exc:
        raise RecordingError(str(exc)) from None


def _check_point(
    problems: Problems,
    lims: dict[str, BendableLimits],
    name: str,
    kappa: float,
    phi: float,
    when: str,
    measured: bool = False,
) -> float:
    """κ clipped into [0, kappa_max] after the daemon's own check (host.limits.kappa_exceeds;
    a measured κ gets the measurement slack). A point outside is added to ``problems`` (the
    caller refuses the plan once every point is checked; it reports unknown bendables once)."""
    lim = lims.get(name)
    if lim is None:
        return kappa
    if not (math.isfinite(kappa) and math.isfinite(phi)):
        problems.add(f"{name}: non-finite waypoint {when}")
        return kappa
    if kappa < -KAPPA_EPS or kappa_exceeds(kappa, lim.kappa_max, measured):
        what = "measured" if measured else "recorded"
        problems.add(
            f"{name}: {what} kappa {kappa:.4g} 1/m {when} is outside "
            f"[0, {lim.kappa_max:.4g}] of the robot file"
        )
    elif (
        not lim.full_circle
        and kappa > 1e-9
        and not (lim.phi_min - 1e-9 <= phi <= lim.phi_max + 1e-9)
    ):
        problems.add(
            f"{name}: recorded phi {math.degrees(phi):.1f} deg {when} is "
            f"outside [{math.degrees(lim.phi_min):.1f}, {math.degrees(lim.phi_max):.1f}] "
            "deg of the robot file"
        )
    return min(max(kappa, 0.0), lim.kappa_max)


def _refuse_if_any(problems: Problems, robot: Any) -> None:
    """One RecordingError naming every problem found (the first MAX_REPORTED_PROBLEMS in full):
    a long recording is fixed in one go, not one point per run."""
    if problems:
        who = getattr(robot, "name", "?")
        raise RecordingError(
            problems.text(f"the recording does not fit robot {who!r} (refused, nothing moves)")
        )


Pose = dict[str, tuple[float, float]]  # bendable -> (kx, ky) 1/m


def _vector(kappa: float, phi: float) -> tuple[float, float]:
    return kappa * math.cos(phi), kappa * math.sin(phi)


def measured_pose_at(states: list[tuple[float, dict[str, tuple[float, float]]]], t: float) -> Pose:
    """(kx, ky) per bendable of the last recorded joint state at or before ``t`` (s, the
    stamps' clock); the first one if the recording starts (< 0.5 s) after ``t``; else empty."""
    i = bisect.bisect_right([s for s, _ in states], t) - 1
    if i < 0:
        if not states or states[0][0] - t > 0.5:
            return {}
        i = 0
    return {name: _vector(k, p) for name, (k, p) in states[i][1].items()}


def _position_at(path: list[tuple[float, float, float]], t: float) -> tuple[float, float]:
    """(kx, ky) at ``t`` along a goal's path [(t, kx, ky), ...] (its start, then its waypoints),
    linear between the points, held at its ends."""
    if t <= path[0][0]:
        return path[0][1], path[0][2]
    for (ta, xa, ya), (tb, xb, yb) in zip(path, path[1:], strict=False):
        if t <= tb:
            f = (t - ta) / (tb - ta) if tb > ta else 1.0
            return xa + f * (xb - xa), ya + f * (yb - ya)
    return path[-1][1], path[-1][2]


def _fastest(plan: Plan, name: str, a: tuple[float, float, float], b: tuple[float, float, float]):
    """Record the mean rate (1/m/s) from ``a`` to ``b`` (each (t s, kx, ky)) of ``name``."""
    if b[0] > a[0]:
        speed = math.hypot(b[1] - a[1], b[2] - a[2]) / (b[0] - a[0])
        plan.fastest[name] = max(plan.fastest.get(name, 0.0), speed)


def commanded_plan(path: str | Path, robot: Any, here: Pose | None = None) -> Plan | None:
    """The recorded goals, each waypoint checked against ``robot``; None if none recorded.

    Rates (``fastest``, and the kappa_rate_max notes) are measured as the daemon runs a goal:
    from where the robot is when the goal starts to its first waypoint (the lead-in), then
    waypoint to waypoint. Where the robot is at a goal's start: for the first goal ``here``
    (the live pose, when known) or else the recorded /joint_states at that time; for a later
    goal the previous goal's path at that time (a goal that replaced a running one starts from
    where that one had got to)."""
    report = ReadReport()
    goals = recorded_goals(path, report)
    if not goals:
        return None
    t0 = goals[0][0]
    plan = Plan(source="commanded", notes=report.warnings(path))
    lims = _limits(robot)
    states = recorded_joint_states(path, ReadReport())  # its warnings are in report already
    paths: dict[str, list[tuple[float, float, float]]] = {}  # the last goal's path per bendable
    problems = Problems()
    moved = {n for _, points in goals for pt in points for n in pt["segments"]}
    unknown = sorted(moved - set(lims))
    if unknown:
        problems.add(
            f"the recording moves {', '.join(unknown)}, which robot "
            f"{getattr(robot, 'name', '?')!r} does not have"
        )
    for i, (t_goal, points) in enumerate(goals):
        start = t_goal - t0
        pose = here if i == 0 and here is not None else measured_pose_at(states, t_goal)
        current = {n: [(start, *xy)] for n, xy in pose.items()}
        for n, p in paths.items():  # the previous goal's path where it has one
            current[n] = [(start, *_position_at(p, start))]
        checked = []
        for k, pt in enumerate(points):
            t = pt["time_from_start"]
            # counted from 1, as `ucr replay` prints the goals ("goal 1/2 sent")
            when = f"in goal {i + 1} (sent at {start:.2f} s), waypoint {k + 1} (t = {t:.2f} s)"
            segs = {}
            for name, v in pt["segments"].items():
                kappa = _check_point(problems, lims, name, v["kappa"], v["phi"], when)
                if name not in lims or not (math.isfinite(kappa) and math.isfinite(v["phi"])):
                    continue
                phi = v["phi"]
                segs[name] = {"kappa": kappa, "phi": phi}
                if name not in plan.segments:
                    plan.segments.append(name)
                lo, hi = plan.kappa_range.get(name, (kappa, kappa))
                plan.kappa_range[name] = (min(lo, kappa), max(hi, kappa))
                plan.start.setdefault(name, (kappa, phi))
                plan.end[name] = (kappa, phi)
                point = (start + t, *_vector(kappa, phi))
                if name in current:
                    _fastest(plan, name, current[name][-1], point)
                current.setdefault(name, []).append(point)
            checked.append({"time_from_start": t, "segments": segs})
        paths.update(current)
        plan.goals.append((start, checked))
        plan.points += checked
    _refuse_if_any(problems, robot)
    plan.lead_in = plan.goals[0][1][0]["time_from_start"]  # the first goal's: to its waypoint 1
    last_start, last = plan.goals[-1]
    plan.duration = last_start + last[-1]["time_from_start"]
    plan.segments.sort()
    _note_now(plan, here)
    _rate_notes(plan, lims)
    return plan


def _note_now(plan: Plan, here: Pose | None) -> None:
    """``plan.now``: (kappa, phi) now of each bendable the plan moves, from ``here`` (the live
    pose, None when unknown); the dry run shows the lead-in from it."""
    if here is None:
        return
    plan.now = {n: (math.hypot(*here[n]), math.atan2(here[n][1], here[n][0]))
                for n in plan.segments if n in here}  # fmt: skip
    if len(plan.now) < len(plan.segments):
        plan.now_unknown = "no valid measurement"


def _rate_notes(plan: Plan, lims: dict[str, BendableLimits]) -> None:
    for name in plan.segments:
        rate = lims[name].kappa_rate_max
        if rate is not None and plan.fastest.get(name, 0.0) > rate * (1 + 1e-3):
            plan.notes.append(
                f"{name}: recorded rate {plan.fastest[name]:.3g} 1/m/s exceeds kappa_rate_max "
                f"{rate:.3g}: the daemon will slow the goal down (retimed)"
            )


def make_plan(
    path: str | Path,
    robot: Any,
    sample_period: float = 0.1,
    lead_in: float = 2.0,
    here: Pose | None = None,
) -> Plan:
    """Waypoints from the recorded joint states, checked against ``robot`` (a parsed U(C)RDF):
    every bendable must exist, κ within [0, kappa_max], φ within its range; rates above
    kappa_rate_max are reported (the daemon stretches such a goal: ``retimed``), the lead-in
    from ``here`` (the live pose, when known) included."""
    report = ReadReport()
    states = recorded_joint_states(path, report)
    if not states:
        why = "".join(f"; {w}" for w in report.warnings(path))
        raise RecordingError(f"{path}: no /joint_states messages to execute{why}")
    names = sorted({n for _, s in states for n in s})
    unknown = [n for n in names if n not in robot.bendables]
    if unknown:
        raise RecordingError(
            f"the recording moves {', '.join(unknown)}, which robot {robot.name!r} does not have"
        )
    plan = Plan(segments=names, lead_in=lead_in, notes=report.warnings(path))
    lims = _limits(robot)
    t0 = states[0][0]
    last_t = -math.inf
    prev = {n: (t0 - lead_in, *xy) for n, xy in (here or {}).items()}  # the lead-in's start
    problems = Problems()
    for i, (t, s) in enumerate(states):
        if t - last_t < sample_period - 1e-9 and i != len(states) - 1:
            continue
        last_t = t
        seg_pts = {}
        for name, (kappa, phi) in s.items():
            kappa = _check_point(
                problems, lims, name, kappa, phi, f"at t = {t - t0:.2f} s", measured=True
            )
            if not (math.isfinite(kappa) and math.isfinite(phi)):
                continue
            kx, ky = _vector(kappa, phi)
            seg_pts[name] = {"kx": kx, "ky": ky}
            lo, hi = plan.kappa_range.get(name, (kappa, kappa))
            plan.kappa_range[name] = (min(lo, kappa), max(hi, kappa))
            plan.start.setdefault(name, (kappa, phi))
            plan.end[name] = (kappa, phi)
            if name in prev:
                _fastest(plan, name, prev[name], (t, kx, ky))
            prev[name] = (t, kx, ky)
        plan.points.append({"time_from_start": lead_in + (t - t0), "segments": seg_pts})
    _refuse_if_any(problems, robot)
    plan.duration = plan.points[-1]["time_from_start"]
    plan.goals = [(0.0, plan.points)]
    _note_now(plan, here)
    _rate_notes(plan, lims)
    return plan


def live_pose(client: Any, timeout: float = 2.0) -> Pose | None:
    """(kx, ky) per bendable of the robot now (one joint state from the daemon), for checking
    the rate of the first goal's lead-in; None if none comes within ``timeout`` s."""
    try:
        with client.subscribe(["joint_states"], buffer=4) as sub:
            deadline = time.monotonic() + timeout
            while (left := deadline - time.monotonic()) > 0:
                msg = sub.get(timeout=left)
                if msg is not None and msg.get("kind") == "joint_states":
                    break
            else:
                return None
    except (ApiError, OSError):
        return None
    pose: Pose = {}
    valid = msg.get("valid") or []
    for i, name in enumerate(msg.get("names") or []):
        k, p = msg["kappa"][i], msg["phi"][i]
        if k is not None and p is not None and (i >= len(valid) or valid[i]):
            pose[name] = _vector(float(k), float(p))
    return pose


def describe(plan: Plan) -> str:
    """What would move: per bendable from where it is now (the lead-in, when the live pose is
    known; else said so) through its first waypoint to its end, the range over all of it."""
    what = (f"the recorded commanded trajectory: {len(plan.goals)} goal(s), "
            if plan.source == "commanded" else "the recorded measured motion: ")  # fmt: skip
    now = plan.now or {}
    head = (
        f"{what}{len(plan.points)} waypoints over {plan.duration:.2f} s, the first after a "
        f"{plan.lead_in:.2f} s lead-in from "
        + ("the robot's pose now:" if now else "wherever the robot is then:")
    )
    lines = [head]
    for name in plan.segments:
        (k0, p0), (k1, p1) = plan.start[name], plan.end[name]
        lo, hi = plan.kappa_range[name]
        if name in now:
            kn, pn = now[name]
            lo, hi = min(lo, kn), max(hi, kn)
            start, phi_start, span = f"{kn:.3f}", f"{math.degrees(pn) + 0.0:.1f}", ""
        else:
            start, phi_start, span = "?", "?", " from the first waypoint on"
        lines.append(
            f"  {name}: kappa {start} now -> {k0:.3f} after the lead-in -> {k1:.3f} 1/m at the "
            f"end (range {lo:.3f}..{hi:.3f}{span}), phi {phi_start} -> "
            f"{math.degrees(p0):.1f} -> {math.degrees(p1):.1f} deg, "
            f"fastest {plan.fastest.get(name, 0.0):.3g} 1/m/s"
        )
    unknown = [n for n in plan.segments if n not in now]
    if unknown:
        who = ("the robot is" if plan.now is None else
               f"{', '.join(unknown)} {'is' if len(unknown) == 1 else 'are'}")  # fmt: skip
        rate = ("not checked" if plan.source == "measured"
                else "checked from the recorded pose at the goal's start")  # fmt: skip
        lines.append(
            f"  note: where {who} now is unknown ({plan.now_unknown or 'not measured'}): the "
            "lead-in to the first waypoint (from wherever the robot is when it starts) is not "
            f"in the figures above, its rate {rate}"
        )
    lines += [f"  note: {n}" for n in plan.notes]
    return "\n".join(lines)


def run_goals(client: Any, plan: Plan) -> dict:
    """Send the plan's goals at their recorded start offsets (a later goal replaces a running
    one, as it did when recorded); returns the last goal's final status. Each goal's progress
    is shown on stderr."""
    t0 = time.monotonic()
    result: dict = {}
    tty = sys.stderr.isatty()  # in place on a terminal, a line per state or 10 % else
    for i, (start, points) in enumerate(plan.goals):
        time.sleep(max(0.0, t0 + start - time.monotonic()))
        gid = client.send_trajectory(points, wait=False)
        print(f"  goal {i + 1}/{len(plan.goals)} sent: {gid} ({len(points)} waypoints)",
              file=sys.stderr, flush=True)  # fmt: skip
        end = (plan.goals[i + 1][0] + t0) if i + 1 < len(plan.goals) else math.inf
        deadline = time.monotonic() + points[-1]["time_from_start"] * 3 + 30
        shown = None
        while True:
            result = client.trajectory_status(gid)
            pct = 100 * (result.get("progress") or 0)
            line = f"  {result.get('state', '?'):10s} {pct:5.1f} %"
            if tty:
                print(f"\r{line}", end="", file=sys.stderr, flush=True)
            elif (result.get("state"), int(pct // 10)) != shown:
                shown = (result.get("state"), int(pct // 10))
                print(line, file=sys.stderr, flush=True)
            if result.get("done") or time.monotonic() >= min(end, deadline):
                break
            time.sleep(0.1)
        if tty:
            print(file=sys.stderr)
        if result.get("done") and result.get("state") != "succeeded" and end < math.inf:
            break  # an aborted goal (limits, tolerance, takeover): stop here, as the daemon did
    return result


def execute(args: Any) -> int:
    """``ucr replay FILE --execute [--go]``."""
    client = None
    try:
        unknown = ""  # why the live pose (the lead-in's start) is unknown
        if args.robot:
            robot = load(args.robot)
            try:  # the lead-in starts where the robot is: ask a daemon if one answers
                client = connect_daemon(args)
            except CliError as exc:
                # "cannot reach the daemon at URL (--url)", without the advice that follows
                unknown = f"no daemon reachable: {str(exc).split(': is `ucr daemon`')[0]}"
        else:
            client = connect_daemon(args)
            robot, _ = robot_for(client, None)
        here = live_pose(client) if client is not None else None  # the lead-in's start
        if client is not None and here is None:
            unknown = "the daemon sent no joint state within 2 s"
        measured = getattr(args, "measured", False)
        plan = None if measured else commanded_plan(args.file, robot, here)
        if plan is None:
            if not measured:
                print("no commanded trajectory in the recording (/ucr/trajectory/commanded): "
                      "re-running the measured motion (/joint_states)")  # fmt: skip
            plan = make_plan(args.file, robot, args.sample_period, args.lead_in, here)
        plan.now_unknown = plan.now_unknown or unknown
        print(describe(plan))
        if not args.go:
            print("dry run: nothing moved (add --go to run it on the robot)")
            return 0
        if client is None:
            client = connect_daemon(args)
        live = set(client.status().get("segments") or [])
        missing = [n for n in plan.segments if n not in live]
        if missing:
            print(f"ucr: the daemon does not control {', '.join(missing)}: refused, nothing moves",
                  file=sys.stderr)  # fmt: skip
            return 1
        result = run_goals(client, plan)
        why = f": {result['reason']}" if result.get("reason") else ""
        print(f"goal {result.get('id')}: {result.get('state')}{why} in "
              f"{result.get('duration') or 0:.2f} s"
              + (" (retimed)" if result.get("retimed") else ""))  # fmt: skip
        return 0 if result.get("state") == "succeeded" else 1
    except (RecordingError, UcrdfError, CliError, FeedError) as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return getattr(exc, "exit_code", 1)  # a CliUsageError: 2
    except ApiError as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    finally:
        if client is not None:
            client.close()


def run(args: Any) -> int:
    """The ``ucr replay`` command: 0 at the end of the file (or SIGTERM), 130 after Ctrl-C."""
    if args.execute:
        return execute(args)
    signals = StopSignals()  # installed once serving: Ctrl-C while starting raises at once
    stop, interrupted = signals.stop, signals.interrupted
    sinks: list[Any] = []
    app = None
    n = 0
    try:  # while starting, Ctrl-C raises KeyboardInterrupt: nothing can block it
        next(iter(read_recording(args.file)), None)  # readable at all, before serving anything
        if getattr(args, "view", False) and getattr(args, "robot", None):
            _check_recorded_robot(args.file, args.robot)
        if not getattr(args, "no_foxglove", False):
            from interop.foxglove import sink_from_args  # noqa: PLC0415 - not for --execute
            from interop.guard import GuardError  # noqa: PLC0415

            try:
                sink = sink_from_args(args.host, args.port, args)
            except (GuardError, OSError, RuntimeError) as exc:  # ListenError: an OSError
                print(f"ucr: {exc}", file=sys.stderr)
                return 1
            sinks.append(sink)
            print(f"ucr: Foxglove server on {sink.url}", file=sys.stderr, flush=True)
        if getattr(args, "view", False):
            try:
                app = _start_view(args)
            except (ImportError, OSError, RuntimeError, UcrdfError) as exc:
                why = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
                print(f"ucr: cannot serve the view: {why}", file=sys.stderr)
                return 1
            sinks.append(app.source)
            print(f"ucr view: {app.url}  (replay)", file=sys.stderr, flush=True)
        if not sinks:
            print("ucr: nothing to play into (--no-foxglove without --view)", file=sys.stderr)
            return 2

        signals.install()
        advertise_recording(args.file, sinks)  # before a client connects (--wait-client)
        speed = f"at {args.rate:g}x" if args.rate > 0 else "as fast as possible (--rate 0)"
        print(f"ucr: replaying {args.file} {speed}", file=sys.stderr, flush=True)
        if args.wait_client > 0:
            stop.wait(args.wait_client)
        report = ReadReport()
        if not stop.is_set():
            n = play(args.file, sinks, rate=args.rate, stop=stop, report=report, advertise=False)
        for line in report.warnings(args.file):
            print(f"ucr: warning: {line}", file=sys.stderr, flush=True)
        cut = "interrupted (Ctrl-C): " if interrupted.is_set() else ""
        print(f"ucr: {cut}{n} messages replayed", file=sys.stderr, flush=True)
        if app is not None and not stop.is_set():
            print("ucr: end of the recording; the view stays up (Ctrl-C to stop)",
                  file=sys.stderr, flush=True)  # fmt: skip
            stop.wait()
        if interrupted.is_set() and not cut:  # at the end of the file, in the view
            print("ucr: interrupted (Ctrl-C)", file=sys.stderr)
        return signals.exit_code()
    except KeyboardInterrupt:
        print("ucr: interrupted (Ctrl-C) while starting", file=sys.stderr)
        return INTERRUPTED
    except (RecordingError, UcrdfError) as exc:
        print(f"ucr: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)  # closing: as while starting
        for s in sinks:
            s.close()
        if app is not None:
            app.stop()


def _check_recorded_robot(path: str | Path, robot_file: str) -> None:
    """RecordingError unless ``robot_file`` has the bendables and joints of the robot the
    recording carries (``/ucr/robot_description_ucrdf``); a recording without it passes."""
    for m in read_recording(path):
        if m.topic == "/ucr/robot_description_ucrdf":
            text = ros2.codec(m.typename).decode(m.data).data
            recorded = parse_string(text, f"{path}:/ucr/robot_description_ucrdf")
            differs = robot_mismatch(load(robot_file), recorded)
            if differs:
                raise RecordingError(
                    f"{robot_file} is not the robot of {path} ({differs}): refused"
                )
            return


def _start_view(args: Any) -> Any:
    """The 3D view (``ucr view``) of the recording, view only (no controls)."""
    from view.app import ViewApp  # noqa: PLC0415 - the view extra, only when asked
    from view.replay import ReplaySource  # noqa: PLC0415

    source = ReplaySource(args.file, getattr(args, "robot", None))
    view = ViewApp(source, args.view_host, args.view_port, control=False, port_option="--view-port")
    return view.start()
