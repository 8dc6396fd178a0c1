"""Commands from ROS 2: ``trajectory_msgs/msg/JointTrajectory`` as the ros2_control joint trajectory
controller takes it on ``<controller>/joint_trajectory``, turned into the daemon's
``trajectory.send`` (docs/api.md). The daemon checks limits and timing, exactly as for any other
client; nothing here decides what the robot may do.

Joint names are ``<bendable>/kappa`` (1/m) and ``<bendable>/phi`` (rad). A bendable the message
names must have both; a bendable it does not name keeps its target (the daemon's rule for a
segment left out of a waypoint). A message with no points stops what this bridge's commands
started: the newest goal sent from the topic or the FollowJointTrajectory action, if it still
runs (:class:`SentGoals`). That is ROS 1's joint trajectory controller's convention; ROS 2's JTC
rejects an empty trajectory, but a topic has no cancel of its own and this is the one way a
publisher can stop what it started. ``header.stamp`` is not used: a trajectory starts when the
daemon accepts it; velocities, accelerations and efforts are ignored (the daemon interpolates
positions and retimes to ``kappa_rate_max``).

A first point at ``time_from_start`` 0 is the start state (MoveIt plans from it; ros2_control's
JTC takes it): the daemon's goals always start from where the robot is and take only times > 0,
so it is not sent (:func:`drop_start_state`), with a warning when it is not where the robot is.

Only a message carrying rmw_zenoh's attachment (the publisher's GID, named in the audit) is
taken: a plain Zenoh ``put`` on the topic is refused, as rmw_zenoh itself drops it.

A message larger than the largest trajectory the daemon would take (:func:`max_trajectory_bytes`:
its 10 000 waypoints for this robot's joints) is refused by its size, before it is decoded.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

from host.api.client_behalf import on_behalf_of
from host.api.schema import MAX_POINTS
from interop import ros2

TRAJECTORY_TYPE = "trajectory_msgs/msg/JointTrajectory"
_NS_PER_S = 1_000_000_000
# CDR bytes a JointTrajectory may spend besides its points (header and frame_id, joint_names) and
# a FollowJointTrajectory goal besides its trajectory (goal id, tolerances)
ENVELOPE_BYTES = 64 * 1024
#: 1/m, Euclidean in (kx, ky): how far a start state (a first point at time 0) may lie from the
#: measured state without a warning: the daemon JTC's default goal_tolerance
START_TOLERANCE = 0.05
#: s without a publisher-less command that end a burst of them: the next one warns again
UNATTRIBUTED_QUIET_S = 10.0


def max_trajectory_bytes(n_bendables: int) -> int:
    """The CDR size of the largest JointTrajectory the daemon could take for ``n_bendables``:
    its :data:`~host.api.schema.MAX_POINTS` waypoints, each point with positions, velocities,
    accelerations and efforts for all ``2 * n_bendables`` joints (kappa, phi), plus
    :data:`ENVELOPE_BYTES`. A point is at most 4 sequences (≤ 11 bytes of length and alignment
    each, 8 per double) and a Duration (≤ 11 bytes with alignment): ≤ 64 + 32 × joints bytes."""
    joints = 2 * max(1, n_bendables)
    return ENVELOPE_BYTES + MAX_POINTS * (64 + 32 * joints)


def _size(n: int) -> str:
    return f"{n / 1e6:.2f} MB ({n} bytes)"


def daemon_said(exc: Any) -> str:
    """The end of "… refused" for a failed daemon call (an ApiError): `` by the daemon (code):
    message``, or ``: the daemon is not connected (…)`` (a broken or absent connection is no
    refusal by the daemon)."""
    from host.api.client import ApiConnectionError  # noqa: PLC0415

    if isinstance(exc, ApiConnectionError):
        return f": the daemon is not connected ({exc.message})"
    return f" by the daemon ({exc.code}): {exc.message}"


def audit(op: str, who: str, **fields: Any) -> None:
    """One audit line (``ucr.audit``, as the daemon's and the view's) for a command this bridge
    sent on behalf of a ROS 2 entity: the daemon's own line names only the bridge's token, so
    this one names the ROS side (``who``: the publisher's GID, the action goal's UUID)."""
    from host.api.audit import audit_field, audit_logger  # noqa: PLC0415

    rest = " ".join(f"{k}={audit_field(v)}" for k, v in fields.items())
    audit_logger().info("zenoh %s op=%s %s", who, audit_field(op), rest)


class CommandError(ValueError):
    """A JointTrajectory ucr refuses before it reaches the daemon (the reason says why)."""


def to_waypoints(msg: Any, bendables: list[str]) -> list[dict]:
    """The daemon's waypoints for a decoded JointTrajectory; CommandError if malformed."""
    names = list(msg.joint_names)
    if len(set(names)) != len(names):
        raise CommandError(f"joint_names repeats a name: {names}")
    known = set(bendables)
    slots: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        bendable, sep, axis = name.rpartition("/")
        if not sep or bendable not in known or axis not in ("kappa", "phi"):
            raise CommandError(
                f"unknown joint {name!r}: joints are <bendable>/kappa and <bendable>/phi with "
                f"bendables {sorted(known)}"
            )
        slots.setdefault(bendable, {})[axis] = i
    for bendable, axes in slots.items():
        if set(axes) != {"kappa", "phi"}:
            raise CommandError(
                f"{bendable}: a trajectory must name both {bendable}/kappa and {bendable}/phi"
            )
    out = []
    for k, pt in enumerate(msg.points):
        pos = list(pt.positions)
        if len(pos) != len(names):
            raise CommandError(f"points[{k}]: {len(pos)} positions for {len(names)} joint_names")
        if not all(math.isfinite(v) for v in pos):
            raise CommandError(f"points[{k}]: positions must be finite")
        d = pt.time_from_start
        t = d.sec + d.nanosec / _NS_PER_S
        segments = {b: {"kappa": pos[a["kappa"]], "phi": pos[a["phi"]]} for b, a in slots.items()}
        out.append({"time_from_start": t, "segments": segments})
    return out


