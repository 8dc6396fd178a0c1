"""The live robot as ROS 2 messages: a client of the daemon's API (docs/api.md) that subscribes to
joint states, events and topology changes, polls status, loop statistics and trajectory goals,
and publishes every topic of :mod:`interop.topics` to a :class:`~interop.sinks.Fanout`.

Runs in the recorder's or the Foxglove server's own process: the daemon never waits for it (a
slow feed loses stream messages in the daemon's per-client outbox, counted, never a cycle).

A long-running client that outlives the daemon (``ucr zenoh``, ``ucr record``, ``ucr foxglove``)
keeps a :class:`DaemonLink` and connects again with :func:`host.api.reconnect.reconnect`, the
back-off ``ucr view``'s live source uses too (:func:`run_reconnecting`: the recorder and the
Foxglove server go on into the same outputs and mark the gap with two events).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from host.api.client_errors import ApiConnectionError, ApiError, ApiTimeoutError
from host.errors import not_utf8
from interop.sinks import Fanout, channels_of
from interop.topics import TOPICS, CommandedGoals, Message, RobotTopics, commanded
from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string


class FeedError(RuntimeError):
    """The feed cannot start (no robot file, daemon refused)."""


def robot_for(client: Any, robot_path: str | None) -> tuple[Any, str]:
    """The robot (parsed U(C)RDF) and its text: ``robot_path`` or the file the daemon reports.
    A ``robot_path`` whose bendables or joints differ from the daemon's robot is refused."""
    path = robot_path or client.topology().get("file")
    if not path:
        raise FeedError("the daemon reports no robot file; pass --robot FILE")
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise FeedError(
            f"cannot read the robot file {path} ({exc.strerror}); pass --robot FILE"
        ) from None
    try:
        robot = load(p)
        text = data.decode("utf-8")
    except UcrdfError as exc:
        raise FeedError(str(exc)) from None
    except UnicodeDecodeError as exc:
        raise FeedError(
            f"{path}: {not_utf8(exc)}: a recording carries the robot file as UTF-8"
        ) from None
    if robot_path:
        differs = None
        try:
            theirs = client.robot_description().get("text")
            if theirs:  # None: too large to send, nothing to compare
                differs = robot_mismatch(robot, parse_string(theirs, "the daemon's robot"))
        except ApiConnectionError:
            raise
        except (UcrdfError, ApiError):  # a daemon without the op, a text this parser refuses:
            pass  # nothing to compare with (as before the comparison existed)
        if differs:
            raise FeedError(f"{path} is not the daemon's robot ({differs}): refused")
    return robot, text


def robot_mismatch(robot: Any, other: Any) -> str | None:
    """How ``robot``'s bendables and joints differ from ``other``'s (by name), else None."""
    for kind in ("bendables", "joints"):
        ours, theirs = list(getattr(robot, kind)), list(getattr(other, kind))
        if ours != theirs:
            return f"{kind} {', '.join(ours) or 'none'} here, {', '.join(theirs) or 'none'} there"
    return None


class DaemonLink:
    """The daemon's API client of the moment: attribute access goes to :attr:`client`, which a
    reconnect replaces (what ``ucr view`` hands its controls), so the parts holding the link
    always call the current connection. ``connected`` and ``why`` say whether the daemon is
    there and, when not, why and what is being done about it."""

    def __init__(self, client: Any) -> None:
        self.client = client
        self.connected = True
        self.why = ""

    def __getattr__(self, name: str) -> Any:
        if name == "client":  # not set yet: no recursion through __getattr__
            raise AttributeError(name)
        return getattr(self.client, name)

    def lost(self, why: str) -> None:
        """The connection broke (``why``): close it; calls fail at once until :meth:`replace`."""
        self.connected, self.why = False, why
        try:
            self.client.close()
        except Exception:  # noqa: BLE001, S110 - closing a broken connection
            pass

    def replace(self, client: Any) -> None:
        """Connected again."""
        self.client, self.connected, self.why = client, True, ""

    def close(self) -> None:
        self.client.close()


def next_due(due: float, period: float, now: float) -> float:
    """When a periodic output is due next, after one that was due at ``due`` went out at ``now``
    (>= ``due``): one ``period`` after ``due``, not after ``now``, so the rate is ``1/period`` even
    when the trigger (a 50 Hz joint state) comes a little after each due time (restarting from
    ``now`` would round every period up to the next trigger: 60 ms instead of 50 at 20 Hz). If
    that time has passed as well (a pause, a stalled stream), from ``now``: no burst to catch up."""
    nxt = due + period
    return nxt if nxt > now else now + period


