"""``control_msgs/action/FollowJointTrajectory`` served the way rmw_zenoh maps a ROS 2 action
(``<controller>/follow_joint_trajectory``, as ros2_control's joint trajectory controller names
it): three services and two topics under ``<action>/_action/``:

- ``send_goal`` (``…_SendGoal``): the goal's trajectory becomes one daemon goal through the API
  (``trajectory.send``; same limits, same retiming). Accepted when the daemon accepts it;
  refused (``accepted: false``, reason on ``/rosout``) when the message is malformed, has
  multi-DOF points, or the daemon refuses (beyond ``kappa_max``, manual control, …). A first
  point at time 0 (MoveIt's start state) is not sent
  (:func:`~interop.zenoh.commands.drop_start_state`).
- ``get_result`` (``…_GetResult``): answered when the goal ends: SUCCEEDED (``error_code``
  SUCCESSFUL); CANCELED for a goal canceled, or replaced by a newer goal (INVALID_GOAL and the
  daemon's reason: what ros2_control's JTC reports for a goal preempted by a new one); ABORTED
  with the daemon's reason in ``error_string`` and ``error_code`` PATH_TOLERANCE_VIOLATED /
  GOAL_TOLERANCE_VIOLATED for a tolerance abort (the daemon's ``abort.cause``), INVALID_GOAL
  otherwise (manual takeover, topology change, link loss). An unknown goal id: status UNKNOWN
  at once.
- ``cancel_goal`` (``action_msgs/srv/CancelGoal``) as action_msgs defines it: a goal id alone
  cancels that goal; a zero id and zero stamp all goals; a stamp all goals accepted at or before
  it, and with a goal id that goal too; through ``trajectory.cancel``.
- ``status`` (``action_msgs/msg/GoalStatusArray``, transient local, depth 1) on every change;
  ``feedback`` (``…_FeedbackMessage``) at ≤ 10 Hz while a goal runs: ``actual`` positions of the
  goal's joints and the time since it started (``desired`` and ``error`` left empty: the daemon
  does not publish its setpoint).

Tolerances and ``goal_time_tolerance`` of the goal are not used: the daemon's own limits and
tolerances apply (docs/ros2.md). Served only with ``--enable-commands``.

A request the services refuse before it is read (too large, not decodable, too many waiting; see
:class:`~interop.zenoh.node.RmwService`) still gets a response of its type: ``send_goal`` not
accepted, ``get_result`` status UNKNOWN with the reason, ``cancel_goal`` ERROR_REJECTED; the
reason goes to ``/rosout``.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from host.api.client_behalf import on_behalf_of
from interop import ros2
from interop.ros2 import actions, services
from interop.ros2.type_hash import action_type_hash, service_type_hash, type_hash
from interop.zenoh import rmw
from interop.zenoh.commands import (
    ENVELOPE_BYTES,
    START_DROPPED,
    CommandError,
    SentGoals,
    audit,
    daemon_said,
    drop_start_state,
    max_trajectory_bytes,
    to_waypoints,
)

ACTION = "control_msgs/action/FollowJointTrajectory"
CANCEL = "action_msgs/srv/CancelGoal"
STATUS_ARRAY = "action_msgs/msg/GoalStatusArray"
STATUS_QOS = rmw.Qos(durability=rmw.TRANSIENT_LOCAL, depth=1)  # rcl_action's status default
# action_msgs/msg/GoalStatus
UNKNOWN, ACCEPTED, EXECUTING, CANCELING, SUCCEEDED, CANCELED, ABORTED = range(7)
# control_msgs FollowJointTrajectory result error codes
SUCCESSFUL, INVALID_GOAL, PATH_TOLERANCE_VIOLATED, GOAL_TOLERANCE_VIOLATED = 0, -1, -4, -5
# action_msgs/srv/CancelGoal return codes
ERROR_NONE, ERROR_REJECTED, ERROR_UNKNOWN_GOAL_ID, ERROR_GOAL_TERMINATED = 0, 1, 2, 3
KEEP_FINISHED = 32  # finished goals whose result can still be asked for
TERMINAL = (SUCCEEDED, CANCELED, ABORTED)


@dataclass
class Goal:
    uuid: bytes
    daemon_id: str
    joints: list[str]
    accepted_ns: int
    status: int = EXECUTING
    error_code: int = SUCCESSFUL
    error_string: str = ""
    waiters: list[Callable[[dict], None]] = field(default_factory=list)


def result_of(state: str, reason: str, cause: str = "") -> tuple[int, int, str]:
    """(goal status, error code, error string) for a finished daemon goal; ``cause`` is the
    daemon's ``abort.cause`` (``path_tolerance``, ``goal_tolerance``, ``link_loss``, …)."""
    if state == "succeeded":
        return SUCCEEDED, SUCCESSFUL, ""
    if state == "canceled":
        return CANCELED, SUCCESSFUL, reason or "canceled"
    text = reason or state
    if cause == "replaced" and text.startswith("replaced by"):
        # a newer goal preempted it: the JTC's preempt_active_goal() sets such a goal CANCELED
        # with INVALID_GOAL ("Current goal cancelled due to new incoming action.")
        return CANCELED, INVALID_GOAL, text
    if cause == "path_tolerance":
        return ABORTED, PATH_TOLERANCE_VIOLATED, text
    if cause == "goal_tolerance":
        return ABORTED, GOAL_TOLERANCE_VIOLATED, text
    return ABORTED, INVALID_GOAL, text


