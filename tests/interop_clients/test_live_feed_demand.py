"""The live feed takes the daemon's joint states at the full rate only while an output wants
them (review 2026-11-28: `ucr zenoh` took all 50 a second with nobody subscribed, so the
daemon's process encoded and sent them and the bridge decoded them for nothing). With no reader
it asks for 2 a second; a reader appearing gets the full stream again within a check period;
across the change each joint state and each event is published once, in order."""

from __future__ import annotations

import queue
import threading
import time

from interop import live
from interop.topics import Message

from .test_live_feed import _Daemon as _PolledDaemon

JS_PERIOD = 0.02


class _Sub:
    def __init__(self, max_rate: float) -> None:
        self.max_rate, self.q, self.closed, self.last = max_rate, queue.Queue(), False, None
        self.dropped_local = self.dropped_server = 0

    def offer(self, msg: dict) -> None:
        """What the API does for this subscription: joint states thinned by its max_rate."""
        if self.closed:
            return
        if msg["kind"] == "joint_states":
            if self.last is not None and msg["t"] - self.last < 0.9 / self.max_rate:
                return
            self.last = msg["t"]
        self.q.put(msg)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.closed = True

    def get(self, timeout: float):
        try:
            return self.q.get(timeout=max(timeout, 0.0)) if timeout else self.q.get_nowait()
        except queue.Empty:
            if self.closed:
                raise StopIteration from None
            return None


class _Daemon(_PolledDaemon):
    """test_live_feed's daemon (its status, topology and loop_stats polls), here publishing a
    joint state every 20 ms to every open subscription; when the feed opens its second
    subscription, an event and a joint state reach the old and the new one both (what arrives
    while they overlap). Its stream is its subscriptions, not the base's one stream."""

    def __init__(self) -> None:
        self.subs: list[_Sub] = []
        self.lock = threading.Lock()
        self.t = 1000.0
        self.stop = threading.Event()
        threading.Thread(target=self._publish, daemon=True).start()

    def _fan(self, msg: dict) -> None:
        with self.lock:
            for s in self.subs:
                s.offer(msg)

    def _publish(self) -> None:
        while not self.stop.wait(JS_PERIOD):
            self.t += JS_PERIOD
            self._fan({"kind": "joint_states", "t": self.t, "names": []})

    def subscribe(self, kinds, max_rate, buffer) -> _Sub:
        sub = _Sub(max_rate)
        with self.lock:
            self.subs.append(sub)
        if len(self.subs) == 2:
            self._fan({"kind": "event", "t": self.t, "event": "overlap", "message": "both"})
            self.t += JS_PERIOD
            self._fan({"kind": "joint_states", "t": self.t, "names": []})
        return sub


class _Topics:
    root = "base"

    def __init__(self) -> None:
        self.js: list[float] = []
        self.events: list[str] = []

    def static_messages(self, t_ns):
        return []

    def joint_states(self, msg, t_ns):
        self.js.append(msg["t"])
        return Message("/joint_states", "", {}, t_ns)

    def event(self, msg, t_ns):
        self.events.append(msg.get("event", ""))
        return []

    def __getattr__(self, name):  # tf, arcs, segments, loop_stats
        return lambda *args: Message(name, "", {}, 0)


class _Out:
    def __init__(self) -> None:
        self.reader = False

    def wants(self, topic: str) -> bool:
        return self.reader

    def publish(self, m: Message) -> None:
        pass

    def tick(self) -> None:
        pass


def test_the_stream_runs_at_full_rate_only_while_someone_reads_it() -> None:
    daemon, topics, out = _Daemon(), _Topics(), _Out()
    feed = live.LiveFeed(daemon, topics, out, js_rate=1000.0)
    stop = threading.Event()
    seen: list[float] = []

    def becomes(rate: float) -> None:
        end = time.monotonic() + 10.0
        while feed.js_rate_now != rate and time.monotonic() < end:
            time.sleep(0.01)
        seen.append(feed.js_rate_now)

    def script() -> None:
        time.sleep(0.8)
        out.reader = True
        becomes(1000.0)
        time.sleep(1.0)  # read at the full rate for a second
        out.reader = False
        becomes(2.0)
        time.sleep(0.6)
        stop.set()

    th = threading.Thread(target=script)
    th.start()
    feed.run(stop, duration=30.0)
    th.join()
    daemon.stop.set()
    # nobody -> 2 Hz; a reader -> the full rate within a check period; nobody again -> 2 Hz
    assert [s.max_rate for s in daemon.subs] == [2.0, 1000.0, 2.0]
    assert seen == [1000.0, 2.0], seen
    assert all(s.closed for s in daemon.subs)
    # each joint state once and in time order; each event once, the overlap's too
    assert topics.js == sorted(set(topics.js)), topics.js
    assert topics.events.count("overlap") == 1, topics.events
    # while read (a second or more) the full 50 a second, else about 2 a second: about 55 in
    # all, where the whole stream would have been about 120 (fewer on a loaded machine)
    assert 15 <= len(topics.js) <= 100, len(topics.js)
