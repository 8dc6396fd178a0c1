"""Topology: compare the discovered chain with the U(C)RDF, cut a robot to the segments present,
and compose a robot from descriptors (``--adopt``).

The bendables of a robot, in chain order, are found by walking the kinematic tree from the root
link (document order among siblings): position k on the wire is the k-th bendable met.

Differences are reported kind by kind (count, config, model, geometry, limits, identity, name)
with the position and both values, so a user knows exactly what to fix. A segment that refused
its own configuration (its DESCRIPTOR's ``config_error``: none flashed, invalid, too large) holds
and never moves, whatever is sent: a blocking ``config`` difference, said first. Identity is
checked only when the U(C)RDF pins it: a ``<hardware>`` param ``<bendable>/uid`` (e.g.
``<param name="seg1/uid">a4cf12fe0b3c</param>``) must equal the segment's unique id.
"""

from __future__ import annotations

import copy
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from host.limits import bendable_limits
from host.positions import label as position_label
from ucrdf.checks import check
from ucrdf.errors import UcrdfError
from ucrdf.model import Robot

REL_TOL = 2e-3  # descriptors carry float32: compare geometry with a relative tolerance
ABS_TOL = 1e-6


@dataclass
class Difference:
    """One way the chain differs from the description. ``blocking`` ones stop a start."""

    kind: str  # count | config | model | geometry | limits | identity | name
    position: int | None  # 0-based chain index (None: the whole chain, e.g. a count)
    bendable: str | None
    message: str
    blocking: bool = True

    def as_dict(self) -> dict[str, Any]:
        """As the API shows it: ``position`` counted from 1, like the message ("position 1")."""
        return {
            "kind": self.kind,
            "position": None if self.position is None else self.position + 1,
            "bendable": self.bendable,
            "message": self.message,
            "blocking": self.blocking,
        }


@dataclass
class Comparison:
    """Result of :func:`compare`. ``matched`` = leading positions that match the description."""

    expected: list[str]
    found: int
    matched: int
    differences: list[Difference] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not any(d.blocking for d in self.differences)

    def text(self) -> str:
        if self.ok:
            return f"chain matches the description ({self.found} segment(s))"
        return "; ".join(d.message for d in self.differences if d.blocking)


def chain_bendables(robot: Robot) -> list[str]:
    """Bendable names in chain order (depth-first from the root link, document order)."""
    children: dict[str, list[tuple[bool, str, str]]] = {}
    for b in robot.bendables.values():
        children.setdefault(b.parent, []).append((True, b.name, b.child))
    for j in robot.joints.values():
        children.setdefault(j.parent, []).append((False, j.name, j.child))
    try:
        root = robot.root_link()
    except ValueError:
        return list(robot.bendables)
    out: list[str] = []
    stack = [root]
    seen: set[str] = set()
    while stack:
        link = stack.pop()
        if link in seen:
            continue
        seen.add(link)
        kids = children.get(link, [])
        out += [name for is_b, name, _ in kids if is_b]
        stack += [child for _, _, child in reversed(kids)]
    return out


def pinned_uids(robot: Robot) -> dict[str, str]:
    """Bendable -> uid pinned in a ``<hardware>`` param ``<bendable>/uid`` (lower-case hex)."""
    out: dict[str, str] = {}
    for key, value in robot.hardware_params().items():
        name, _, what = key.rpartition("/")
        if what == "uid" and name in robot.bendables:
            out[name] = str(value).strip().lower()
    return out


def _close(a: float, b: float) -> bool:
    return abs(a - b) <= max(ABS_TOL, REL_TOL * max(abs(a), abs(b)))


