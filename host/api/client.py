"""Python client of the daemon API (synchronous; a reader thread matches replies and pushes).

    from host.api.client import connect
    with connect() as c:                       # ws://127.0.0.1:8765 or $UCR_URL
        print(c.status())
        result = c.send_trajectory(points, progress=print)
        with c.subscribe(["joint_states"], max_rate=10) as sub:
            for msg in sub:
                ...

Errors: :class:`ApiError` (``code``, ``message``) for refused requests; connection problems raise
:class:`ApiConnectionError`, which is also a built-in ``ConnectionError``; a refused token raises
:class:`ApiAuthError` (also a ``PermissionError``); timeouts raise :class:`ApiTimeoutError`.
Opening the connection (token, TLS, handshake refusals) is :mod:`host.api.client_open`, sending
a trajectory above the request limit in chunks :mod:`host.api.client_upload`, a request's
JSON :mod:`host.api.client_json`, progress callbacks :mod:`host.api.client_goals`; the
errors live in :mod:`host.api.client_errors` and are re-exported here.

One piece: the reader thread, the pending replies, the subscriptions and the goal waits share
one lock and one connection's state, and each public method is a thin call over them.
"""

from __future__ import annotations

import collections
import itertools
import json
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from typing import Any

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection

from host.api import default_url
from host.api.client_behalf import _ON_BEHALF_OF, on_behalf_of, sender_words
from host.api.client_errors import ApiAuthError, ApiConnectionError, ApiError, ApiTimeoutError
from host.api.client_goals import Callbacks, final_or_raise, positive_seconds
from host.api.client_json import as_pair, name_list, plain_json, unencodable, waypoint_list
from host.api.client_open import open_websocket, read_token
from host.api.client_upload import cancel_upload, send_in_chunks

__all__ = [
    "ApiAuthError",
    "ApiConnectionError",
    "ApiError",
    "ApiTimeoutError",
    "Client",
    "Subscription",
    "connect",
    "on_behalf_of",
    "sender_words",
    "read_token",
]

_COMPACT = (",", ":")


class _Pending:
    __slots__ = ("event", "reply")

    def __init__(self) -> None:
        self.event = threading.Event()
        self.reply: dict | None = None


