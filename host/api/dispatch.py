"""The API server's request side (:class:`Dispatcher`): parsing and scope check
(:meth:`Dispatcher.parse`, so the connection can charge a request by its parsed op before it is
served), dispatch to the daemon (:meth:`Dispatcher.serve`), uploads, goal progress.

A part the server composes: it gets the options, the shared counters, the outboxes (subscriptions,
progress pushes) and callables to reach the daemon (``call``, ``status_text``) and to list the
connected sessions. ``status`` is answered from the latest snapshot the daemon sent, without a
round trip; ops that move the robot or switch controllers are written to ``ucr.audit``, every
value a client chose written as a Python literal (``repr``), so no request can add a line.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from websockets.protocol import State

from host.api import schema as S
from host.api.audit import audit_log
from host.api.auth import CONTROL, READ_OPS
from host.api.bridge import BridgeClosed, RemoteError
from host.api.connection import Outboxes
from host.api.session import (
    ON_BEHALF_OF,
    _Request,
    _Session,
    _Subscription,
    _Upload,
    command_source,
)

log = logging.getLogger("ucr.api")

UPLOAD_IDLE_S = 60.0  # an upload untouched this long is dropped

_TERMINAL_STATES = frozenset(
    {
        "succeeded",
        "success",
        "aborted",
        "canceled",
        "cancelled",
        "failed",
        "rejected",
        "done",
        "preempted",
        "replaced",
    }
)
_CONTROL_OPS_AUDITED = (
    "controllers.switch",
    "controllers.hand_back",
    "trajectory.send",
    "trajectory.cancel",
)


def goal_done(status: Any) -> bool:
    """Whether a ``trajectory_status`` result describes a finished goal."""
    if not isinstance(status, dict):
        return False
    if status.get("done") is True or status.get("finished") is True:
        return True
    for key in ("state", "status", "result"):
        value = status.get(key)
        if isinstance(value, str) and value.lower() in _TERMINAL_STATES:
            return True
    return False


class Dispatcher:
    """Answering one request frame of a session (and pushing its goals' progress).

    ``upload_points``: waypoints held by unfinished uploads of every client. Uploads are kept
    here by id, each with the session that owns it: a connection may have up to
    ``schema.MAX_UPLOADS`` at once, and a new one never replaces another.
    """

    def __init__(
        self,
        opts: Any,
        counters: dict[str, int],
        outboxes: Outboxes,
        call: Callable[..., Awaitable[Any]],
        status_text: Callable[[], str | None],
        sessions: Callable[[], Iterable[_Session]],
    ) -> None:
        self.opts = opts
        self.counters = counters
        self._outboxes = outboxes
        self._call = call
        self._status_text = status_text
        self._sessions = sessions
        self._next_sub = 1
        self._next_upload = 1
        self._uploads: dict[int, _Upload] = {}
        self.upload_points = 0

    # ------------------------------------------------------------------ requests
    async def serve_frame(self, session: _Session, frame: str | bytes) -> dict | str:
        """Parse and serve one frame (no budget: the connection's loop charges between)."""
        request = self.parse(session, frame)
        return request if isinstance(request, dict) else await self.serve(session, request)

    def parse(self, session: _Session, frame: str | bytes) -> _Request | dict:
        """The parsed request, or the error reply (bad frame, unknown op, wrong scope)."""
        self.counters["requests"] += 1
        try:
            rid, op, params, behalf = S.parse_request(
                frame, self.opts.max_request_bytes, lambda uid: self._held(session, uid)
            )
        except S.RequestError as exc:
            self.counters["errors"] += 1
            if exc.upload is not None:  # a refused chunk ends its upload
                self.end_upload(session, exc.upload)
            return S.error_reply(exc.request_id, exc.code, exc.message)
        if op not in READ_OPS and session.scope != CONTROL:
            self.counters["errors"] += 1
            self.counters["forbidden"] += 1
            return S.error_reply(
                rid, S.FORBIDDEN, f"{op!r} needs a token with the control scope (this one: read)"
            )
        return _Request(rid, op, params, behalf)

    async def serve(self, session: _Session, request: _Request) -> dict | str:
        """Run a parsed request; the reply (an error reply for any failure)."""
        rid, op, params, behalf = request
        scope = ON_BEHALF_OF.set(behalf)  # this request's task only (the audit reads it)
        try:
            result = await self._dispatch(session, op, params)
        except S.RequestError as exc:
            self.counters["errors"] += 1
            return S.error_reply(rid, exc.code, exc.message)
        except RemoteError as exc:
            self.counters["errors"] += 1
            return S.error_reply(rid, exc.code, str(exc))
        except Exception as exc:  # noqa: BLE001 - becomes an error reply, never kills the server
            self.counters["errors"] += 1
            log.exception("API: op %s failed", op)
            return S.error_reply(rid, S.INTERNAL, f"internal error ({type(exc).__name__}): {exc}")
        finally:
            ON_BEHALF_OF.reset(scope)
        if isinstance(result, _Raw):
            return f'{{"id":{json.dumps(rid)},"ok":true,"result":{result.text}}}'
        return S.ok_reply(rid, result)

    def _audit(self, session: _Session, op: str, goal: Any, summary: str) -> None:
        audit_log(
            session.peer,
            session.who,
            session.scope,
            op,
            goal,
            summary,
            session.agent,
            on_behalf_of=ON_BEHALF_OF.get(),
        )

    async def _dispatch(self, session: _Session, op: str, p: dict) -> Any:
        call = self._call
        if op == "ping":
            return {"pong": True, "t": time.time()}
        if op == "session":
            return self._session(session)
        if op == "status":
            return self._status()
        if op == "topology":
            return await call("topology")
        if op == "robot.description":
            return await call("robot_description")
        if op == "loop_stats":
            return await call("loop_stats")
        if op == "controllers.list":
            return await call("controllers")
        if op == "controllers.switch":
            self._audit(session, op, None, f"start {p['start']!r} stop {p['stop']!r}")
            return await call("switch_controllers", p["start"], p["stop"])
        if op == "controllers.hand_back":
            self._audit(session, op, None, f"manual {p['manual']!r}")
            return await call("hand_back", p["manual"])
        if op == "faults.clear":
            where = "every segment" if p["segment"] is None else repr(p["segment"])
            self._audit(session, op, None, f"clear fault on {where}")
            return await call("clear_fault", p["segment"])
        if op == "trajectory.upload":
            return self._upload(session, p)
        if op == "trajectory.upload_cancel":
            up = self._own_upload(session, p["upload"])
            self.end_upload(session, up.uid)
            return {"upload": up.uid, "canceled": True, "points": len(up.points)}
        if op == "trajectory.send":
            return await self._send_trajectory(session, p)
        if op == "trajectory.status":
            return await call("trajectory_status", p["goal"])
        if op == "trajectory.cancel":
            self._audit(session, op, p["goal"], "cancel")
            return await call("cancel_trajectory", p["goal"])
        if op == "ffc.input":
            return await self._ffc_input(session, p["rates"])
        if op == "subscribe":
            return self._subscribe(session, p["kinds"], p["max_rate"])
        if op == "unsubscribe":
            sub = session.subs.pop(p["sub"], None)
            if sub is None:
                raise S.RequestError(S.NOT_FOUND, f"no subscription {p['sub']} on this connection")
            self._outboxes.remove(sub)
            return {
                "sub": sub.sid,
                "sent": sub.sent,
                "dropped": sub.dropped,
                "thinned": sub.thinned,
            }
        raise S.RequestError(S.UNKNOWN_OP, f"unknown op {op!r}")  # pragma: no cover - schema guards

    @staticmethod
    def _session(session: _Session) -> dict:
        """What this connection is to the server: its scope (what it may call), whether a token
        let it in, its address and program as the server sees them. Never a token's value or
        label: a client learns only what it already holds."""
        return {
            "scope": session.scope,
            "authenticated": session.authenticated,
            "peer": session.peer,
            "agent": session.agent,
        }

    def _status(self) -> Any:
        text = self._status_text()
        if text is None:
            raise S.RequestError(S.UNAVAILABLE, "no status from the daemon yet")
        if text.startswith('{"__error__"'):
            err = json.loads(text)["__error__"]
            raise S.RequestError(err["code"], err["message"])
        return _Raw(text)

    async def _ffc_input(self, session: _Session, rates: dict) -> Any:
        # Remember before calling: if the call fails half-way the input may still be set,
        # and a disconnect must then zero it.
        before = set(session.ffc_active)
        deflected = {n for n, (x, y) in rates.items() if x or y}
        if deflected != session.ffc_audited:  # a 50 Hz stream is audited when its sticks change
            session.ffc_audited = deflected
            self._audit(session, "ffc.input", None, f"deflected {sorted(deflected)}")
        session.ffc_active.update(deflected)
        try:
            result = await self._call("ffc_input", rates, command_source(session))
        except RemoteError as exc:
            if exc.code == S.REJECTED:
                session.ffc_active = before  # refused: the daemon did not take this input
            raise
        session.ffc_active.difference_update(n for n, (x, y) in rates.items() if not (x or y))
        if isinstance(result, dict) and result.get("takeover"):
            self._audit(session, "ffc.takeover", None, str(result.get("takeover")))
        return result

    async def _send_trajectory(self, session: _Session, p: dict) -> dict:
        points = p["points"] or []
        if p.get("upload") is not None:
            up = self._own_upload(session, p["upload"])
            self.end_upload(session, p["upload"])  # sent or refused, the upload ends here
            if points and points[0]["time_from_start"] <= up.last_t:
                raise S.RequestError(
                    S.INVALID_PARAMS,
                    f"points[{len(up.points)}].time_from_start: must continue after the upload",
                )
            points = up.points + points
            if len(points) > S.MAX_POINTS:
                raise S.RequestError(S.INVALID_PARAMS, f"at most {S.MAX_POINTS} waypoints")
        if not points:
            raise S.RequestError(S.INVALID_PARAMS, "points: needs at least one waypoint")
        t_end = points[-1]["time_from_start"]
        names = sorted({n for pt in points for n in pt["segments"]})
        summary = f"{len(points)} waypoint(s) over {t_end:g} s, segments {names}, " + (
            "the active trajectory controller"
            if p["controller"] is None
            else f"controller {p['controller']!r}"
        )
        try:
            source = command_source(session)
            goal = await self._call("send_trajectory", points, p["controller"], source)
        except (RemoteError, S.RequestError) as exc:  # refused motion is logged too
            code = getattr(exc, "code", "error")
            self._audit(session, "trajectory.send", None, f"refused ({code}: {exc}): {summary}")
            raise
        if _gone(session):
            # The sender left (Ctrl-C, a crash) before it could learn the goal's id: nobody
            # could watch or cancel this goal, so it does not run.
            with contextlib.suppress(RemoteError, BridgeClosed):
                await self._call("cancel_trajectory", goal)
            self._audit(
                session, "trajectory.send", goal, f"{summary}; canceled: the sender left "
                "before the goal was accepted"
            )  # fmt: skip
            return {"goal": goal, "canceled": True}
        session.goals[goal] = None
        self._audit(session, "trajectory.send", goal, summary)
        return {"goal": goal}

    def _upload(self, session: _Session, p: dict) -> dict:
        """One chunk: a first one (no ``upload``) opens a new upload beside the connection's
        others, never replacing one; a refused later chunk ends its upload."""
        new = p.get("upload") is None
        if new:
            mine = sum(1 for u in self._uploads.values() if u.owner is session)
            if mine >= S.MAX_UPLOADS:
                raise S.RequestError(
                    S.REJECTED,
                    f"at most {S.MAX_UPLOADS} uploads in progress on one connection: finish one "
                    f"(trajectory.send with its id) or wait ({UPLOAD_IDLE_S:g} s untouched ends "
                    "one)",
                )
            up = _Upload(self._next_upload, session)
        else:
            up = self._own_upload(session, p["upload"])
        try:
            self._check_chunk(up, p["points"])
        except S.RequestError:
            self.end_upload(session, up.uid)
            raise
        if new:  # kept once its first chunk is accepted
            self._next_upload += 1
            self._uploads[up.uid] = up
        pts = p["points"]
        up.points.extend(pts)
        up.last_t = pts[-1]["time_from_start"]
        up.t_touched = time.monotonic()
        self.upload_points += len(pts)
        return {"upload": up.uid, "points": len(up.points)}

    def _check_chunk(self, up: _Upload, pts: list[dict]) -> None:
        if pts[0]["time_from_start"] <= up.last_t:  # schema checks it too, given the upload
            raise S.RequestError(
                S.INVALID_PARAMS,
                f"points[{len(up.points)}].time_from_start: times must increase strictly across "
                f"chunks ({pts[0]['time_from_start']:g} s after {up.last_t:g} s)",
            )
        if len(up.points) + len(pts) > S.MAX_POINTS:
            raise S.RequestError(
                S.INVALID_PARAMS, f"an upload holds at most {S.MAX_POINTS} waypoints"
            )
        if self.upload_points + len(pts) > self.opts.upload_points_total:
            raise S.RequestError(S.UNAVAILABLE, "too many uploads in progress; try again later")

    def _own_upload(self, session: _Session, uid: int) -> _Upload:
        up = self._uploads.get(uid)
        if up is None or up.owner is not session:
            raise S.RequestError(S.NOT_FOUND, f"no upload {uid} on this connection")
        return up

    def _held(self, session: _Session, uid: int) -> tuple[int, float] | None:
        """Waypoints held by ``session``'s upload ``uid`` and the time of the last (parsing)."""
        up = self._uploads.get(uid)
        if up is None or up.owner is not session:
            return None
        return len(up.points), up.last_t

    def end_upload(self, session: _Session, uid: int | None = None) -> None:
        """Forget ``session``'s upload ``uid``, or every unfinished upload it has."""
        for key in list(self._uploads) if uid is None else [uid]:
            up = self._uploads.get(key)
            if up is not None and up.owner is session:
                del self._uploads[key]
                self.upload_points -= len(up.points)

    def drop_stale_uploads(self, now: float) -> None:
        """Forget every upload untouched for ``UPLOAD_IDLE_S`` (janitor)."""
        for up in list(self._uploads.values()):
            if now - up.t_touched > UPLOAD_IDLE_S:
                self.end_upload(up.owner, up.uid)

    def _subscribe(self, session: _Session, kinds: list[str], max_rate: float | None) -> dict:
        if len(session.subs) >= self.opts.max_subscriptions:
            raise S.RequestError(
                S.REJECTED, f"at most {self.opts.max_subscriptions} subscriptions per connection"
            )
        sid = self._next_sub
        self._next_sub += 1
        sub = _Subscription(sid, kinds, max_rate)
        session.subs[sid] = sub
        self._outboxes.add(session, sub)
        return {"sub": sid, "kinds": kinds, "max_rate": max_rate}

    # ------------------------------------------------------------------ goal progress
    async def goal_pump(self) -> None:
        """Push the status of every goal a client sent while it changes, until it ends."""
        while True:
            await asyncio.sleep(self.opts.goal_poll_s)
            for session in list(self._sessions()):
                if session.goals and not session.closed:
                    try:
                        await self._poll_goals(session)
                    except Exception:  # noqa: BLE001 - the pump must outlive any one goal
                        log.exception("API: goal progress failed")

    async def _poll_goals(self, session: _Session) -> None:
        for goal, last in list(session.goals.items()):
            try:
                status = await self._call("trajectory_status", goal)
            except (RemoteError, BridgeClosed) as exc:
                session.goals.pop(goal, None)
                status = {"state": "unknown", "error": str(exc)}
                self._outboxes.push_priority(
                    session,
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": True}),
                )
                continue
            done = goal_done(status)
            if _progress_key(status) != _progress_key(last) or done:
                self._outboxes.push_priority(
                    session,
                    S.encode({"push": "trajectory", "goal": goal, "status": status, "done": done}),
                )
                session.goals[goal] = status
            if done:
                session.goals.pop(goal, None)


class _Raw:
    """A result that is already JSON text (the status snapshot): spliced, not re-encoded."""

    __slots__ = ("text",)

    def __init__(self, text: str) -> None:
        self.text = text


def _progress_key(status: Any) -> Any:
    """What makes a status worth pushing again: everything but time stamps, progress rounded."""
    if not isinstance(status, dict):
        return status
    key = []
    for k, v in sorted(status.items()):
        if k in ("t", "time", "elapsed", "stamp"):
            continue
        if isinstance(v, float) and math.isfinite(v):
            v = round(v, 2)
        key.append((k, repr(v)))
    return tuple(key)


def _gone(session: _Session) -> bool:
    """True once the client's connection is closed or closing (its reply cannot arrive)."""
    return session.closed or getattr(session.ws, "state", State.OPEN) is not State.OPEN