#: A change of the wall clock against the monotonic one above this (s) is a step (NTP setting the
#: clock: ntpd steps from 0.128 s, chrony and timesyncd likewise), which every stamp follows
CLOCK_STEP_S = 0.1
#: Joint states a second the feed takes while no output wants them (a Zenoh sink that nobody
#: subscribes to: the daemon's process then encodes and sends 2 of its 50 a second, not 50);
#: a reader matching is seen within :data:`DEMAND_CHECK_S` and gets the full stream again.
IDLE_JS_RATE_HZ = 2.0
DEMAND_CHECK_S = 0.25
#: The topics computed from the joint states (their demand decides the stream's rate).
STREAMED = ("/joint_states", "/tf", "/ucr/arcs")


def _end(sub: Any) -> int:
    """Close a subscription; the messages it dropped (locally and at the server)."""
    sub.__exit__(None, None, None)
    return int(getattr(sub, "dropped_local", 0) or 0) + int(getattr(sub, "dropped_server", 0) or 0)


def _rest(sub: Any) -> list[dict]:
    """What a closed subscription still held (at most its buffer's 4096)."""
    out: list[dict] = []
    while len(out) < 4096:
        try:
            msg = sub.get(timeout=0)
        except LOST:
            return out
        if msg is None:
            return out
        out.append(msg)
    return out


class _Swap:
    """Across a change of subscription (old and new overlap by one request): each joint state
    once, in time order (only those after the last one published), and each event or topology
    change once (one the old subscription delivered is skipped on the new one for a while)."""

    WINDOW_S = 5.0

    def __init__(self) -> None:
        self.last_js: float | None = None
        self.keys: list[tuple] = []
        self.until = 0.0

    def seen(self, msg: dict) -> dict:
        t = msg.get("t")
        if msg.get("kind") == "joint_states" and isinstance(t, int | float):
            self.last_js = float(t) if self.last_js is None else max(self.last_js, float(t))
        elif msg.get("kind") in ("event", "topology"):
            self.keys.append(_key(msg))
        return msg

    def started(self) -> None:
        self.until = time.monotonic() + self.WINDOW_S

    def fresh(self, msg: dict | None) -> dict | None:
        if msg is None:
            return None
        kind, t = msg.get("kind"), msg.get("t")
        if kind == "joint_states" and isinstance(t, int | float):
            if self.last_js is not None and t <= self.last_js:
                return None  # the old subscription published it already
            self.last_js = float(t)
        elif kind in ("event", "topology") and self.keys:
            if time.monotonic() > self.until:
                self.keys.clear()
            elif _key(msg) in self.keys:
                self.keys.remove(_key(msg))
                return None
        return msg


def _key(msg: dict) -> tuple:
    return (msg.get("kind"), msg.get("t"), repr(sorted(msg.items(), key=lambda kv: kv[0])))


def _everything(topic: str) -> bool:
    """``wants`` of an output that takes every topic (one without the method)."""
    return True


