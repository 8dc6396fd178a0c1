"""The robot's data as ROS 2 topics: turns the daemon's API messages (docs/api.md) into ROS 2
messages (nested dicts for :mod:`interop.ros2`). One place for recording, replay and the live
Foxglove server, so every consumer sees the same topics (docs/recording.md lists them).

The transforms are computed here from the joint states, as ROS's robot_state_publisher does from
/robot_description: /tf carries every movable joint of the exported URDF (the pseudo-rigid joints
subdivided along each arc included), /tf_static every fixed one; /ucr/arcs draws each segment's
true backbone curve (exact model FK, not the pseudo-rigid chord).

Only measured poses are shown (one rule for /tf and /ucr/arcs, so for every output built on this
module: ``ucr record``, ``ucr foxglove``, ``ucr zenoh``): a bendable that a joint state leaves out
(unplugged, beyond a cut) or reports without a valid measurement (``valid`` false, κ or φ missing
or not finite) keeps the last pose measured for it, and its arc is drawn in STALE_COLOR. One
never measured yet has no /tf transforms and no arc, and the bendables it carries no arc either
(their place in the root frame is unknown): never a made-up straight pose. /joint_states carries
what the daemon reported, unchanged.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from lxml import etree

from ucrdf.export import export_urdf, frames_along, subdivision_angles
from ucrdf.fk import RobotKinematics, axis_rotation
from ucrdf.model import Origin, Robot

# topic -> ROS 2 type (docs/recording.md)
TOPICS: dict[str, str] = {
    "/robot_description": "std_msgs/msg/String",
    "/ucr/robot_description_ucrdf": "std_msgs/msg/String",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/joint_states": "sensor_msgs/msg/JointState",
    "/ucr/arcs": "visualization_msgs/msg/MarkerArray",
    "/ucr/segments": "diagnostic_msgs/msg/DiagnosticArray",
    "/ucr/loop_stats": "diagnostic_msgs/msg/DiagnosticArray",
    "/rosout": "rcl_interfaces/msg/Log",
    "/ucr/events": "std_msgs/msg/String",
    "/ucr/trajectory/goals": "std_msgs/msg/String",
    "/ucr/trajectory/results": "std_msgs/msg/String",
    "/ucr/trajectory/commanded": "trajectory_msgs/msg/JointTrajectory",
}
LATCHED = ("/robot_description", "/ucr/robot_description_ucrdf", "/tf_static")

#: A velocity is derived from two consecutive samples at most this far apart (s); else unknown.
VELOCITY_MAX_GAP_S = 0.25
#: Below this κ (1/m) the bending plane φ is undefined: φ̇ is reported unknown (NaN).
PHI_RATE_MIN_KAPPA = 0.02

LINE_STRIP = 4
#: /ucr/arcs colour (RGBA) of a bendable measured in this joint state, and of one shown at its
#: last measured pose because this joint state has no valid measurement of it (stale).
ARC_COLOR = {"r": 0.1, "g": 0.6, "b": 0.95, "a": 1.0}
STALE_COLOR = {"r": 0.6, "g": 0.6, "b": 0.6, "a": 0.4}

# rcl_interfaces/msg/Log levels
LOG_DEBUG, LOG_INFO, LOG_WARN, LOG_ERROR, LOG_FATAL = 10, 20, 30, 40, 50
#: /rosout level of each event the daemon emits (docs/daemon.md lists them), of the topology
#: messages (``kind`` topology) and of the events the feed makes itself (interop/). An
#: event not in the table (a newer daemon's, or a segment event code this version does not
#: know, ``event_<code>``) gets EVENT_LEVEL_DEFAULT. Kept complete by
#: tests/interop_clients/test_review_topics.py, which reads the event names from host/ and
#: interop/.
EVENT_LEVELS: dict[str, int] = {
    # segment events (protocol EVENT frames, host/supervision.py)
    "downstream_up": LOG_INFO,  # a segment appeared behind another: a rejoin or a new one
    "downstream_down": LOG_WARN,  # a neighbour went silent: the chain is cut there
    "watchdog_tripped": LOG_WARN,  # the segment holds: no command reached it in time
    "watchdog_cleared": LOG_INFO,
    "servo_fault": LOG_ERROR,
    "limit_clamped": LOG_WARN,  # the segment clamped a setpoint
    "boot": LOG_WARN,  # a segment (re)booted: a topology change
    "fault": LOG_ERROR,  # the segment is in FAULT and holds until cleared
    "fault_cleared": LOG_INFO,
    # daemon events
    "topology_changed": LOG_WARN,
    "link_stall": LOG_WARN,  # a stall, resumed with the chain unchanged
    "link_degraded": LOG_WARN,  # the loop slowed down for a slow link
    "link_recovered": LOG_INFO,
    "link_too_slow": LOG_ERROR,  # segments behind it not reliably under control
    "link_lossy": LOG_WARN,
    "link_loss_cleared": LOG_INFO,
    "segment_refused": LOG_WARN,  # a segment to reflash: the chain ends before it
    "segments_held": LOG_WARN,  # segments reported HOLD: controllers re-held
    "misaddressed": LOG_ERROR,  # a segment applied another's setpoint: goals aborted
    "fault_clear_sent": LOG_INFO,  # the user's own request (ucr clear-fault)
    "chain_lost": LOG_ERROR,
    "link_lost": LOG_ERROR,
    "link_restored": LOG_INFO,
    "manual_takeover": LOG_WARN,
    "hand_back": LOG_INFO,
    "controllers_switched": LOG_INFO,
    "goal_accepted": LOG_INFO,
    "goal_waypoints": LOG_INFO,
    "adopted": LOG_INFO,
    "cycle_error": LOG_ERROR,
    # not events of the daemon: its topology messages, and the feed's own (interop/)
    "topology": LOG_WARN,
    "goal_waypoints_incomplete": LOG_WARN,  # the recording lacks a goal's commanded trajectory
    "daemon_lost": LOG_WARN,  # the live feed lost the daemon: no data until it is back
    "daemon_reconnected": LOG_INFO,
}
#: /rosout level of an event name not in EVENT_LEVELS: WARN, so that it is seen.
EVENT_LEVEL_DEFAULT = LOG_WARN


def event_level(name: str) -> int:
    """rcl_interfaces/Log level of an API event (or ``topology``) on /rosout: EVENT_LEVELS,
    else EVENT_LEVEL_DEFAULT."""
    return EVENT_LEVELS.get(name, EVENT_LEVEL_DEFAULT)


@dataclass(frozen=True)
class Message:
    """One ROS 2 message to publish: topic, type, content (dict) and stamp (ns, wall clock)."""

    topic: str
    typename: str
    msg: dict[str, Any]
    t_ns: int


def quaternion(r: np.ndarray) -> dict[str, float]:
    """geometry_msgs/Quaternion of a 3x3 rotation matrix (largest-component branch)."""
    tr = float(r[0, 0] + r[1, 1] + r[2, 2])
    diag = [tr, float(r[0, 0]), float(r[1, 1]), float(r[2, 2])]
    k = int(np.argmax(diag))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, s / 4
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = s / 4, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = (r[0, 1] + r[1, 0]) / s, s / 4, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, s / 4, (r[1, 0] - r[0, 1]) / s
    if q[3] < 0:
        q = tuple(-v for v in q)
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


def _transform(t: np.ndarray) -> dict[str, Any]:
    return {
        "translation": {"x": float(t[0, 3]), "y": float(t[1, 3]), "z": float(t[2, 3])},
        "rotation": quaternion(t[:3, :3]),
    }


def _header(t_ns: int, frame: str = "") -> dict[str, Any]:
    return {"stamp": {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000},
            "frame_id": frame}  # fmt: skip


def _string(topic: str, text: str, t_ns: int) -> Message:
    return Message(topic, TOPICS[topic], {"data": text}, t_ns)


@dataclass
class _UrdfJoint:
    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray


def _parse_joints(urdf: str) -> list[_UrdfJoint]:
    root = etree.fromstring(urdf.encode())
    out = []
    for j in root.findall("joint"):  # the robot's joints (a <transmission> names joints too)
        o = j.find("origin")
        xyz = tuple(float(v) for v in o.get("xyz", "0 0 0").split()) if o is not None else (0,) * 3
        rpy = tuple(float(v) for v in o.get("rpy", "0 0 0").split()) if o is not None else (0,) * 3
        ax = j.find("axis")
        axis = np.array([float(v) for v in ax.get("xyz").split()]) if ax is not None else None
        if axis is not None:
            axis = axis / np.linalg.norm(axis)
        out.append(_UrdfJoint(j.get("name"), j.get("type"), j.find("parent").get("link"),
                              j.find("child").get("link"), Origin(xyz, rpy).matrix(),
                              axis))  # fmt: skip
    return out


class RobotTopics:
    """Converter for one robot: exported URDF with ``subdivisions`` per bendable."""

    def __init__(self, robot: Robot, ucrdf_text: str = "", subdivisions: int = 10) -> None:
        self.robot = robot
        self.kin = RobotKinematics(robot)
        self.root = self.kin.root
        self.subdivisions = subdivisions
        self.urdf = export_urdf(robot, subdivisions)
        self.ucrdf_text = ucrdf_text
        self.joints = _parse_joints(self.urdf)
        self.movable = [j for j in self.joints if j.type != "fixed"]
        self.fixed = [j for j in self.joints if j.type == "fixed"]
        self.bendables = list(robot.bendables)
        self._prev: dict[str, tuple[float, float, float] | None] = {}  # for velocities
        # the last valid (kappa, phi) measured of each bendable (see the module's docstring)
        self._measured: dict[str, tuple[float, float]] = {}
        # the exported URDF's movable joints that place each bendable (export.py's names)
        self._own_joints = {
            name: {f"{name}_prb{k}_{ax}" for k in range(subdivisions) for ax in ("rx", "ry")}
            | {f"{name}_prb_twist"}
            for name in self.kin.models
        }

    # -- latched -------------------------------------------------------------------------------
    def static_messages(self, t_ns: int) -> list[Message]:
        """/robot_description, the U(C)RDF text and /tf_static (every fixed joint)."""
        tf = [
            {"header": _header(t_ns, j.parent), "child_frame_id": j.child,
             "transform": _transform(j.origin)}
            for j in self.fixed
        ]  # fmt: skip
        return [
            _string("/robot_description", self.urdf, t_ns),
            _string("/ucr/robot_description_ucrdf", self.ucrdf_text, t_ns),
            Message("/tf_static", TOPICS["/tf_static"], {"transforms": tf}, t_ns),
        ]

    # -- joint states --------------------------------------------------------------------------
    def _measure(self, js: dict) -> set[str]:
        """Take the valid measurements of joint state ``js`` as the bendables' last measured
        poses; returns the bendables measured in it. Valid: named, ``valid`` true (or no flags),
        κ and φ finite numbers. Every method given a joint state calls this (the same state
        twice changes nothing), so the last measured pose is the newest one this converter saw."""
        fresh: set[str] = set()
        names = js.get("names") or []
        kappas, phis = js.get("kappa") or [], js.get("phi") or []
        flags = js.get("valid") or []
        for i, name in enumerate(names):
            if name not in self.kin.models or i >= len(kappas) or i >= len(phis):
                continue
            kappa, phi = kappas[i], phis[i]
            if i < len(flags) and not flags[i]:
                continue
            if not (_finite(kappa) and _finite(phi)):
                continue
            self._measured[name] = (float(kappa), float(phi))
            fresh.add(name)
        return fresh

    def _coords(self, js: dict) -> tuple[dict[str, np.ndarray], dict[str, float], set[str]]:
        """Model coordinates of every bendable at its last measured pose (zeros, a placeholder
        only, for one never measured), the rigid joints, and the bendables measured in ``js``."""
        fresh = self._measure(js)
        coords: dict[str, np.ndarray] = {}
        for name, model in self.kin.models.items():
            q = np.zeros(len(model.coordinate_names()))
            if name in self._measured:
                # from (kappa, phi) as /joint_states carries them, so /tf is exactly what a
                # consumer recomputes from /joint_states (the daemon's kx, ky are rounded apart)
                kappa, phi = self._measured[name]
                q[:2] = kappa * math.cos(phi), kappa * math.sin(phi)
            coords[name] = q
        rigid = {k: float(v["position"]) for k, v in (js.get("rigid") or {}).items()
                 if isinstance(v, dict) and v.get("position") is not None}  # fmt: skip
        return coords, rigid, fresh

    def _placed(self) -> set[str]:
        """The bendables whose pose in the root frame is known: measured, and every bendable
        between them and the root measured too."""
        unknown_links: set[str] = set()
        placed: set[str] = set()
        for el in self.kin.order:
            lost = el.parent in unknown_links
            if el.kind == "bendable":
                if lost or el.name not in self._measured:
                    lost = True
                else:
                    placed.add(el.name)
            if lost:
                unknown_links.add(el.child)
        return placed

    def joint_states(self, js: dict, t_ns: int) -> Message:
        """sensor_msgs/JointState: ``<b>/kappa`` (1/m) and ``<b>/phi`` (rad) per reported
        bendable, then the movable rigid joints. ``velocity`` (1/m/s, rad/s) is derived from the
        state stream (:meth:`_rates`); NaN where unknown. Effort stays empty (not measured)."""
        self._measure(js)
        names: list[str] = []
        pos: list[float] = []
        vel: list[float] = []
        t = js.get("t")
        for i, name in enumerate(js.get("names", [])):
            k, p = js["kappa"][i], js["phi"][i]
            names += [f"{name}/kappa", f"{name}/phi"]
            kf = float("nan") if k is None else float(k)
            pf = float("nan") if p is None else float(p)
            pos += [kf, pf]
            flags = js.get("valid") or []
            valid = bool(flags[i]) if i < len(flags) else True
            vel += self._rates(name, t, kf, pf, valid)
        for name, v in (js.get("rigid") or {}).items():
            if isinstance(v, dict) and v.get("position") is not None:
                names.append(name)
                pos.append(float(v["position"]))
                rate = v.get("velocity")
                vel.append(float(rate) if isinstance(rate, int | float) else float("nan"))
        msg = {"header": _header(t_ns, self.root), "name": names, "position": pos,
               "velocity": vel, "effort": []}  # fmt: skip
        return Message("/joint_states", TOPICS["/joint_states"], msg, t_ns)

    def _rates(self, name: str, t: Any, kappa: float, phi: float, valid: bool) -> list[float]:
        """(κ̇ 1/m/s, φ̇ rad/s) of one bendable: backward difference between this and the
        previous measured sample of the daemon's state stream, on the daemon's clock ``t`` (s).
        Unknown (NaN) for the first sample, after a gap over VELOCITY_MAX_GAP_S, for an invalid
        sample, and φ̇ while either κ is below PHI_RATE_MIN_KAPPA (φ undefined when straight)."""
        nan = float("nan")
        ok = valid and isinstance(t, int | float) and math.isfinite(kappa) and math.isfinite(phi)
        prev = self._prev.get(name)
        self._prev[name] = (float(t), kappa, phi) if ok else None  # type: ignore[arg-type]
        if not ok or prev is None:
            return [nan, nan]
        dt = float(t) - prev[0]
        if not 0.0 < dt <= VELOCITY_MAX_GAP_S:
            return [nan, nan]
        k_rate = (kappa - prev[1]) / dt
        if min(kappa, prev[1]) < PHI_RATE_MIN_KAPPA:
            return [k_rate, nan]
        return [k_rate, math.remainder(phi - prev[2], 2.0 * math.pi) / dt]

    def joint_positions(self, js: dict) -> dict[str, float]:
        """The movable joints of the exported URDF for an API joint_states message (rad / m):
        each bendable's at its last measured pose; none for a bendable never measured."""
        coords, rigid, _ = self._coords(js)
        out = dict(rigid)
        for name, mimic in self.kin.mimics.items():  # follows its master (ucrdf/fk.py)
            out[name] = mimic.position(rigid.get(mimic.joint, 0.0))
        for name, model in self.kin.models.items():
            if name not in self._measured:
                continue
            angles, twist = subdivision_angles(model, coords[name], self.subdivisions)
            for k, (a, b) in enumerate(angles):
                out[f"{name}_prb{k}_rx"] = a
                out[f"{name}_prb{k}_ry"] = b
            out[f"{name}_prb_twist"] = twist
        return out

    def tf(self, js: dict, t_ns: int) -> Message:
        """tf2_msgs/TFMessage: parent -> child of every movable joint of the exported URDF, a
        bendable's at its last measured pose; none of a bendable never measured (its child
        links have no transform to the root until it is)."""
        q = self.joint_positions(js)
        skip: set[str] = set()
        for name, joints in self._own_joints.items():
            if name not in self._measured:
                skip |= joints
        out = []
        for j in self.movable:
            if j.name in skip:
                continue
            t = j.origin.copy()
            v = q.get(j.name, 0.0)
            if j.type in ("revolute", "continuous"):
                m = np.eye(4)
                m[:3, :3] = axis_rotation(j.axis, v)
                t = t @ m
            elif j.type == "prismatic":
                m = np.eye(4)
                m[:3, 3] = j.axis * v
                t = t @ m
            out.append({"header": _header(t_ns, j.parent), "child_frame_id": j.child,
                        "transform": _transform(t)})  # fmt: skip
        return Message("/tf", TOPICS["/tf"], {"transforms": out}, t_ns)

    def arcs(self, js: dict, t_ns: int, samples: int = 24) -> Message:
        """visualization_msgs/MarkerArray: one LINE_STRIP per bendable along its true backbone
        (root frame), as wide as the segment's backbone (at least 5 mm), at its last measured
        pose: ARC_COLOR when measured in ``js``, STALE_COLOR when not. No marker for a bendable
        not placed yet (it, or one between it and the root, never measured)."""
        coords, rigid, fresh = self._coords(js)
        placed = self._placed()
        frames = self.kin.fk_coordinates(coords, rigid)
        markers = []
        for i, (name, model) in enumerate(self.kin.models.items()):
            if name not in placed:
                continue
            b = self.robot.bendables[name]
            base = frames[b.parent] @ b.origin.matrix()
            along = frames_along(model, coords[name], np.linspace(0.0, model.length, samples))
            xyz = (base @ along[:, :, 3].T).T
            pts = [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in xyz]
            width = max(2.0 * b.model.backbone.radius, 0.005)
            markers.append({
                "header": _header(t_ns, self.root), "ns": "ucr/arcs", "id": i,
                "type": LINE_STRIP, "action": 0, "pose": {"orientation": {"w": 1.0}},
                "scale": {"x": width, "y": 0.0, "z": 0.0},
                "color": dict(ARC_COLOR if name in fresh else STALE_COLOR),
                "frame_locked": False, "points": pts, "text": name,
            })  # fmt: skip
        return Message("/ucr/arcs", TOPICS["/ucr/arcs"], {"markers": markers}, t_ns)

    # -- status, events, goals -----------------------------------------------------------------
    def segments(self, status: dict, topology: dict | None, t_ns: int) -> Message:
        """diagnostic_msgs/DiagnosticArray: one status per bendable (OK measured and controlled,
        WARN not valid this cycle, STALE not on the chain) with κ, φ, uid, firmware."""
        js = status.get("joint_states") or {}
        found = {s.get("bendable"): s for s in (topology or {}).get("segments", [])}
        out = []
        for name in self.bendables:
            st, seg = js.get(name), found.get(name, {})
            if st is None:
                level, text = 3, "not on the chain"
            elif st.get("valid"):
                level, text = 0, "ok"
            else:
                level, text = 1, "no valid state this cycle"
            values = {"state": status.get("state", ""), "kappa_1_per_m": (st or {}).get("kappa"),
                      "phi_rad": (st or {}).get("phi"), "uid": seg.get("uid"),
                      "position": seg.get("position"), "fw_version": seg.get("fw_version"),
                      "controlled": seg.get("controlled")}  # fmt: skip
            out.append({"level": level, "name": f"ucr/{name}", "message": text,
                        "hardware_id": str(seg.get("uid") or ""),
                        "values": _key_values(values)})  # fmt: skip
        msg = {"header": _header(t_ns, ""), "status": out}
        return Message("/ucr/segments", TOPICS["/ucr/segments"], msg, t_ns)

    @staticmethod
    def loop_stats(stats: dict, t_ns: int) -> Message:
        """diagnostic_msgs/DiagnosticArray with one status ``ucr/loop``: every number of the
        daemon's ``loop_stats`` flattened to ``key.sub`` = value (µs, counts)."""
        flat = _flatten(stats)
        level = 1 if (stats.get("overruns") or 0) > 0 else 0
        status = {"level": level, "name": "ucr/loop", "message": f"{stats.get('cycles')} cycles",
                  "hardware_id": "", "values": _key_values(flat)}  # fmt: skip
        msg = {"header": _header(t_ns, ""), "status": [status]}
        return Message("/ucr/loop_stats", TOPICS["/ucr/loop_stats"], msg, t_ns)

    @staticmethod
    def event(ev: dict, t_ns: int) -> list[Message]:
        """An API event or topology message: rcl_interfaces/Log on /rosout (for log viewers) and
        the full JSON on /ucr/events (lossless)."""
        name = str(ev.get("event") or ev.get("kind") or "event")
        text = str(ev.get("message") or ev.get("reason") or name)
        level = event_level(name)
        log = {"stamp": _header(t_ns)["stamp"], "level": level, "name": f"ucr.{name}",
               "msg": text, "file": "", "function": "", "line": 0}  # fmt: skip
        return [
            Message("/rosout", TOPICS["/rosout"], log, t_ns),
            _string("/ucr/events", json.dumps(ev, sort_keys=True, default=str), t_ns),
        ]

    @staticmethod
    def goal(status: dict, t_ns: int, done: bool) -> Message:
        """A trajectory goal's status as JSON: on /ucr/trajectory/goals when first seen, on
        /ucr/trajectory/results when it ended (succeeded, aborted, canceled)."""
        topic = "/ucr/trajectory/results" if done else "/ucr/trajectory/goals"
        return _string(topic, json.dumps(status, sort_keys=True, default=str), t_ns)