def _diff_one(
    robot: Robot, name: str, pos: int, d: dict[str, Any], uids: dict[str, str]
) -> list[Difference]:
    b = robot.bendables[name]
    out: list[Difference] = []
    label = f"{position_label(pos)} ({name})"

    def add(kind: str, msg: str, blocking: bool = True) -> None:
        out.append(Difference(kind, pos, name, f"{label}: {msg}", blocking))

    refused = d.get("config_error")
    if refused:  # it runs no configuration of ours: the rest of its descriptor is no robot's
        add(
            "config",
            f"the segment refused its configuration ({str(refused)[:120]}) and will not move; "
            f"flash it: ucr flash --robot ROBOT --segment {name} --port PORT",
        )
    model = d.get("model")
    if model != b.model.type:
        add("model", f"model {model!r} on the segment, {b.model.type!r} in the description")
    length = d.get("length")
    if not isinstance(length, int | float) or not _close(float(length), b.length):
        add("geometry", f"length {length} m on the segment, {b.length:g} m in the description")
    act = b.actuation
    if act is not None:
        angles = d.get("tendon_angles") or []
        if len(angles) != len(act.angles):
            add(
                "geometry",
                f"{len(angles)} tendon(s) on the segment, {len(act.angles)} in the description",
            )
        elif not all(_close(float(x), y) for x, y in zip(angles, act.angles, strict=True)):
            fmt = ", ".join(f"{math.degrees(float(a)):.1f}" for a in angles)
            exp = ", ".join(f"{math.degrees(a):.1f}" for a in act.angles)
            add(
                "geometry",
                f"tendon angles [{fmt}] deg on the segment, [{exp}] deg in the description",
            )
        for key, expected in (("tendon_radius", act.radius), ("spool_radius", act.spool_radius)):
            got = d.get(key)
            if expected and (not isinstance(got, int | float) or not _close(float(got), expected)):
                add("geometry", f"{key} {got} m on the segment, {expected:g} m in the description")
    # A description tighter than the segment is safe (the host never commands beyond it): noted,
    # not blocking. A looser one would command what the segment refuses: blocking.
    lim = b.model.limits
    kmax = d.get("kappa_max")
    if not isinstance(kmax, int | float) or not _close(float(kmax), lim.kappa_max):
        tighter = isinstance(kmax, int | float) and lim.kappa_max < float(kmax)
        add(
            "limits",
            f"kappa_max {kmax} 1/m on the segment, {lim.kappa_max:g} 1/m in the description"
            + (" (the description's tighter limit applies)" if tighter else ""),
            blocking=not tighter,
        )
    rate = d.get("kappa_rate_max")
    if (
        lim.kappa_rate_max
        and isinstance(rate, int | float)
        and not _close(float(rate), lim.kappa_rate_max)
    ):
        tighter = lim.kappa_rate_max < float(rate)
        add(
            "limits",
            f"kappa_rate_max {rate} 1/m/s on the segment, {lim.kappa_rate_max:g} "
            "1/m/s in the description"
            + (" (the description's tighter limit applies)" if tighter else ""),
            blocking=not tighter,
        )
    if name in uids and str(d.get("uid", "")).lower() != uids[name]:
        add(
            "identity",
            f"uid {d.get('uid')!r} on the segment, {uids[name]!r} pinned in the description",
        )
    seg_name = d.get("name")
    if seg_name and seg_name != name:
        add("name", f"segment calls itself {seg_name!r}", blocking=False)
    return out


def compare(robot: Robot, descriptors: list[dict[str, Any]]) -> Comparison:
    """Compare discovered descriptors (chain order) with the robot's bendables (chain order)."""
    names = chain_bendables(robot)
    uids = pinned_uids(robot)
    cmp = Comparison(expected=names, found=len(descriptors), matched=0)
    src = Path(robot.source).name if robot.source else robot.name
    matching = True
    for pos, d in enumerate(descriptors[: len(names)]):
        diffs = _diff_one(robot, names[pos], pos, d, uids)
        cmp.differences += diffs
        if matching and not any(x.blocking for x in diffs):
            cmp.matched = pos + 1
        else:
            matching = False
    if len(descriptors) != len(names):
        if len(descriptors) < len(names):
            missing = ", ".join(names[len(descriptors) :])
            msg = (
                f"chain has {len(descriptors)} segment(s), {src} declares {len(names)}: "
                f"missing {missing}"
            )
        else:
            extra = ", ".join(
                f"{i + 1} ({descriptors[i].get('name') or descriptors[i].get('uid')})"
                for i in range(len(names), len(descriptors))
            )
            msg = (
                f"chain has {len(descriptors)} segment(s), {src} declares {len(names)}: "
                f"extra at position(s) {extra}"
            )
        cmp.differences.insert(0, Difference("count", None, None, msg))
    return cmp


def truncate(robot: Robot, keep: int) -> Robot:
    """A copy of ``robot`` with only its first ``keep`` bendables (chain order): everything
    downstream of the first dropped bendable is cut, and ``<ros2_control>`` entries for dropped
    elements are removed."""
    names = chain_bendables(robot)
    if keep >= len(names):
        return robot
    out = copy.deepcopy(robot)
    cut = names[keep]
    drop_links: set[str] = set()
    frontier = [out.bendables[cut].child]
    while frontier:
        link = frontier.pop()
        if link in drop_links:
            continue
        drop_links.add(link)
        frontier += [b.child for b in out.bendables.values() if b.parent == link]
        frontier += [j.child for j in out.joints.values() if j.parent == link]
    dropped_elems = {cut}
    for n, b in list(out.bendables.items()):
        if b.parent in drop_links or n == cut:
            del out.bendables[n]
            dropped_elems.add(n)
    for n, j in list(out.joints.items()):
        if j.parent in drop_links:
            del out.joints[n]
            dropped_elems.add(n)
    for link in drop_links:
        out.links.pop(link, None)
    for block in out.ros2_control:
        block.joints = [j for j in block.joints if j.name not in dropped_elems]
    out.source = robot.source
    return out


@dataclass(frozen=True)
class Envelope:
    """The most a segment may claim for itself when adopted (1/m, 1/m/s); None = no bound."""

    kappa_max: float | None = None
    kappa_rate_max: float | None = None


