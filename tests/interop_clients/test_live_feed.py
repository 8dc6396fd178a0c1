"""interop.live.LiveFeed on a simulated clock: /tf and /ucr/arcs at --viz-rate while joint states
stream at 50 Hz, and no burst after a pause. Counted over simulated time (no wall-clock rates)."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

import pytest

from interop import live
from interop.topics import Message

JS_PERIOD = 0.02  # the daemon's joint states: 50 Hz


class _Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def monotonic(self) -> float:
        return self.t


class _Stream:
    """The daemon's subscription: a joint state every 20 ms of simulated time, except in
    ``pauses`` ((start, end) s after the first), where ``get`` waits its timeout for nothing."""

    dropped_local = dropped_server = 0

    def __init__(self, clock: _Clock, pauses=()) -> None:
        self.clock, self.t0, self.pauses = clock, clock.t, pauses

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        pass

    def get(self, timeout: float):
        at = self.clock.t - self.t0
        if any(a <= at < b for a, b in self.pauses):
            self.clock.t += timeout
            return None
        self.clock.t += JS_PERIOD
        return {"kind": "joint_states"}


class _Daemon:
    def __init__(self, stream: _Stream) -> None:
        self.stream = stream

    def subscribe(self, *args, **kw) -> _Stream:
        return self.stream

    def status(self) -> dict:
        return {"running_goals": []}

    def topology(self) -> dict:
        return {}

    def loop_stats(self) -> dict:
        return {}


class _Topics:
    root = "base"

    def static_messages(self, t_ns):
        return []

    def __getattr__(self, name):  # joint_states, tf, arcs, segments, loop_stats
        return lambda *args: Message(name, "", {}, 0)


class _Out:
    def __init__(self, clock: _Clock) -> None:
        self.clock = clock
        self.sent: list[tuple[str, float]] = []

    def publish(self, m: Message) -> None:
        self.sent.append((m.topic, self.clock.t))

    def tick(self) -> None:
        pass


def _run(monkeypatch, seconds: float, viz_rate: float, pauses=()) -> list[tuple[str, float]]:
    clock = _Clock()
    monkeypatch.setattr(live, "time", SimpleNamespace(monotonic=clock.monotonic, time=time.time))
    out = _Out(clock)
    feed = live.LiveFeed(_Daemon(_Stream(clock, pauses)), _Topics(), out, viz_rate=viz_rate)
    feed.run(threading.Event(), duration=seconds)
    t0 = out.sent[0][1] - JS_PERIOD
    return [(topic, t - t0) for topic, t in out.sent]


@pytest.mark.parametrize("viz_rate", [20.0, 10.0])
def test_tf_and_arcs_go_out_at_the_viz_rate_not_slower(monkeypatch, viz_rate):
    """Defect: the next /tf was scheduled one period after the joint state that triggered it,
    so each period rounded up to the next 50 Hz joint state: 60 ms, ~16.7 Hz instead of 20."""
    sent = _run(monkeypatch, 10.0, viz_rate)
    js = [t for topic, t in sent if topic == "joint_states"]
    assert len(js) == pytest.approx(10.0 / JS_PERIOD, abs=2)
    for topic in ("tf", "arcs"):
        n = sum(1 for name, _ in sent if name == topic)
        assert n == pytest.approx(10.0 * viz_rate, abs=2), (topic, n)


def test_no_burst_of_tf_after_a_pause(monkeypatch):
    """After a pause in the stream the schedule starts again from then: no /tf on consecutive
    joint states to catch up (the due times missed in the pause are dropped), and the rate is
    the viz rate again."""
    sent = _run(monkeypatch, 6.0, 20.0, pauses=[(2.0, 3.0)])
    tf = [t for topic, t in sent if topic == "tf"]
    gaps = [b - a for a, b in zip(tf, tf[1:], strict=False)]
    assert min(gaps) > JS_PERIOD + 1e-6, min(gaps)  # never on two joint states in a row
    after = [t for t in tf if t >= 3.1]
    assert len(after) == pytest.approx((6.0 - 3.1) * 20, abs=2)


class _BurstStream(_Stream):
    """Joint states stamped every 20 ms of the daemon's clock ("t"), delivered in bursts: the
    recorder gets to them ``burst`` at a time (a backlog drained at once), its own clock
    advancing only between bursts."""

    def __init__(self, clock: _Clock, burst: int) -> None:
        super().__init__(clock)
        self.burst, self.n = burst, 0

    def get(self, timeout: float):
        if self.n % self.burst == 0:
            self.clock.t += JS_PERIOD * self.burst
        self.n += 1
        return {"kind": "joint_states", "t": 5000.0 + JS_PERIOD * self.n}


class _StampedTopics(_Topics):
    def __getattr__(self, name):  # the stamp (ns) each message was made for
        return lambda msg, t_ns=0, *rest: Message(name, "", {"t": msg.get("t")}, t_ns)


class _StampOut(_Out):
    def publish(self, m: Message) -> None:
        self.sent.append((m.topic, (m.msg or {}).get("t")))


def test_tf_is_due_by_the_joint_states_stamp_when_a_backlog_is_drained(monkeypatch):
    """Issue 16 audit: /tf was gated on the recorder's clock when it processed a joint state,
    so a backlog drained in a burst gave one /tf for the whole burst (80-140 ms holes in /tf
    and /ucr/arcs while /joint_states flowed). By the samples' stamps, a burst yields the /tf
    of every sample that was due: 40/60 ms apart in stamp time, 20 Hz."""
    clock = _Clock()
    monkeypatch.setattr(live, "time", SimpleNamespace(monotonic=clock.monotonic, time=time.time))
    out = _StampOut(clock)
    feed = live.LiveFeed(_Daemon(_BurstStream(clock, burst=6)), _StampedTopics(), out,
                         viz_rate=20.0)  # fmt: skip
    feed.run(threading.Event(), duration=6.0)
    for topic in ("tf", "arcs"):
        stamps = [t for name, t in out.sent if name == topic]
        gaps = [round(b - a, 6) for a, b in zip(stamps, stamps[1:], strict=False)]
        assert len(stamps) == pytest.approx(6.0 * 20, abs=3), (topic, len(stamps))
        assert set(gaps) <= {0.04, 0.06}, (topic, sorted(set(gaps)))


class _RealStream(_Stream):
    """A joint state every 20 ms of real time."""

    def __init__(self) -> None:
        self.next = time.monotonic()

    def get(self, timeout: float):
        self.next += JS_PERIOD
        time.sleep(max(0.0, self.next - time.monotonic()))
        return {"kind": "joint_states"}


class _SlowDaemon(_Daemon):
    def status(self) -> dict:
        time.sleep(0.4)  # a loaded daemon answering a poll
        return {"running_goals": []}


def test_slow_status_polls_do_not_hold_back_the_joint_states():
    """Issue 16 audit: the status, goal and statistics polls ran in the publishing loop, so
    each round trip held the joint states back (written in a burst up to 228 ms late). They
    run in their own thread now: a 0.4 s poll leaves the joint states flowing."""
    t_real: list[float] = []

    class Out(_Out):
        def publish(self, m: Message) -> None:
            if m.topic == "joint_states":
                t_real.append(time.monotonic())

    feed = live.LiveFeed(_SlowDaemon(_RealStream()), _Topics(), Out(None), status_period=0.5)
    feed.run(threading.Event(), duration=3.0)
    gaps = sorted(b - a for a, b in zip(t_real, t_real[1:], strict=False))
    assert len(t_real) > 100 and gaps[-3] < 0.2, gaps[-5:]  # a hiccup of the machine aside


def test_a_topic_no_output_wants_is_neither_computed_nor_sent(monkeypatch):
    """`ucr zenoh` with no subscriber spent about a quarter of a core on FK and CDR for /tf,
    /ucr/arcs and /joint_states that went nowhere (252 ms/s; 26 with this): the feed asks its
    output first, and an output that cannot say (a recording) still gets everything."""
    clock = _Clock()
    monkeypatch.setattr(live, "time", SimpleNamespace(monotonic=clock.monotonic, time=time.time))
    built: list[str] = []

    class Topics(_Topics):
        def __getattr__(self, name):
            def make(*args):
                built.append(name)
                return Message(name, "", {}, 0)

            return make

    wanted = {"/tf"}

    class Picky(_Out):
        def wants(self, topic: str) -> bool:
            return topic in wanted

    out = Picky(clock)
    live.LiveFeed(_Daemon(_Stream(clock)), Topics(), out, viz_rate=20.0).run(
        threading.Event(), duration=2.0
    )
    assert "tf" in built and "arcs" not in built and "joint_states" not in built
    sent = {topic for topic, _ in out.sent}  # (+ the 1 Hz polled ones: segments, loop_stats)
    assert "tf" in sent and not sent & {"arcs", "joint_states"}
    wanted.update({"/joint_states", "/ucr/arcs"})  # a subscriber came: everything again
    built.clear()
    live.LiveFeed(_Daemon(_Stream(clock)), Topics(), out, viz_rate=20.0).run(
        threading.Event(), duration=1.0
    )
    assert {"tf", "arcs", "joint_states"} <= set(built)
