"""Commands from ROS 2: ``trajectory_msgs/msg/JointTrajectory`` as the ros2_control joint trajectory
controller takes it on ``<controller>/joint_trajectory``, turned into the daemon's
``trajectory.send`` (docs/api.md). The daemon checks limits and timing, exactly as for any other
client; nothing here decides what the robot may do.

Joint names are ``<bendable>/kappa`` (1/m) and ``<bendable>/phi`` (rad). A bendable the message
names must have both; a bendable it does not name keeps its target (the daemon's rule for a
segment left out of a waypoint). A message with no points cancels the goal this bridge sent last
(what the JTC does with an empty trajectory). ``header.stamp`` is not used: a trajectory starts
when the daemon accepts it; velocities, accelerations and efforts are ignored (the daemon
interpolates positions and retimes to ``kappa_rate_max``).
"""

from __future__ import annotations

import math
import queue
import sys
import threading
from collections.abc import Callable
from typing import Any

from interop import ros2

TRAJECTORY_TYPE = "trajectory_msgs/msg/JointTrajectory"
_NS_PER_S = 1_000_000_000


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


class TrajectoryCommands:
    """Receives JointTrajectory CDR on a Zenoh thread; a worker thread sends it to the daemon.

    Only the newest message waits (a newer one replaces one not yet sent, as a new JTC goal
    replaces the running one); the Zenoh thread never waits for the daemon. ``report(level,
    text)`` tells ROS 2 (``/rosout``) and the console what happened to each message."""

    def __init__(
        self,
        client: Any,
        bendables: list[str],
        *,
        controller: str | None = None,
        report: Callable[[int, str], None] | None = None,
    ) -> None:
        self.client = client
        self.bendables = list(bendables)
        self.controller = controller
        self.report = report or (lambda level, text: print(f"ucr zenoh: {text}", file=sys.stderr))
        self._codec = ros2.codec(TRAJECTORY_TYPE)
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=1)
        self._stop = threading.Event()
        self._goal: str | None = None
        self.accepted = 0
        self.refused = 0
        self._thread = threading.Thread(target=self._run, name="ucr-zenoh-commands", daemon=True)
        self._thread.start()

    def on_message(self, data: bytes, attachment: Any = None) -> None:
        """Zenoh callback: queue the message (replacing one still waiting)."""
        while True:
            try:
                self._queue.put_nowait(data)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._queue.get(timeout=0.2)
            except queue.Empty:
                continue
            self.handle(data)

    def handle(self, data: bytes) -> None:
        """Decode, check and send one JointTrajectory (runs on the worker thread)."""
        from host.api.client import ApiError  # noqa: PLC0415

        try:
            msg = self._codec.decode(data)
        except Exception as exc:  # noqa: BLE001 - any byte from the network is untrusted
            self.refused += 1
            self.report(40, f"JointTrajectory refused: not decodable CDR ({type(exc).__name__})")
            return
        try:
            if not msg.points:
                if self._goal is not None:
                    st = self.client.cancel(self._goal)
                    self.report(
                        20, f"empty JointTrajectory: goal {self._goal} canceled ({st.get('state')})"
                    )
                return
            points = to_waypoints(msg, self.bendables)
            self._goal = self.client.send_trajectory(points, wait=False, controller=self.controller)
            self.accepted += 1
            self.report(20, f"JointTrajectory accepted: goal {self._goal}, {len(points)} points")
        except CommandError as exc:
            self.refused += 1
            self.report(40, f"JointTrajectory refused: {exc}")
        except ApiError as exc:
            self.refused += 1
            self.report(40, f"JointTrajectory refused by the daemon ({exc.code}): {exc.message}")

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