def envelope_from(robot: Robot) -> Envelope:
    """The configured envelope: the largest *effective* limits among the described robot's
    bendables, as the host runs them (:func:`host.limits.bendable_limits`: the model's
    ``<limits>`` tightened by the ``<ros2_control>`` kappa command interface ``max``, an unset
    ``kappa_rate_max`` read as ``DEFAULT_KAPPA_RATE_MAX``), so an adopted segment never gets
    more than the user's own description allows anywhere."""
    lims = list(bendable_limits(robot).values())
    if not lims:
        return Envelope()
    return Envelope(max(lim.kappa_max for lim in lims), max(lim.kappa_rate_max for lim in lims))


def cap_limits(robot: Robot, envelope: Envelope) -> list[str]:
    """Clamp every bendable's limits (model and ``<ros2_control>`` kappa max) to ``envelope``;
    returns one line per value that was lowered."""
    out = []
    for name, b in robot.bendables.items():
        lim = b.model.limits
        cap = envelope.kappa_max
        if cap is not None and lim.kappa_max > cap:
            out.append(f"{name}: kappa_max {lim.kappa_max:g} 1/m capped to {cap:g} 1/m")
            lim.kappa_max = cap
        cap = envelope.kappa_rate_max
        if cap is not None and (lim.kappa_rate_max is None or lim.kappa_rate_max > cap):
            shown = "unset" if lim.kappa_rate_max is None else f"{lim.kappa_rate_max:g} 1/m/s"
            out.append(f"{name}: kappa_rate_max {shown} capped to {cap:g} 1/m/s")
            lim.kappa_rate_max = cap
    for block in getattr(robot, "ros2_control", []):
        for joint in block.joints:
            bend = robot.bendables.get(joint.name)
            for itf in joint.command_interfaces:
                if bend is not None and itf.name == "kappa" and "max" in itf.params:
                    itf.params["max"] = min(float(itf.params["max"]), bend.model.limits.kappa_max)
    return out


def write_atomic(path: str | Path, text: str, mode: int = 0o644) -> None:
    """Write ``text`` to ``path`` atomically (temp file in the same directory, created with
    ``mode``, then rename): readers see the old file or the new one, never half; a symlink at
    ``path`` is replaced, never followed, so no other file can be overwritten through it."""
    p = Path(path)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, mode)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def keep_wiring(adopted: Robot, original: Robot) -> None:
    """What a descriptor does not carry, taken from the description the daemon was started
    with for every segment found under the same name with the same tendon count: its servos
    (ids, ranges, zero offsets, directions), board and wiring, and the segment-level hardware
    parameters (watchdog_ms, tick_ms). Without them every adopted segment got servo ids 0, 1, 2
    and the default watchdog, so flashing from the adopted file broke real hardware."""
    for name, bend in adopted.bendables.items():
        old = original.bendables.get(name)
        act, old_act = bend.actuation, old.actuation if old is not None else None
        if act is None or old_act is None or old_act.count != act.count:
            continue
        act.servos = list(old_act.servos)
        act.board, act.uarts, act.pwm_pins = (
            old_act.board,
            dict(old_act.uarts),
            dict(old_act.pwm_pins),
        )
    old_params = original.hardware_params()
    for control in adopted.ros2_control:
        for key in ("watchdog_ms", "tick_ms"):
            if key in old_params:
                control.hardware_params.setdefault(key, old_params[key])


def adopt_capped(
    descriptors: list[dict[str, Any]],
    name: str,
    out_path: str | Path,
    envelope: Envelope | None = None,
    original: Robot | None = None,
) -> tuple[Robot, list[str]]:
    """Compose a robot from the descriptors (``ucrdf.compose``), keep the ``original``
    description's wiring for the segments it names (:func:`keep_wiring`), cap its limits to
    ``envelope`` and write it atomically to ``out_path``; returns the robot and what was
    capped."""
    from ucrdf.compose import robot_from_descriptors  # noqa: PLC0415 - optional until used
    from ucrdf.writer import dumps  # noqa: PLC0415

    robot = robot_from_descriptors(descriptors, name)
    if original is not None:
        keep_wiring(robot, original)
        problems = check(robot)
        if problems:  # the file's wiring does not fit the segment found under that name
            raise UcrdfError(problems)
    capped = cap_limits(robot, envelope) if envelope is not None else []
    write_atomic(out_path, dumps(robot))
    robot.source = str(out_path)
    return robot, capped


def adopt(
    descriptors: list[dict[str, Any]],
    name: str,
    out_path: str | Path,
    envelope: Envelope | None = None,
) -> Robot:
    """:func:`adopt_capped` without the report."""
    return adopt_capped(descriptors, name, out_path, envelope)[0]


def adopted_path(robot_path: str | Path | None, name: str) -> Path:
    """Where ``--adopt`` writes: the state directory when there is one (``$STATE_DIRECTORY``, set
    by systemd's StateDirectory=), else ``<file>.adopted.ucrdf`` beside the given file, else
    ``./<name>.adopted.ucrdf``."""
    state = os.environ.get("STATE_DIRECTORY", "").split(":")[0]
    stem = Path(robot_path).stem if robot_path else name
    if state:
        return Path(state) / f"{stem}.adopted.ucrdf"
    if robot_path:
        p = Path(robot_path)
        return p.with_name(p.stem + ".adopted.ucrdf")
    return Path(f"{name}.adopted.ucrdf")