class LiveFeed:
    """Publishes the live robot. ``viz_rate`` (Hz) caps /tf and /ucr/arcs (FK is the costly
    part), ``status_period`` (s) the segment diagnostics and loop statistics; joint states go
    out as the daemon publishes them (cJSB, 50 Hz by default), up to ``js_rate``. Those three
    are computed only when the output ``wants`` them (a Zenoh sink: while a subscriber
    matches; a recording: always)."""

    def __init__(
        self,
        client: Any,
        topics: RobotTopics,
        out: Fanout,
        *,
        viz_rate: float = 20.0,
        js_rate: float = 1000.0,
        status_period: float = 1.0,
        goal_period: float = 0.5,
    ) -> None:
        self.client = client
        self.topics = topics
        self.goals_commanded = CommandedGoals()  # a long goal's waypoints come in parts
        self.out = out
        self.viz_period = 1.0 / viz_rate if viz_rate > 0 else float("inf")
        self.js_rate = js_rate
        self.status_period = status_period
        self.goal_period = goal_period
        self._mono_offset: float | None = None  # this host's monotonic - the daemon's (s)
        self._offset: float | None = None  # wall - this host's monotonic (s), steps followed
        self._goals: dict[str, dict] = {}
        self._topology_changed = False
        self.dropped = 0
        #: the joint-state rate asked of the daemon now (``js_rate``, or the idle rate)
        self.js_rate_now = js_rate

    def _t_ns(self, t_daemon: float | None) -> int:
        """Wall-clock stamp (ns) of a daemon monotonic time (None: now), the one stamping path
        of every topic. The daemon's monotonic clock is mapped onto this host's (same host: the
        same clock; another host: the difference estimated once, from the first message's
        arrival: monotonic clocks do not step), then onto the wall clock by the wall-minus-
        monotonic offset (:meth:`_wall_offset`), checked at each message: after a wall-clock
        step (NTP setting the clock of a Pi without RTC) every topic follows it at once, and no
        two topics disagree by the step."""
        offset = self._wall_offset()
        if t_daemon is None:
            return int((time.monotonic() + offset) * 1e9)
        if self._mono_offset is None:
            local = time.monotonic()
            same_clock = abs(local - t_daemon) < 1.0
            self._mono_offset = 0.0 if same_clock else local - t_daemon
        return int((t_daemon + self._mono_offset + offset) * 1e9)

    def _wall_offset(self) -> float:
        """Wall clock minus this host's monotonic clock (s), read now; a change of more than
        :data:`CLOCK_STEP_S` (a step) is taken, a smaller one (a synchronised clock's slew, the
        jitter of reading two clocks) is not: consecutive stamps keep the daemon's own spacing,
        the one the joint states' velocities are computed on."""
        m1 = time.monotonic()
        wall = time.time()
        m2 = time.monotonic()
        fresh = wall - (m1 + m2) / 2
        if self._offset is None or (
            m2 - m1 < CLOCK_STEP_S / 2 and abs(fresh - self._offset) > CLOCK_STEP_S
        ):
            self._offset = fresh
        return self._offset

    def _poll_goals(self, status: dict) -> list[Message]:
        """The goal messages of this poll: each goal newly running, each goal that ended."""
        out: list[Message] = []
        running = set(status.get("running_goals") or [])
        for gid in running - set(self._goals):
            try:
                st = self.client.trajectory_status(gid)
            except Exception:  # noqa: BLE001 - gone already: the result poll reports it
                continue
            self._goals[gid] = st
            out.append(self.topics.goal(st, self._t_ns(None), done=False))
        for gid in list(self._goals):
            if gid in running:
                continue
            try:
                st = self.client.trajectory_status(gid)
            except Exception as exc:  # noqa: BLE001 - forgotten by the daemon (500 kept)
                st = {**self._goals[gid], "state": "unknown", "reason": str(exc)}
            if not st.get("done", True) and st.get("state") in ("running", "pending"):
                continue
            del self._goals[gid]
            out.append(self.topics.goal(st, self._t_ns(None), done=True))
        return out

    def _poll(self, halt: threading.Event, results: queue.SimpleQueue) -> None:
        """The polls (status and goals every ``goal_period``, segment diagnostics and loop
        statistics every ``status_period``), in their own thread: each is a round trip to the
        daemon, and made in the publishing loop they held back the joint states (drained late
        in a burst). Their messages (or the exception that ended the polls) go to ``results``,
        which the publishing loop, the only writer, empties."""
        next_status = 0.0
        topology: dict | None = None
        while not halt.is_set():
            now = time.monotonic()
            try:
                status = self.client.status()
                msgs = self._poll_goals(status)
                if now >= next_status:
                    next_status = next_due(next_status, self.status_period, now)
                    if topology is None or self._topology_changed:
                        self._topology_changed = False
                        topology = self.client.topology()
                    t_ns = self._t_ns(None)
                    msgs.append(self.topics.segments(status, topology, t_ns))
                    msgs.append(self.topics.loop_stats(self.client.loop_stats(), t_ns))
            except Exception as exc:  # noqa: BLE001 - raised again in the publishing loop
                results.put(exc)
                return
            for m in msgs:
                results.put(m)
            halt.wait(self.goal_period)

    def _publish_polled(self, results: queue.SimpleQueue) -> None:
        while True:
            try:
                item = results.get_nowait()
            except queue.Empty:
                return
            if isinstance(item, Exception):
                raise item
            self.out.publish(item)

    def run(
        self,
        stop: threading.Event,
        duration: float | None = None,
        on_tick: Callable[[], None] | None = None,
    ) -> None:
        """Publish until ``stop`` is set, ``duration`` (s) passed or the connection ends."""
        t0 = time.monotonic()
        advertise = getattr(self.out, "advertise", None)
        if advertise is not None:  # every topic before any message: a client can subscribe
            advertise(channels_of(TOPICS))
        for m in self.topics.static_messages(self._t_ns(None)):
            self.out.publish(m)
        next_viz = 0.0  # on the joint states' own clock (their stamps)
        results: queue.SimpleQueue = queue.SimpleQueue()
        halt = threading.Event()
        poller = threading.Thread(target=self._poll, args=(halt, results), name="ucr-feed-poll",
                                  daemon=True)  # fmt: skip
        demand = self._demand()
        sub = self._subscribe(demand)
        swap = _Swap()
        try:
            poller.start()
            next_check = time.monotonic() + DEMAND_CHECK_S
            try:
                while not stop.is_set():
                    now = time.monotonic()
                    if duration is not None and now - t0 >= duration:
                        break
                    if now >= next_check:
                        next_check = now + DEMAND_CHECK_S
                        if self._demand() != demand:  # a reader came or the last one went
                            demand = not demand
                            old, sub = sub, self._subscribe(demand)
                            self.dropped += _end(old)
                            for msg in _rest(old):  # what the old one still held, in order
                                next_viz = self._publish_stream(swap.seen(msg), next_viz)
                            swap.started()
                    msg = swap.fresh(sub.get(timeout=0.05))
                    if msg is not None:
                        next_viz = self._publish_stream(msg, next_viz)
                    self._publish_polled(results)
                    self.out.tick()
                    if on_tick is not None:
                        on_tick()
            finally:
                halt.set()
                poller.join(timeout=30.0)  # a poll waits for its reply at most the API timeout
            self._publish_polled(results)
            t_ns = self._t_ns(None)
            for ev in self.goals_commanded.finish():
                for m in self.topics.event(ev, t_ns):
                    self.out.publish(m)
        finally:
            self.dropped += _end(sub)

    def _demand(self) -> bool:
        """Whether the output takes joint states at the full rate now: a recording always, a
        Zenoh sink while a subscriber matches /joint_states, /tf or /ucr/arcs."""
        wants = getattr(self.out, "wants", None) or _everything
        return any(wants(t) for t in STREAMED)

    def _subscribe(self, demand: bool) -> Any:
        """The daemon's stream at ``js_rate`` while a reader wants it, else at
        :data:`IDLE_JS_RATE_HZ` (events and topology are never thinned)."""
        rate = self.js_rate if demand else min(self.js_rate, IDLE_JS_RATE_HZ)
        sub = self.client.subscribe(
            ["joint_states", "events", "topology"], max_rate=rate, buffer=4096
        )
        self.js_rate_now = rate
        return sub.__enter__()

    def _publish_stream(self, msg: dict, next_viz: float) -> float:
        """Publish one message of the daemon's stream; returns when /tf is due next.

        /tf and /ucr/arcs are due by the joint state's own time (its stamp, the daemon's
        clock), not by when the loop gets to it: a backlog drained in a burst yields the /tf of
        every sample that was due, 1/viz_rate apart in stamp time, as when it came on time."""
        kind = msg.get("kind")
        t = msg.get("t")
        t_ns = self._t_ns(t)
        if kind == "joint_states":
            wants = getattr(self.out, "wants", None) or _everything
            if wants("/joint_states"):
                self.out.publish(self.topics.joint_states(msg, t_ns))
            at = float(t) if isinstance(t, int | float) else time.monotonic()
            if at >= next_viz:
                next_viz = next_due(next_viz, self.viz_period, at)
                # the FK and the CDR of these two are most of a bridge's CPU: only for a reader
                if wants("/tf"):
                    self.out.publish(self.topics.tf(msg, t_ns))
                if wants("/ucr/arcs"):
                    self.out.publish(self.topics.arcs(msg, t_ns))
        elif kind in ("event", "topology"):
            for m in self.topics.event(msg, t_ns):
                self.out.publish(m)
            whole, lost = self.goals_commanded.feed(msg)
            for ev in lost:
                for m in self.topics.event(ev, t_ns):
                    self.out.publish(m)
            if whole is not None:
                cmd = commanded(whole, self.topics.root, t_ns)
                if cmd is not None:
                    self.out.publish(cmd)
            if kind == "topology":
                self._topology_changed = True  # re-read with the next status poll
        return next_viz


