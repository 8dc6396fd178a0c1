"""The ROS 2 services ``ucr zenoh`` serves (``std_srvs/srv/Trigger``), each answered through the
daemon's API like any other client's request; nothing here decides what the robot may do.

- ``<ns>/ucr/status`` (always, read-only): ``success`` when the daemon is connected to the chain
  and every segment has a valid state and no fault; ``message`` a one-line JSON summary, whose
  ``daemon`` says whether the bridge reaches the daemon (``connected``, or why not and when it
  tries again).
- ``<ns>/ucr/stop`` (only with ``--enable-commands``): cancels every running trajectory goal
  (the daemon decelerates the robot to rest and holds it, as ``trajectory.cancel`` does).
  ``success`` is false when the daemon refused or a goal could not be canceled; manual control
  (cFFC) is not affected.

A request the service refuses before it is read (:class:`~interop.zenoh.node.RmwService`) gets
``success`` false and the reason (:func:`status_refused`, :func:`stop_refused`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any

TRIGGER = "std_srvs/srv/Trigger"
STATUS, STOP = "ucr/status", "ucr/stop"


def _json(d: dict) -> str:
    return json.dumps(d, separators=(",", ":"))


def status_refused(why: str) -> dict:
    """``ucr/status``'s response to a request refused before it was read (JSON, as always)."""
    return {"success": False, "message": _json({"refused": why})}


def stop_refused(why: str) -> dict:
    """``ucr/stop``'s response to a request refused before it was read: nothing was canceled."""
    return {"success": False, "message": f"stop refused: {why}; nothing was canceled"}


class RobotServices:
    """Handlers of the bridge's services (run on the service worker thread)."""

    def __init__(self, client: Any, report: Callable[[int, str], None]) -> None:
        self.client = client
        self.report = report

    def _away(self) -> str | None:
        """Why the daemon is not connected (a :class:`~interop.live.DaemonLink`), or None."""
        if getattr(self.client, "connected", True):
            return None
        return str(getattr(self.client, "why", "") or "disconnected")

    def status(self, request: Any) -> dict:
        from host.api.client import ApiError  # noqa: PLC0415

        away = self._away()
        if away is not None:
            return {"success": False, "message": _json({"state": None, "daemon": away})}
        try:
            st = self.client.status()
        except ApiError as exc:
            daemon = f"{exc.code}: {exc.message}"
            return {"success": False, "message": _json({"state": None, "daemon": daemon})}
        joints = st.get("joint_states") or {}
        valid = all(j.get("valid") for j in joints.values()) and bool(joints)
        faults = sorted(st.get("faults") or {})
        ok = st.get("state") == "connected" and valid and not faults
        summary = {
            "daemon": "connected",
            "state": st.get("state"),
            "robot": st.get("robot"),
            "segments": st.get("segments"),
            "all_valid": valid,
            "faults": faults,
            "running_goals": st.get("running_goals"),
            "manual_control": st.get("manual_control"),
            "active_controllers": st.get("active_controllers"),
        }
        return {"success": ok, "message": _json(summary)}

    def stop(self, request: Any) -> dict:
        from host.api.client import ApiConnectionError, ApiError  # noqa: PLC0415

        away = self._away()
        if away is not None:
            text = f"stop failed: the daemon is not connected ({away}); nothing was canceled"
            self.report(40, text)
            return {"success": False, "message": text}
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
        except ApiConnectionError as exc:
            text = f"stop failed: the connection to the daemon broke ({exc.message})"
            self.report(40, text)
            return {"success": False, "message": text}
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