class Subscription:
    """Iterator over messages of one subscription; ``close()`` unsubscribes.

    Messages are the daemon's dicts (``{"kind": ..., "t": ..., ...}``). If the caller reads more
    slowly than messages arrive, the oldest are dropped locally (``dropped_local``); the server
    reports its own drops in ``dropped_server``.
    """

    def __init__(self, client: Client, sid: int, kinds: list[str], buffer: int) -> None:
        self.client = client
        self.sid = sid
        self.kinds = kinds
        self._buf: collections.deque[dict] = collections.deque()
        self._cond = threading.Condition()
        self._limit = buffer
        self.dropped_local = 0
        self.dropped_server = 0
        self.closed = False

    def _put(self, msg: dict, dropped: int) -> None:
        with self._cond:
            self.dropped_server = dropped
            if len(self._buf) >= self._limit:
                self._buf.popleft()
                self.dropped_local += 1
            self._buf.append(msg)
            self._cond.notify()

    def _end(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def get(self, timeout: float | None = None) -> dict | None:
        """Next message, or None after ``timeout`` s. Raises StopIteration once the subscription
        is closed, and the connection's :class:`ApiConnectionError` if the connection broke."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while not self._buf:
                if self.closed or self.client.closed:
                    if self.client.closed and self.client.error is not None:
                        raise self.client.error
                    raise StopIteration
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                self._cond.wait(remaining if remaining is not None else 0.5)
            return self._buf.popleft()

    def __iter__(self) -> Iterator[dict]:
        while True:
            try:
                msg = self.get()
            except StopIteration:
                return
            if msg is not None:
                yield msg

    def close(self) -> dict | None:
        """Unsubscribe; returns the server's counters (sent, dropped, thinned) if connected."""
        if self.closed:
            return None
        with self.client._lock:
            self.client._subs.pop(self.sid, None)
            self.client._gone_subs.add(self.sid)
        self._end()
        if self.client.closed:
            return None
        return self.client.call("unsubscribe", sub=self.sid)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self.close()
        except ApiError:
            pass


class Client:
    """One connection to the daemon API. Thread-safe: calls may come from several threads."""

    def __init__(self, ws: ClientConnection, url: str, timeout: float) -> None:
        self.ws = ws
        self.url = url
        self.timeout = timeout
        self.closed = False
        self.error: ApiConnectionError | None = None
        self._ids = itertools.count(1)
        self._pending: dict[int, _Pending] = {}
        self._lock = threading.Lock()
        self._subs: dict[int, Subscription] = {}
        self._orphans: dict[Any, list[tuple[dict, int]]] = {}
        self._gone_subs: set[int] = set()
        self._goals: dict[Any, Callable[[dict], None]] = {}
        self._goal_final: dict[Any, dict] = {}
        self._goal_cond = threading.Condition()
        self._upload_lock = threading.Lock()  # one chunked upload at a time from this client
        self.last_goal: Any = None
        self._callbacks = Callbacks()
        self._reader = threading.Thread(target=self._read_loop, name="ucr-api-client", daemon=True)
        self._reader.start()

    # ------------------------------------------------------------------ plumbing
    def _read_loop(self) -> None:
        try:
            for frame in self.ws:
                try:
                    msg = json.loads(frame)
                except ValueError:
                    continue  # the server only sends JSON; ignore anything else defensively
                if not isinstance(msg, dict):
                    continue
                if "push" in msg:
                    self._on_push(msg)
                    continue
                with self._lock:
                    pending = self._pending.pop(msg.get("id"), None)
                if pending is not None:
                    pending.reply = msg
                    pending.event.set()
            if not self.closed:
                code = self.ws.close_code
                self.error = ApiConnectionError(
                    f"the daemon at {self.url} closed the connection (code {code})"
                )
        except ConnectionClosed as exc:
            if not self.closed:
                self.error = ApiConnectionError(f"connection to {self.url} lost: {exc}")
        except Exception as exc:  # noqa: BLE001 - surfaced to callers as a connection error
            self.error = ApiConnectionError(f"connection to {self.url} failed: {exc}")
        finally:
            self._shutdown()

    def _shutdown(self) -> None:
        self.closed = True
        with self._lock:
            pending = list(self._pending.values())
            self._pending.clear()
        for p in pending:
            p.event.set()
        for sub in list(self._subs.values()):
            sub._end()
        self._callbacks.close()
        with self._goal_cond:
            self._goal_cond.notify_all()

    def _on_push(self, msg: dict) -> None:
        kind = msg.get("push")
        if kind == "stream":
            data, dropped = msg.get("msg"), int(msg.get("dropped") or 0)
            if not isinstance(data, dict):
                return
            with self._lock:
                sub = self._subs.get(msg.get("sub"))
                if sub is None and msg.get("sub") not in self._gone_subs:
                    # A message can overtake the subscribe reply: keep a few until it is known.
                    early = self._orphans.setdefault(msg.get("sub"), [])
                    if len(early) < 100 and len(self._orphans) < 100:
                        early.append((data, dropped))
                    return
            if sub is not None:
                sub._put(data, dropped)
        elif kind == "trajectory":
            goal = msg.get("goal")
            status = msg.get("status") if isinstance(msg.get("status"), dict) else {}
            # A push overtaking the send reply finds no callback yet: only that progress is lost.
            callback = self._goals.get(goal)
            if callback is not None:  # on a thread of its own: it may call this client
                self._callbacks.put(callback, status)
            if msg.get("done"):
                with self._goal_cond:
                    self._goals.pop(goal, None)
                    self._goal_final[goal] = status
                    while len(self._goal_final) > 100:  # goals nobody waits for
                        self._goal_final.pop(next(iter(self._goal_final)))
                    self._goal_cond.notify_all()

    def call(self, op: str, timeout: float | None = None, **params: Any) -> Any:
        """Send one request, wait for its reply; return ``result`` or raise :class:`ApiError`."""
        if self.closed:
            raise self.error or ApiConnectionError(f"connection to {self.url} is closed")
        rid = next(self._ids)
        pending = _Pending()
        with self._lock:
            self._pending[rid] = pending
        try:
            msg = {"id": rid, "op": op, **params}
            behalf = _ON_BEHALF_OF.get()
            if behalf is not None:
                msg["on_behalf_of"] = behalf
            try:
                text = json.dumps(msg, allow_nan=False, separators=_COMPACT, default=plain_json)
            except (ValueError, TypeError) as exc:
                where = unencodable(params) or str(exc)
                raise ApiError("invalid_params", f"cannot encode request: {where}") from None
            self.ws.send(text)
        except ApiError:
            with self._lock:
                self._pending.pop(rid, None)
            raise
        except (ConnectionClosed, OSError) as exc:
            with self._lock:
                self._pending.pop(rid, None)
            raise ApiConnectionError(f"connection to {self.url} lost: {exc}") from None
        wait = self.timeout if timeout is None else timeout
        if not pending.event.wait(wait):
            with self._lock:
                self._pending.pop(rid, None)
            raise ApiTimeoutError(f"no reply to {op!r} within {wait:g} s")
        reply = pending.reply
        if reply is None:
            raise self.error or ApiConnectionError(f"connection to {self.url} closed")
        if reply.get("ok"):
            return reply.get("result")
        err = reply.get("error") or {}
        raise ApiError(str(err.get("code", "error")), str(err.get("message", "request failed")))

    # ------------------------------------------------------------------ ops
    def ping(self) -> float:
        """Round trip time (s)."""
        t0 = time.perf_counter()
        self.call("ping")
        return time.perf_counter() - t0

    def status(self) -> dict:
        return self.call("status")

    def session(self) -> dict:
        """This connection as the daemon sees it: ``scope`` ("read" or "control": what its token
        may call), ``authenticated``, ``peer``, ``agent``. ``unknown_op`` from a daemon older
        than the op."""
        return self.call("session")

    def topology(self) -> Any:
        return self.call("topology")

    def robot_description(self) -> dict:
        """The daemon's robot: ``robot``, ``file``, ``sha256``, ``bytes`` and ``text`` (its
        U(C)RDF as canonical text; None when too large)."""
        return self.call("robot.description")

    def loop_stats(self) -> dict:
        return self.call("loop_stats")

    def controllers(self) -> Any:
        return self.call("controllers.list")

    def switch(
        self, start: list[str] | str | None = None, stop: list[str] | str | None = None
    ) -> Any:
        """Activate ``start`` and deactivate ``stop`` controllers (names, or one name) in one
        switch."""
        return self.call("controllers.switch", start=name_list(start), stop=name_list(stop))

    def hand_back(self, manual: str | None = None) -> Any:
        """End a manual (cFFC) takeover and restart the controllers it preempted."""
        return self.call("controllers.hand_back", **({} if manual is None else {"manual": manual}))

    def clear_fault(self, segment: str | None = None) -> Any:
        """Send CLEAR_FAULT to ``segment`` (or every segment): it leaves FAULT for HOLD."""
        return self.call("faults.clear", **({} if segment is None else {"segment": segment}))

    def cancel_upload(self, upload: int) -> bool:
        """End an unfinished chunked upload of this connection; False if the server no longer
        had it (sent, refused or expired) or did not answer."""
        return cancel_upload(self.call, upload)

    def send_trajectory(
        self,
        points: Iterable[dict],
        *,
        wait: bool = True,
        progress: Callable[[dict], None] | None = None,
        controller: str | None = None,
        timeout: float | None = None,
    ) -> Any:
        """Send waypoints (docs/api.md); with ``wait`` return the final status, else the goal id.

        ``progress`` is called with each status the daemon pushes, in order, on a thread of the
        client's own (it may call the client). ``timeout`` (s) bounds the wait for the result;
        None waits as long as it takes. Ctrl-C (KeyboardInterrupt) while waiting cancels the
        goal (the robot decelerates to rest and holds), as ``ucr trajectory`` does; a timeout
        leaves it running.
        """
        points = waypoint_list(points)  # (a generator, a tuple: read once)
        params: dict[str, Any] = {}
        if controller is not None:
            params["controller"] = controller
        # The daemon builds and retimes the whole path before it answers: ~0.2 ms per waypoint
        # on a Pi-class CPU, more when loaded, so a long trajectory gets a longer reply timeout.
        reply_s = self.timeout + 0.002 * len(points)
        result = send_in_chunks(self.call, points, params, reply_s, self._upload_lock)
        goal = result["goal"]
        self.last_goal = goal
        if progress is not None:
            self._goals[goal] = progress
        if not wait:
            return goal
        try:
            return self.wait_trajectory(goal, timeout)
        except KeyboardInterrupt:
            try:  # the person stopped the script: the motion too
                self.call("trajectory.cancel", goal=goal, timeout=min(self.timeout, 2.0))
            except (ApiError, ConnectionError, OSError):
                pass
            raise

    def wait_trajectory(self, goal: Any, timeout: float | None = None) -> dict:
        """Block until the goal ends; returns its final status (after the goal's progress
        callbacks ran). Any goal: one this client did not send (or waited for already) is
        asked for (``trajectory.status``) once a second. :class:`ApiConnectionError` if the
        daemon went away meanwhile (how the goal ended is unknown)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        ask_at = time.monotonic() + 1.0
        while True:
            with self._goal_cond:
                if goal in self._goal_final:
                    final = self._goal_final.pop(goal)
                    break
                if self.closed:
                    raise self.error or ApiConnectionError(f"connection to {self.url} closed")
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    raise ApiTimeoutError(f"trajectory {goal} not finished within {timeout:g} s")
                self._goal_cond.wait(0.5 if remaining is None else min(remaining, 0.5))
            if time.monotonic() >= ask_at:  # no push for it (not ours, or read already)
                ask_at = time.monotonic() + 1.0
                status = self.call("trajectory.status", goal=goal)
                if isinstance(status, dict) and status.get("done"):
                    with self._goal_cond:
                        self._goal_final.pop(goal, None)
                    final = status
                    break
        self._callbacks.flush()
        return final_or_raise(goal, final)

    def trajectory_status(self, goal: Any = None) -> Any:
        return self.call("trajectory.status", goal=self._goal(goal))

    def cancel(self, goal: Any = None) -> Any:
        """Cancel a goal (default: the last one this client sent)."""
        return self.call("trajectory.cancel", goal=self._goal(goal))

    def _goal(self, goal: Any) -> Any:
        goal = self.last_goal if goal is None else goal
        if goal is None:
            raise ApiError("invalid_params", "no goal given and none sent on this connection")
        return goal

    def ffc_input(self, rates: dict[str, tuple[float, float] | list[float]]) -> Any:
        """Stream one cFFC input: ``{segment: (dkx, dky)}`` deflections in [-1, 1]. Anything
        but a dict is sent as it is: the daemon's error names what it expected."""
        if isinstance(rates, dict):
            rates = {k: as_pair(v) for k, v in rates.items()}
        return self.call("ffc.input", rates=rates)

    def subscribe(
        self, kinds: list[str] | str, max_rate: float | None = None, buffer: int = 1000
    ) -> Subscription:
        """Subscribe to ``joint_states``, ``transforms``, ``events``, ``topology``; ``buffer``:
        messages kept for a slow reader (>= 1; the oldest go first). Close it (``with``, or
        ``close()``): a loop left by ``break`` or ``return`` does not unsubscribe."""
        if isinstance(buffer, bool) or not isinstance(buffer, int) or buffer < 1:
            raise ValueError(f"buffer must be a whole number of messages >= 1, got {buffer!r}")
        kinds = [kinds] if isinstance(kinds, str) else list(kinds)
        params: dict[str, Any] = {"kinds": kinds}
        if max_rate is not None:
            params["max_rate"] = max_rate
        result = self.call("subscribe", **params)
        sub = Subscription(self, result["sub"], result.get("kinds", kinds), buffer)
        with self._lock:
            self._subs[sub.sid] = sub
            early = self._orphans.pop(sub.sid, [])
        for msg, dropped in early:
            sub._put(msg, dropped)
        return sub

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            try:
                self.ws.close()
            except Exception:  # noqa: BLE001, S110 - closing a broken socket
                pass
        self._reader.join(2.0)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def connect(
    url: str | None = None,
    token: str | None = None,
    timeout: float = 5.0,
    *,
    cafile: str | None = None,
    agent: str | None = None,
) -> Client:
    """Open a connection; ``url`` defaults to ``$UCR_URL``, ``token`` to what
    :func:`read_token` finds (the file ``$UCR_TOKEN_FILE`` names, else ``$UCR_TOKEN``).

    ``cafile`` (default ``$UCR_CA``): a CA bundle or the daemon's own certificate, to verify a
    ``wss://`` server that uses a self-signed certificate. ``agent``: the program's name, sent
    as the User-Agent (the daemon's audit lines show it; default ``ucr python client``).
    """
    timeout = positive_seconds(timeout)
    url = url or default_url()
    token = token if token is not None else read_token()
    return Client(open_websocket(url, token, timeout, cafile, agent), url, timeout)