class CommandedGoals:
    """Puts a goal's waypoints back together from the daemon's events: ``goal_accepted`` carries
    the first EVENT_MAX_WAYPOINTS of them (host.motion.commanded), ``goal_waypoints`` parts 2 ..
    ``parts`` the rest, in order. :meth:`feed` takes every event and returns what to record:
    the whole ``goal_accepted`` event once its last part came (for :func:`commanded`), and a
    ``goal_waypoints_incomplete`` event (for /ucr/events, where replay finds it) for a goal one
    of whose parts was lost — a later part of it, or the end of the recording (:meth:`finish`),
    came before the missing part; nothing of such a goal goes to /ucr/trajectory/commanded.
    Goals are kept apart by id (two controllers' goals may interleave)."""

    def __init__(self) -> None:
        self._open: dict[str, tuple[dict, list, int]] = {}  # goal -> (head, waypoints, next part)
        self._lost: set[str] = set()  # goals already reported incomplete

    def feed(self, ev: dict) -> tuple[dict | None, list[dict]]:
        """(the complete goal_accepted event or None, incomplete-goal events to record)."""
        name, goal = ev.get("event"), str(ev.get("goal"))
        lost: list[dict] = []
        if name == "goal_accepted":
            wps = ev.get("waypoints")
            parts = ev.get("parts", 1)
            if not isinstance(wps, list) or not isinstance(parts, int):
                return None, lost  # an older daemon's waypoints_omitted: replay refuses it
            if parts <= 1:
                return ev, lost
            self._open[goal] = (ev, list(wps), 2)
            return None, lost
        if name != "goal_waypoints":
            return None, lost
        entry = self._open.get(goal)
        wps = ev.get("waypoints")
        if entry is None:  # its start was lost, or came before the recording began
            if goal in self._lost:
                return None, lost
            self._lost.add(goal)
            n = ev.get("parts", "?")
            return None, [_incomplete(goal, ev.get("t"), "?", "?",
                                      f"its goal_accepted was not recorded; part "
                                      f"{ev.get('part')} of {n} came")]  # fmt: skip
        head, acc, want = entry
        if ev.get("part") != want or not isinstance(wps, list):
            return None, self._lose(f"part {want} was lost", only=goal)
        acc.extend(wps)
        if want < head.get("parts", 1):
            self._open[goal] = (head, acc, want + 1)
            return None, lost
        del self._open[goal]
        return {**head, "waypoints": acc, "part": 1, "parts": 1}, lost

    def finish(self) -> list[dict]:
        """Incomplete-goal events for the goals still waiting for parts (the recording ends)."""
        return self._lose("the recording ended first")

    def _lose(self, why: str, only: str | None = None) -> list[dict]:
        """Give up the goals (or goal ``only``) still waiting for parts."""
        out = []
        for goal, (head, acc, _) in list(self._open.items()):
            if only is not None and goal != only:
                continue
            del self._open[goal]
            self._lost.add(goal)
            out.append(_incomplete(goal, head.get("t"), len(acc), head.get("waypoint_count"), why))
        return out


