"""The ROS 2 services ``ucr zenoh`` serves (``std_srvs/srv/Trigger``), each answered through the
daemon's API like any other client's request; nothing here decides what the robot may do.

- ``<ns>/ucr/status`` (always, read-only): ``success`` when the daemon is connected to the chain
  and every segment has a valid state and no fault; ``message`` a one-line JSON summary.
- ``<ns>/ucr/stop`` (only with ``--enable-commands``): cancels every running trajectory goal
  (the daemon decelerates the robot to rest and holds it, as ``trajectory.cancel`` does).
  ``success`` is false when the daemon refused or a goal could not be canceled; manual control
  (cFFC) is not affected.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

TRIGGER = "std_srvs/srv/Trigger"
STATUS, STOP = "ucr/status", "ucr/stop"


class RobotServices:
    """Handlers of the bridge's services (run on the service worker thread)."""

    def __init__(self, client: Any, report: Callable[[int, str], None]) -> None:
        self.client = client
        self.report = report

    def status(self, request: Any) -> dict:
        from host.api.client import ApiError  # noqa: PLC0415

        try:
            st = self.client.status()
        except ApiError as exc:
            return {"success": False, "message": f"daemon: {exc.code}: {exc.message}"}
        joints = st.get("joint_states") or {}
        valid = all(j.get("valid") for j in joints.values()) and bool(joints)
        faults = sorted(st.get("faults") or {})
        ok = st.get("state") == "connected" and valid and not faults
        summary = {
            "state": st.get("state"),
            "robot": st.get("robot"),
            "segments": st.get("segments"),
            "all_valid": valid,
            "faults": faults,
            "running_goals": st.get("running_goals"),
            "manual_control": st.get("manual_control"),
            "active_controllers": st.get("active_controllers"),
        }
        return {"success": ok, "message": json.dumps(summary, separators=(",", ":"))}

    def stop(self, request: Any) -> dict:
        from host.api.client import ApiError  # noqa: PLC0415

        try:
            goals = list(self.client.status().get("running_goals") or [])
            canceled, failed = [], []
            for goal in goals:
                try:
                    st = self.client.cancel(goal)
                    (canceled if st.get("canceled") else failed).append(goal)
                except ApiError as exc:
                    if exc.code != "not_found":  # finished meanwhile: nothing to stop
                        failed.append(f"{goal} ({exc.code})")
        except ApiError as exc:
            text = f"stop refused by the daemon ({exc.code}): {exc.message}"
            self.report(40, text)
            return {"success": False, "message": text}
        if failed:
            text = f"stop: canceled {canceled}, could not cancel {failed}"
            self.report(40, text)
            return {"success": False, "message": text}
        text = f"stop: canceled {canceled}" if canceled else "stop: no trajectory goal running"
        self.report(20, text)
        return {"success": True, "message": text}