#: What ends a feed because the daemon went away (stopped, restarted, unreachable): connect again
LOST = (ApiConnectionError, ApiTimeoutError, StopIteration, ConnectionError)


def run_reconnecting(
    link: DaemonLink,
    make_feed: Callable[[Any], LiveFeed],
    stop: threading.Event,
    connect: Callable[[], Any],
    *,
    robot_text: str,
    robot_path: str | None,
    duration: float | None = None,
    on_tick: Callable[[], None] | None = None,
    say: Callable[[str], None] = print,
) -> int:
    """Run ``make_feed(client)`` until ``stop`` or ``duration`` (s); when the daemon goes away (a
    restart: systemd starts it again 3 s after a failure) say so, publish a ``daemon_lost`` event
    (/rosout, /ucr/events), connect again with :func:`host.api.reconnect.reconnect` (``connect()``
    makes a client), publish ``daemon_reconnected`` (with the gap in s) and go on into the same
    outputs. A daemon back with another robot (its text differs from ``robot_text``) ends it with
    FeedError. Returns the stream messages dropped. ``on_tick`` runs while waiting too (a
    recording's chunks are still flushed, its progress line goes on)."""
    end = None if duration is None else time.monotonic() + duration
    dropped = 0
    while True:
        feed = make_feed(link.client)
        left = None if end is None else max(0.0, end - time.monotonic())
        try:
            feed.run(stop, duration=left, on_tick=on_tick)
            return dropped + feed.dropped
        except LOST as exc:
            why = str(exc) or "the connection closed"
        dropped += feed.dropped  # (each connection's feed counts its own)
        if stop.is_set() or (end is not None and time.monotonic() >= end):
            return dropped
        lost_at = time.monotonic()
        link.lost(why)
        say(f"lost the daemon ({why}); reconnecting, the outputs stay open")
        _gap_event(feed, "daemon_lost", f"lost the daemon ({why}); reconnecting")
        while True:  # until a daemon answers the robot check too (it may drop again meanwhile)
            client = _wait_for_daemon(link, feed, stop, end, connect, on_tick, say)
            if client is None:
                return dropped
            link.replace(client)
            try:
                _robot, text = robot_for(client, robot_path)
                break
            except LOST as exc:
                why = str(exc) or "the connection closed"
                link.lost(why)
                say(f"lost the daemon again ({why}); reconnecting")
        if text != robot_text:
            raise FeedError("the daemon came back with another robot file: stopped (the "
                            "outputs hold the robot until then)")  # fmt: skip
        gap = time.monotonic() - lost_at
        say(f"reconnected to the daemon at {getattr(client, 'url', '?')} after {gap:.1f} s")
        text = f"reconnected to the daemon after {gap:.1f} s without data"
        _gap_event(feed, "daemon_reconnected", text, gap_s=round(gap, 3))