def _incomplete(goal: str, t: Any, received: Any, count: Any, why: str) -> dict:
    return {
        "kind": "event", "event": "goal_waypoints_incomplete", "goal": goal, "t": t,
        "waypoints_received": received, "waypoint_count": count,
        "message": f"goal {goal}: {received} of {count} waypoints recorded ({why}): its "
        "commanded trajectory is not in the recording",
    }  # fmt: skip


def commanded(ev: dict, root: str, t_ns: int) -> Message | None:
    """trajectory_msgs/JointTrajectory of a ``goal_accepted`` event (the waypoints a goal was
    sent with, before retiming): joints ``<b>/kappa`` (1/m), ``<b>/phi`` (rad) for every bendable
    of the controller, as ``ucr zenoh`` takes commands. ``ev`` is whole (:class:`CommandedGoals`
    puts a long goal's parts together). None when the event carries no waypoints (an older
    daemon's ``waypoints_omitted``)."""
    joints, wps = ev.get("joints"), ev.get("waypoints")
    if not isinstance(joints, list) or not isinstance(wps, list):
        return None
    names = [f"{j}/{v}" for j in joints for v in ("kappa", "phi")]
    points = []
    for t, pos in wps:
        flat: list[float] = []
        for kx, ky in pos:
            flat += [math.hypot(kx, ky), math.atan2(ky, kx)]
        ns = round(float(t) * 1e9)
        points.append({"positions": flat, "time_from_start": {
            "sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}})  # fmt: skip
    msg = {"header": _header(t_ns, root), "joint_names": names, "points": points}
    topic = "/ucr/trajectory/commanded"
    return Message(topic, TOPICS[topic], msg, t_ns)


def _finite(v: Any) -> bool:
    """A real number (not None, not a bool, not NaN or infinite)."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(d, list):
        if all(not isinstance(v, dict | list) for v in d):
            out[prefix] = json.dumps(d)
        else:
            for i, v in enumerate(d):
                out.update(_flatten(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = d
    return out


def _key_values(values: dict[str, Any]) -> list[dict[str, str]]:
    return [{"key": k, "value": "" if v is None else str(v)} for k, v in values.items()]