def _kxy(kappa: float, phi: float) -> tuple[float, float]:
    return kappa * math.cos(phi), kappa * math.sin(phi)


def start_deviation(start: dict, measured: dict) -> list[str]:
    """What of a start state (a waypoint's ``segments``) lies farther than
    :data:`START_TOLERANCE` from ``measured`` (the daemon's ``status()["joint_states"]``): one
    phrase per segment, empty when all are within. Compared in (kx, ky), as the daemon's
    tolerances: phi means nothing at kappa 0."""
    out = []
    for name, target in start.items():
        m = measured.get(name) or {}
        if not m.get("valid", True) or "kappa" not in m or "phi" not in m:
            out.append(f"{name} (no valid measured state to compare with)")
            continue
        tx, ty = _kxy(target["kappa"], target["phi"])
        mx, my = _kxy(float(m["kappa"]), float(m["phi"]))
        d = math.hypot(tx - mx, ty - my)
        if d > START_TOLERANCE:
            out.append(f"{name} {d:.3g} 1/m away")
    return out


def drop_start_state(points: list[dict], measured: Any) -> tuple[list[dict], str | None]:
    """The waypoints to send and, if a start state was dropped far from the robot, a warning.

    A first point at ``time_from_start`` 0 is the start state of the trajectory (MoveIt puts
    the robot's state there; ros2_control's JTC accepts it). The daemon refuses a waypoint at
    0 (``points[0].time_from_start: must be > 0``): it is the state the goal starts from, which
    the daemon takes from the robot itself. So that point is not sent; when it lies farther than
    :data:`START_TOLERANCE` from the measured state (``measured()``, the daemon's
    ``joint_states``; asked only then) the warning says the trajectory starts from the measured
    state instead: never a jump to it, never silently. A later point at 0 is no start state:
    CommandError, naming it by its index in the message."""
    if not points or points[0]["time_from_start"] != 0:
        return points, None
    rest = points[1:]
    if not rest:
        raise CommandError(
            "only a start state (points[0] at time_from_start 0): no point to move to"
        )
    if rest[0]["time_from_start"] <= 0:
        raise CommandError(
            "points[1].time_from_start: must be > 0 (only points[0], the start state, may be 0)"
        )
    try:
        far = start_deviation(points[0]["segments"], measured())
    except Exception as exc:  # noqa: BLE001 - an ApiError: the send then says more
        far = [f"the measured state could not be read ({exc})"]
    if not far:
        return rest, None
    return rest, (
        f"points[0] (time_from_start 0, the start state) is not where the robot is "
        f"({'; '.join(far)}; tolerance {START_TOLERANCE:g} 1/m): it is not sent, the trajectory "
        "starts from the measured state instead (no jump to points[0])"
    )