def _wait_for_daemon(
    link: DaemonLink,
    feed: LiveFeed,
    stop: threading.Event,
    end: float | None,
    connect: Callable[[], Any],
    on_tick: Callable[[], None] | None,
    say: Callable[[str], None],
) -> Any:
    """A new client of the daemon (the back-off of :func:`host.api.reconnect.reconnect`), or
    None once ``stop`` is set or the duration ``end`` (monotonic s) passed."""
    from host.api.reconnect import reconnect  # noqa: PLC0415

    halt = threading.Event()

    def tick() -> None:
        if stop.is_set() or (end is not None and time.monotonic() >= end):
            halt.set()
        feed.out.tick()
        if on_tick is not None:
            on_tick()

    def retry(reason: str, attempt: int, next_s: float) -> None:
        link.why = f"{reason} (attempt {attempt}, next in {next_s:.1f} s)"
        if attempt <= 3 or attempt % 12 == 0:  # about once a minute after the first ones
            say(f"daemon still away: {link.why}")

    back = reconnect(connect, halt, retry, tick=tick, tick_s=0.1)
    return None if back is None else back[0]


def _gap_event(feed: LiveFeed, name: str, text: str, **extra: Any) -> None:
    """A gap in the live data as an event on /rosout and /ucr/events (as the daemon's own)."""
    t_ns = feed._t_ns(None)
    ev = {"kind": "event", "event": name, "message": text, **extra}
    for m in feed.topics.event(ev, t_ns):
        feed.out.publish(m)