def _stamp(t_ns: int) -> dict:
    return ros2.stamp(t_ns)


class FollowJointTrajectoryServer:
    """The action server of one daemon trajectory controller on an :class:`RmwNode`."""

    def __init__(
        self,
        node: Any,
        client: Any,
        bendables: list[str],
        *,
        controller: str,
        report: Callable[[int, str], None],
        period_s: float = 0.1,
        sent: SentGoals | None = None,
    ) -> None:
        self.client = client
        self.send_goal: Any = None  # declared below; the bendables setter sizes its requests
        self.bendables = list(bendables)
        self.controller = controller
        self.report = report
        self.period_s = period_s
        self.sent = sent if sent is not None else SentGoals()
        self._notes: list[str] = []  # refusals of the services, reported by the tracker thread
        self.name = f"{controller}/follow_joint_trajectory"
        self.goals: dict[bytes, Goal] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        base = actions.full_name(ACTION)
        prefix = f"{self.name}/_action"

        def refused(response: Callable[[str], dict]) -> Callable[[str], dict]:
            def refusal(why: str) -> dict:
                with self._lock:
                    if len(self._notes) < 8:  # a flood of them is not a flood of log lines
                        self._notes.append(why)
                return response(why)

            return refusal

        def srv(part: str, suffix: str, handler: Any, **kw: Any) -> Any:
            codecs = (
                actions.codec(ACTION, f"{part}_Request"),
                actions.codec(ACTION, f"{part}_Response"),
            )
            return node.service(
                f"{prefix}/{suffix}",
                f"{base}_{part}",
                handler,
                type_hash_=action_type_hash(ACTION, part),
                codecs=codecs,
                **kw,
            )

        self.send_goal = srv(
            "SendGoal",
            "send_goal",
            self._send_goal,
            refusal=refused(lambda why: {"accepted": False, "stamp": _stamp(time.time_ns())}),
            # the largest goal the daemon could take, as for the JointTrajectory topic (kept
            # in step with the robot by the bendables setter)
            max_request_bytes=self.max_request_bytes,
        )
        self.get_result = srv(
            "GetResult",
            "get_result",
            self._get_result,
            deferred=True,
            refusal=refused(
                lambda why: {
                    "status": UNKNOWN,
                    "result": {"error_code": INVALID_GOAL, "error_string": why},
                }
            ),
        )
        self.cancel_goal = node.service(
            f"{prefix}/cancel_goal",
            CANCEL,
            self._cancel_goal,
            type_hash_=service_type_hash(CANCEL),
            refusal=refused(lambda why: {"return_code": ERROR_REJECTED, "goals_canceling": []}),
        )
        self._cancel_codecs = services.codecs(CANCEL)
        self.feedback = node.publisher(
            f"{prefix}/feedback",
            f"{base}_FeedbackMessage",
            rmw.DEFAULT_QOS,
            action_type_hash(ACTION, "FeedbackMessage"),
        )
        self.status = node.publisher(f"{prefix}/status", STATUS_ARRAY, STATUS_QOS)
        self._fb_codec = actions.codec(ACTION, "FeedbackMessage")
        self._status_codec = ros2.codec(STATUS_ARRAY)
        self.action_fqn = self.send_goal.fqn.rsplit("/_action/", 1)[0]
        self._publish_status()
        self._thread = threading.Thread(target=self._track, name="ucr-zenoh-fjt", daemon=True)
        self._thread.start()

    @property
    def bendables(self) -> list[str]:
        """The robot's bendables: the joints a goal may name."""
        return self._bendables

    @bendables.setter
    def bendables(self, names: list[str]) -> None:
        """New bendables (the bridge reconnected to a daemon running another robot): the
        send_goal size bound follows them, as the topic's (:attr:`TrajectoryCommands.max_bytes`)
        does. It was fixed at start: after a switch to a robot with more bendables, goals the
        daemon would take were refused unread by the old robot's bound."""
        self._bendables = list(names)
        if self.send_goal is not None:
            self.send_goal.max_request_bytes = self.max_request_bytes

    @property
    def max_request_bytes(self) -> int:
        """The largest send_goal request taken: the largest trajectory the daemon could take for
        this robot plus :data:`ENVELOPE_BYTES` for the rest of the goal (tolerances, goal id)."""
        return max_trajectory_bytes(len(self._bendables)) + ENVELOPE_BYTES

    # ---------------------------------------------------------------- services
    def _send_goal(self, req: Any) -> dict:
        from host.api.client import ApiError  # noqa: PLC0415

        uuid = bytes(req.goal_id.uuid)
        now = time.time_ns()
        refuse = {"accepted": False, "stamp": _stamp(now)}
        goal = req.goal
        dropped = False
        try:
            if len(uuid) != 16:
                raise CommandError("goal_id must be 16 bytes")
            with self._lock:
                if uuid in self.goals:
                    raise CommandError("goal_id already used")
            if goal.multi_dof_trajectory.points or goal.multi_dof_trajectory.joint_names:
                raise CommandError("multi_dof_trajectory is not supported (no such joints)")
            if not goal.trajectory.points:
                raise CommandError("empty trajectory")
            points = to_waypoints(goal.trajectory, self.bendables)
            # MoveIt's first point is the start state at 0 s: not sent (the daemon starts from
            # where the robot is and refuses a time of 0), a warning if it is not where it is
            points, warning = drop_start_state(points, self._measured)
            dropped = len(points) < len(goal.trajectory.points)
            if warning:
                self.report(30, f"FollowJointTrajectory goal: {warning}")
            with on_behalf_of(f"zenoh goal_uuid={uuid.hex()}"):  # named in the daemon's audit
                daemon_id = self.client.send_trajectory(
                    points, wait=False, controller=self.controller
                )
        except CommandError as exc:
            self.report(40, f"FollowJointTrajectory goal refused: {exc}")
            return refuse
        except ApiError as exc:
            self.report(
                40,
                f"FollowJointTrajectory goal refused{daemon_said(exc)}"
                + (START_DROPPED if dropped else ""),
            )
            return refuse
        g = Goal(uuid, str(daemon_id), list(goal.trajectory.joint_names), now)
        self.sent.note(g.daemon_id, "action")
        audit("follow_joint_trajectory", f"goal_uuid={uuid.hex()}", goal=g.daemon_id,
              points=len(points))  # fmt: skip
        with self._lock:
            self.goals[uuid] = g
            self._forget_old()
        self.report(20, f"FollowJointTrajectory goal accepted: daemon goal {daemon_id}")
        self._publish_status()
        return {"accepted": True, "stamp": _stamp(now)}

    def _measured(self) -> dict:
        """The daemon's measured joint states (asked only for a start state to compare)."""
        return self.client.status().get("joint_states") or {}

    def _get_result(self, req: Any, respond: Callable[[dict], None]) -> None:
        uuid = bytes(req.goal_id.uuid)
        with self._lock:
            g = self.goals.get(uuid)
            if g is not None and g.status not in TERMINAL:
                g.waiters.append(respond)
                return
        if g is None:
            respond({"status": UNKNOWN, "result": {"error_code": 0, "error_string": ""}})
        else:
            respond(self._result(g))

    @staticmethod
    def _result(g: Goal) -> dict:
        return {
            "status": g.status,
            "result": {"error_code": g.error_code, "error_string": g.error_string},
        }

    def _cancel_goal(self, req: Any) -> dict:
        from host.api.client import ApiError  # noqa: PLC0415

        info = req.goal_info
        uuid = bytes(info.goal_id.uuid)
        stamp_ns = info.stamp.sec * 1_000_000_000 + info.stamp.nanosec
        with self._lock:
            if any(uuid) and not stamp_ns:  # that goal only
                g = self.goals.get(uuid)
                if g is None:
                    return {"return_code": ERROR_UNKNOWN_GOAL_ID, "goals_canceling": []}
                if g.status in TERMINAL:
                    return {"return_code": ERROR_GOAL_TERMINATED, "goals_canceling": []}
                chosen = [g]
            else:  # all; or all accepted at or before the stamp, and the goal id's one if given
                every = not any(uuid) and not stamp_ns
                chosen = [
                    g
                    for g in self.goals.values()
                    if g.status in (ACCEPTED, EXECUTING)  # cancelable, as rcl_action says
                    and (every or g.accepted_ns <= stamp_ns or g.uuid == uuid)
                ]
        canceling = []
        if chosen:
            audit("follow_joint_trajectory.cancel", f"goal_uuid={uuid.hex()}",
                  stamp_ns=stamp_ns, goals=",".join(g.daemon_id for g in chosen))  # fmt: skip
        for g in chosen:
            try:
                with on_behalf_of(f"zenoh goal_uuid={uuid.hex()}"):
                    self.client.cancel(g.daemon_id)
            except ApiError as exc:
                if exc.code != "not_found":
                    self.report(40, f"cancel of {g.daemon_id} refused{daemon_said(exc)}")
                    continue
            with self._lock:
                if g.status not in TERMINAL:
                    g.status = CANCELING
            canceling.append({"goal_id": {"uuid": list(g.uuid)}, "stamp": _stamp(g.accepted_ns)})
        self._publish_status()
        code = ERROR_NONE if canceling or not chosen else ERROR_REJECTED
        return {"return_code": code, "goals_canceling": canceling}

    # ---------------------------------------------------------------- tracking
    def _forget_old(self) -> None:
        done = [u for u, g in self.goals.items() if g.status in TERMINAL]
        for u in done[: max(0, len(done) - KEEP_FINISHED)]:
            del self.goals[u]

    def _track(self) -> None:
        from host.api.client import ApiConnectionError, ApiError, ApiTimeoutError  # noqa: PLC0415

        while not self._stop.wait(self.period_s):
            with self._lock:
                live = [g for g in self.goals.values() if g.status not in TERMINAL]
                notes, self._notes = self._notes, []
            for why in notes:
                self.report(40, f"FollowJointTrajectory request refused: {why}")
            if not live:
                continue
            changed = False
            try:
                joints = self.client.status().get("joint_states") or {}
            except ApiError:
                joints = {}
            for g in live:
                try:
                    st = self.client.trajectory_status(g.daemon_id)
                except (ApiConnectionError, ApiTimeoutError):
                    continue  # the daemon is away or slow: asked again in the next round
                except ApiError as exc:
                    known = "no longer knows" if exc.code == "not_found" else "gave no status of"
                    why = f"the daemon {known} goal {g.daemon_id} ({exc.code}: {exc.message})"
                    st = {"state": "aborted", "reason": why, "done": True}
                state = str(st.get("state", ""))
                if st.get("done") or state in ("succeeded", "aborted", "canceled"):
                    cause = str((st.get("abort") or {}).get("cause") or "")
                    status, code, text = result_of(state, str(st.get("reason") or ""), cause)
                    with self._lock:
                        g.status, g.error_code, g.error_string = status, code, text
                        waiters, g.waiters = g.waiters, []
                    for w in waiters:
                        w(self._result(g))
                    changed = True
                    continue
                self._publish_feedback(g, joints)
            if changed:
                self._publish_status()

    def _publish_feedback(self, g: Goal, joints: dict) -> None:
        positions = []
        for name in g.joints:
            bendable, _, axis = name.rpartition("/")
            positions.append(float((joints.get(bendable) or {}).get(axis, 0.0)))
        now = time.time_ns()
        elapsed = now - g.accepted_ns
        msg = {
            "goal_id": {"uuid": list(g.uuid)},
            "feedback": {
                "header": {"stamp": _stamp(now), "frame_id": ""},
                "joint_names": g.joints,
                "actual": {
                    "positions": positions,
                    "time_from_start": {
                        "sec": elapsed // 1_000_000_000,
                        "nanosec": elapsed % 1_000_000_000,
                    },
                },
            },
        }
        self.feedback.publish(self._fb_codec.encode(msg))

    def _publish_status(self) -> None:
        with self._lock:
            lst = [
                {
                    "goal_info": {
                        "goal_id": {"uuid": list(g.uuid)},
                        "stamp": _stamp(g.accepted_ns),
                    },
                    "status": g.status,
                }
                for g in self.goals.values()
            ]
        self.status.publish(self._status_codec.encode({"status_list": lst}))

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        with self._lock:
            waiting = [(g, w) for g in self.goals.values() for w in g.waiters]
            for g in self.goals.values():
                g.waiters = []
        for _g, w in waiting:  # the bridge stops: the goal keeps running in the daemon
            w({"status": UNKNOWN, "result": {"error_code": INVALID_GOAL,
                                             "error_string": "ucr zenoh stopped"}})  # fmt: skip


def hashes() -> dict[str, str]:
    """The type hashes this server's key expressions carry (for logs and tests)."""
    return {
        "send_goal": action_type_hash(ACTION, "SendGoal"),
        "get_result": action_type_hash(ACTION, "GetResult"),
        "cancel_goal": service_type_hash(CANCEL),
        "feedback": action_type_hash(ACTION, "FeedbackMessage"),
        "status": type_hash(STATUS_ARRAY),
    }