#: said after a daemon's refusal of a trajectory whose start state was not sent: its indices
START_DROPPED = (
    " (points[0], the start state at time_from_start 0, was not sent: the daemon's points[i] is "
    "the message's points[i+1])"
)


class SentGoals:
    """The daemon goals this bridge's commands started (JointTrajectory topic and
    FollowJointTrajectory action), newest last: what an empty JointTrajectory stops. A new goal
    of either replaces the running one in the daemon, so the newest is the one that may run."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last: tuple[str, str] | None = None

    def note(self, goal: str, source: str) -> None:
        """``goal`` (the daemon's id) was accepted from ``source`` (``topic``, ``action``)."""
        with self._lock:
            self._last = (str(goal), source)

    def last(self) -> tuple[str, str] | None:
        """(goal id, source) of the newest goal, or None if none was sent."""
        with self._lock:
            return self._last


class TrajectoryCommands:
    """Receives JointTrajectory CDR on a Zenoh thread; a worker thread sends it to the daemon.

    Only the newest message waits (a newer one replaces one not yet sent, as a new JTC goal
    replaces the running one); the Zenoh thread never waits for the daemon. ``report(level,
    text)`` tells ROS 2 (``/rosout``) and the console what happened to each message. ``sent`` is
    shared with the FollowJointTrajectory action: an empty message stops the newest goal of
    either."""

    def __init__(
        self,
        client: Any,
        bendables: list[str],
        *,
        controller: str | None = None,
        report: Callable[[int, str], None] | None = None,
        sent: SentGoals | None = None,
    ) -> None:
        self.client = client
        self.bendables = list(bendables)
        self.controller = controller
        self.report = report or (lambda level, text: print(f"ucr zenoh: {text}", file=sys.stderr))
        self.sent = sent if sent is not None else SentGoals()
        self._codec = ros2.codec(TRAJECTORY_TYPE)
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._data: bytes | None = None  # the newest message not yet handled
        self._att: Any = None  # its rmw_zenoh attachment (the publisher's GID), if any
        # refusals made on the Zenoh thread, (level, text), reported by the worker
        self._notes: list[tuple[int, str]] = []
        self._stop = threading.Event()
        self.accepted = 0
        self.refused = 0
        self.unattributed = 0  # refused: no (valid) rmw_zenoh attachment, no publisher GID
        self._burst_at: float | None = None  # last publisher-less message of the current burst
        self._thread = threading.Thread(target=self._run, name="ucr-zenoh-commands", daemon=True)
        self._thread.start()

    @property
    def max_bytes(self) -> int:
        """The largest message taken (:func:`max_trajectory_bytes` for this robot)."""
        return max_trajectory_bytes(len(self.bendables))

    def on_message(self, data: bytes, attachment: Any = None) -> None:
        """Zenoh callback: keep the message for the worker (replacing one still waiting); one
        without rmw_zenoh's attachment (:meth:`unattributed`) or too large to be a trajectory the
        daemon takes is refused here, never decoded."""
        if attachment is None:
            self.unattributed_message("no rmw_zenoh attachment")
            return
        limit = self.max_bytes
        with self._lock:
            self._burst_at = None  # a ROS 2 publisher's message ends a publisher-less burst
            if len(data) > limit:
                self.refused += 1
                if len(self._notes) < 8:  # a flood of them is not a flood of log lines
                    text = (
                        f"JointTrajectory refused unread: {_size(len(data))}, more than the "
                        f"{_size(limit)} of the largest trajectory the daemon takes "
                        f"({MAX_POINTS} waypoints of {2 * len(self.bendables)} joints)"
                    )
                    self._notes.append((40, text))
            else:
                self._data = data
                self._att = attachment
        self._wake.set()

    def unattributed_message(self, why: str) -> None:
        """A message without a valid rmw_zenoh attachment (Zenoh thread): refused, never sent.
        Without the publisher's GID the audit could not say who moved the robot (docs/ros2.md
        "Who sent it"), and no ROS 2 publisher sends one (rmw_zenoh's own subscriptions drop
        them): it is a plain Zenoh ``put``. Each is counted; a WARN is said once per burst (the
        first after a ROS 2 publisher's message, or after :data:`UNATTRIBUTED_QUIET_S` s without
        one), not per message: a flood of puts is not a flood of log lines."""
        now = time.monotonic()
        with self._lock:
            self.refused += 1
            self.unattributed += 1
            new_burst = self._burst_at is None or now - self._burst_at > UNATTRIBUTED_QUIET_S
            self._burst_at = now
            if new_burst:
                text = (
                    f"JointTrajectory refused ({why}): no publisher GID to name in the audit, "
                    "so not a ROS 2 publisher's message (a plain Zenoh put); nothing sent. More "
                    "such messages are refused without a word until a ROS 2 publisher's message "
                    f"or {UNATTRIBUTED_QUIET_S:g} s without one ({self.unattributed} refused "
                    "so far)"
                )
                self._notes.append((30, text))
        self._wake.set()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._wake.wait(0.2):
                continue
            with self._lock:
                self._wake.clear()
                data, self._data = self._data, None
                att, self._att = self._att, None
                notes, self._notes = self._notes, []
            for level, text in notes:
                self.report(level, text)
            if data is not None:
                self.handle(data, att)

    def handle(self, data: bytes, attachment: Any = None) -> None:
        """Decode, check and send one JointTrajectory (runs on the worker thread)."""
        gid = getattr(attachment, "gid", None)
        who = f"publisher={gid.hex()}" if gid else "publisher=unknown"
        from host.api.client import ApiError  # noqa: PLC0415

        try:
            msg = self._codec.decode(data)
        except Exception as exc:  # noqa: BLE001 - any byte from the network is untrusted
            self.refused += 1
            self.report(40, f"JointTrajectory refused: not decodable CDR ({type(exc).__name__})")
            return
        if not msg.points:
            audit("joint_trajectory.stop", who)
            self.stop_sent(who)
            return
        dropped = False
        try:
            points = to_waypoints(msg, self.bendables)
            to_send, warning = drop_start_state(points, self._measured)
            dropped = len(to_send) < len(points)
            if warning:
                self.report(30, f"JointTrajectory: {warning}")
            with on_behalf_of(f"zenoh {who}"):  # the daemon's audit line names it too
                goal = self.client.send_trajectory(to_send, wait=False, controller=self.controller)
            self.sent.note(goal, "topic")
            audit("joint_trajectory", who, goal=goal, points=len(to_send))
            self.accepted += 1
            self.report(20, f"JointTrajectory accepted: goal {goal}, {len(to_send)} points"
                        + (" after the start state" if dropped else ""))  # fmt: skip
        except CommandError as exc:
            self.refused += 1
            self.report(40, f"JointTrajectory refused: {exc}")
        except ApiError as exc:
            self.refused += 1
            said = daemon_said(exc) + (START_DROPPED if dropped else "")
            self.report(40, f"JointTrajectory refused{said}")

    def _measured(self) -> dict:
        """The daemon's measured joint states (asked only for a start state to compare)."""
        return self.client.status().get("joint_states") or {}

    def stop_sent(self, who: str | None = None) -> None:
        """An empty JointTrajectory: cancel the newest goal this bridge's commands started, if it
        still runs, and say what happened (nothing to cancel is said as such). ``who``: the
        publisher that sent it (the daemon's audit line names it)."""
        from host.api.client import ApiError  # noqa: PLC0415

        what = "empty JointTrajectory"
        last = self.sent.last()
        if last is None:
            self.report(20, f"{what}: nothing to cancel (this bridge has started no goal)")
            return
        goal, source = last
        try:
            with on_behalf_of(None if who is None else f"zenoh {who}"):
                st = self.client.cancel(goal)
        except ApiError as exc:
            if exc.code == "not_found":
                self.report(
                    20, f"{what}: nothing to cancel (goal {goal} is no longer known to the daemon)"
                )
            else:
                self.report(40, f"{what}: cancel of goal {goal} refused{daemon_said(exc)}")
            return
        if st.get("canceled"):
            self.report(
                20,
                f"{what}: goal {goal} (from the {source}) canceled: the robot decelerates to rest "
                "and holds",
            )
        else:
            self.report(
                20,
                f"{what}: nothing to cancel (goal {goal} from the {source} already "
                f"{st.get('state') or 'ended'})",
            )

    def close(self) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=5)
