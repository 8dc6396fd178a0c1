"""Commands from ROS 2: ``trajectory_msgs/msg/JointTrajectory`` as the ros2_control joint trajectory
controller takes it on ``<controller>/joint_trajectory``, turned into the daemon's
``trajectory.send`` (docs/api.md). The daemon checks limits and timing, exactly as for any other
client; nothing here decides what the robot may do.

Joint names are ``<bendable>/kappa`` (1/m) and ``<bendable>/phi`` (rad). A bendable the message
names must have both; a bendable it does not name keeps its target (the daemon's rule for a
segment left out of a waypoint). A message with no points stops what this bridge's commands
started (the JTC's convention for an empty trajectory): the newest goal sent from the topic or
the FollowJointTrajectory action, if it still runs (:class:`SentGoals`). ``header.stamp`` is not
used: a trajectory starts when the daemon accepts it; velocities, accelerations and efforts are
ignored (the daemon interpolates positions and retimes to ``kappa_rate_max``).

A message larger than the largest trajectory the daemon would take (:func:`max_trajectory_bytes`:
its 10 000 waypoints for this robot's joints) is refused by its size, before it is decoded.
"""

from __future__ import annotations

import math
import sys
import threading
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
        self._notes: list[str] = []  # refusals made on the Zenoh thread, reported by the worker
        self._stop = threading.Event()
        self.accepted = 0
        self.refused = 0
        self._thread = threading.Thread(target=self._run, name="ucr-zenoh-commands", daemon=True)
        self._thread.start()

    @property
    def max_bytes(self) -> int:
        """The largest message taken (:func:`max_trajectory_bytes` for this robot)."""
        return max_trajectory_bytes(len(self.bendables))

    def on_message(self, data: bytes, attachment: Any = None) -> None:
        """Zenoh callback: keep the message for the worker (replacing one still waiting); one
        too large to be a trajectory the daemon takes is refused here, never decoded."""
        limit = self.max_bytes
        with self._lock:
            if len(data) > limit:
                self.refused += 1
                if len(self._notes) < 8:  # a flood of them is not a flood of log lines
                    self._notes.append(
                        f"JointTrajectory refused unread: {_size(len(data))}, more than the "
                        f"{_size(limit)} of the largest trajectory the daemon takes "
                        f"({MAX_POINTS} waypoints of {2 * len(self.bendables)} joints)"
                    )
            else:
                self._data = data
                self._att = attachment
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
            for text in notes:
                self.report(40, text)
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
        try:
            points = to_waypoints(msg, self.bendables)
            with on_behalf_of(f"zenoh {who}"):  # the daemon's audit line names it too
                goal = self.client.send_trajectory(points, wait=False, controller=self.controller)
            self.sent.note(goal, "topic")
            audit("joint_trajectory", who, goal=goal, points=len(points))
            self.accepted += 1
            self.report(20, f"JointTrajectory accepted: goal {goal}, {len(points)} points")
        except CommandError as exc:
            self.refused += 1
            self.report(40, f"JointTrajectory refused: {exc}")
        except ApiError as exc:
            self.refused += 1
            self.report(40, f"JointTrajectory refused{daemon_said(exc)}")

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
