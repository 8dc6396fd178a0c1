"""The parts split out of the daemon, the topology follower and the API server work alone, through
the interfaces they are given: the usable rate (link health -> events, period), the chain report,
and the API server's outboxes and request side."""

from __future__ import annotations

import asyncio
import collections
from types import SimpleNamespace

from host.api import schema as S
from host.api.connection import Outboxes
from host.api.dispatch import Dispatcher
from host.api.session import _Subscription
from host.chain_report import rate_warning, rebuild_message
from host.link_health import LinkHealth
from host.usable_rate import UsableRate


def _usable_rate() -> tuple[LinkHealth, UsableRate, SimpleNamespace, list[float]]:
    """A 100 Hz usable rate (floor 10 Hz) on a link with one late-reply counter; the periods
    it applies."""
    periods: list[float] = []
    health = LinkHealth(0.01, 0.8, min_rate_hz=10.0)
    rate = UsableRate(health, 100.0, lambda kind, **kw: None, periods.append)
    link = SimpleNamespace(stats={"unmatched": 0})
    rate.start(link)
    return health, rate, link, periods


def test_usable_rate_slows_the_loop_through_its_callback_and_reports_which_link():
    events: list[tuple[str, dict]] = []
    periods: list[float] = []
    rate = UsableRate(
        LinkHealth(0.01, 0.8, min_rate_hz=10.0),
        100.0,
        lambda kind, **kw: events.append((kind, kw)),
        periods.append,
    )
    link = SimpleNamespace(stats={"unmatched": 0})
    rate.start(link)
    hwi = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008,
        reply_timeout=0.008,
    )  # fmt: skip
    for k in range(40):  # position 1 never answers in time, its replies come late
        link.stats["unmatched"] += 1
        rate.observe(hwi, link, 0.01 * k)
    assert periods == [0.02]
    (kind, ev), *_ = events
    assert kind == "link_degraded" and ev["segment"] == "segment_2" and ev["link"] == 2
    assert "loop slowed to 50.0 Hz (nominal 100.0 Hz)" in ev["message"]


def test_exchanges_held_up_in_the_daemons_own_process_do_not_slow_the_loop():
    """A garbage collection (or any thread holding the interpreter lock) stalls the link reader
    and the loop alike: replies miss their exchange and arrive late — what a slow link looks
    like — but the exchange itself returns long after its reply timeout, which a slow link's
    never does. Such exchanges are left out (counted), so the daemon does not halve its rate
    for its own stalls."""
    health, rate, link, periods = _usable_rate()
    stalled = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008 + 0.015,
        reply_timeout=0.008,
    )  # fmt: skip
    for k in range(40):
        link.stats["unmatched"] += 1
        rate.observe(stalled, link, 0.01 * k)
    assert periods == [] and health.host_stalls == 40
    assert health.snapshot()["host_stalls"] == 40 and not health.snapshot()["degraded"]
    # supervision's silent stretch right after it is the process's too
    link.stats["unmatched"] += 1
    rate.stall(stalled, link, 1, 0.4)
    assert periods == []
    # later, a stretch that is the link's own: exchanges on time, position 1 missing and its
    # replies coming late (the documented rule: >= 60 % missed and >= 3 late replies)
    slow = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008,
        reply_timeout=0.008,
    )  # fmt: skip
    for k in range(5):
        link.stats["unmatched"] += 1
        rate.observe(slow, link, 2.0 + 0.01 * k)
    assert periods == []  # (a window is not full yet)
    rate.stall(slow, link, 1, 2.1)
    assert periods == [0.02]


def test_chain_report_words_a_cut_and_a_rate_the_chain_cannot_carry():
    cmp = SimpleNamespace(differences=[])
    cut = {"after": "segment_1", "after_position": 1, "lost": ["segment_2", "segment_3"]}
    msg = rebuild_message(["segment_1"], cut, cmp)
    assert msg == (
        "now 1 segment(s): segment_1; chain cut after segment_1 (position 1): "
        "segment_2, segment_3 unreachable"
    )
    assert rate_warning(3, 1_000_000, 0.004, 0.004, 200.0) is None
    slow = rate_warning(8, 9600, 0.004, 0.004, 200.0)
    assert slow is not None and "8 segment(s) at 9600 baud" in slow and "rate_hz <=" in slow


def _session():
    return SimpleNamespace(
        subs={},
        stream=collections.deque(),
        priority=collections.deque(),
        queued_bytes=0,
        closed=False,
        wakeup=asyncio.Event(),
        t_progress=0.0,
        upload=None,
        scope="control",
    )


def _opts(**over):
    base = dict(
        outbox_size=2,
        outbox_bytes=1 << 20,
        global_outbox_bytes=1 << 20,
        max_subscriptions=4,
        upload_points_total=3,
        max_request_bytes=S.MAX_REQUEST_BYTES,
        goal_poll_s=0.1,
    )
    return SimpleNamespace(**{**base, **over})


def test_outboxes_fan_out_by_kind_drop_the_oldest_and_send_progress_first():
    wanted: list[dict] = []
    counters = {"dropped": 0}
    out = Outboxes(_opts(), counters, wanted.append)
    session = _session()
    sub = _Subscription(1, ["joint_states"], None)
    session.subs[1] = sub
    out.add(session, sub)
    assert wanted[-1] == {"joint_states": None}  # unthinned: every message
    for k in range(3):
        out.publish("joint_states", f'{{"k":{k}}}')
    out.publish("events", '{"e":1}')  # nobody subscribed
    out.push_priority(session, "progress")
    assert counters["dropped"] == 1 and sub.dropped == 1 and sub.sent == 3
    sent = []
    while (text := out.take(session)) is not None:
        sent.append(text)
    assert sent[0] == "progress" and [t[-7:] for t in sent[1:]] == ['"k":1}}', '"k":2}}']
    assert out.queued_bytes == 0 and session.queued_bytes == 0
    out.drop(session)
    assert wanted[-1] == {}


def test_dispatcher_alone_bounds_uploads_and_registers_subscriptions_with_the_outboxes():
    counters = {k: 0 for k in ("requests", "errors", "forbidden", "dropped")}
    out = Outboxes(_opts(), counters, lambda kinds: None)

    async def call(name, *args):
        raise AssertionError(f"no daemon call expected, got {name}")

    d = Dispatcher(_opts(), counters, out, call, lambda: None, list)
    session = _session()

    def ask(op, **params):
        frame = S.encode({"id": 1, "op": op, **params})
        return asyncio.run(d.serve_frame(session, frame))

    pts = [{"time_from_start": t, "segments": {"s": {"kx": 0.0, "ky": 0.0}}} for t in (1, 2)]
    up = ask("trajectory.upload", points=pts)
    assert up["ok"] and d.upload_points == 2
    more = [{"time_from_start": t, "segments": {"s": {"kx": 0.0, "ky": 0.0}}} for t in (3, 4)]
    over = ask("trajectory.upload", points=more, upload=up["result"]["upload"])
    assert not over["ok"] and "too many uploads" in over["error"]["message"]
    d.end_upload(session)
    assert d.upload_points == 0
    sub = ask("subscribe", kinds=["events"])
    assert sub["ok"] and out.by_kind["events"]
    assert ask("status")["error"]["message"] == "no status from the daemon yet"


def test_outboxes_forget_a_removed_subscription():
    kinds = ["joint_states", "events"]
    wanted: list[dict] = []
    out = Outboxes(_opts(), {"dropped": 0}, wanted.append)
    sub = _Subscription(7, kinds, None)
    out.add(_session(), sub)
    out.remove(sub)
    assert wanted == [dict.fromkeys(kinds), {}]
    assert all(not subs for subs in out.by_kind.values())


def test_a_slow_links_exchanges_are_not_taken_for_held_up_ones_for_their_send_and_decode():
    """Held up means the wait for replies woke past its deadline (the link's
    ``wait_overrun_s``, copied by the HWI as ``wait_overrun_s``). Before: the whole exchange
    (sending the SYNC, decoding the STATEs: 2-6 ms over on a loaded 2-core host) was compared with
    the reply time, so nearly every exchange of a slow link counted as held up; the window
    filled from the few left and the stall path was held off — at 50 Hz the daemon waited
    for 7-10 silent stretches instead of 1 before slowing again."""
    health, rate, link, periods = _usable_rate()
    slow = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008 + 0.003,
        reply_timeout=0.008, wait_overrun_s=0.0002, exchanges=0,
    )  # fmt: skip
    for k in range(5):
        slow.exchanges += 1
        link.stats["unmatched"] += 1
        rate.observe(slow, link, 0.01 * k)
    assert health.host_stalls == 0
    rate.stall(slow, link, 1, 0.06)  # the first silent stretch slows the loop
    assert periods == [0.02]
    # a wait that did wake 15 ms late is the process's: left out, as before
    slow.wait_overrun_s = 0.015
    slow.exchanges += 1
    rate.observe(slow, link, 0.1)
    assert health.host_stalls == 1


def test_an_exchange_is_observed_once_however_many_cycles_read_it():
    """A cycle that ends in supervision (a stall, a rebuild) sends no exchange; the next one
    reads no new states and hands the link health the same exchange again. Before: it was
    counted each time (one miss counted twice)."""
    health, rate, link, periods = _usable_rate()
    hwi = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.004,
        reply_timeout=0.008, exchanges=7,
    )  # fmt: skip
    for k in range(40):
        link.stats["unmatched"] += 1
        rate.observe(hwi, link, 0.01 * k)
    assert len(health._answered) == 1 and periods == []
    hwi.exchanges += 1  # a new exchange counts
    rate.observe(hwi, link, 0.5)
    assert len(health._answered) == 2


def test_a_stall_counts_the_late_replies_of_its_whole_stretch_of_misses():
    """Silent stretches follow one another while a slow link keeps replies late; the window
    holds the misses of all of them. Before: the late replies were counted from the last stall
    only, fell below half the window's misses, and the stall was taken for a lossy link's
    (at 50 Hz the loop slowed again only once the window was full)."""
    health, rate, link, periods = _usable_rate()
    hwi = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008,
        reply_timeout=0.008, wait_overrun_s=0.0, exchanges=0,
    )  # fmt: skip

    def exchanges(n: int, t: float, late: int) -> float:
        for _ in range(n):
            hwi.exchanges += 1
            link.stats["unmatched"] += late  # late replies arriving meanwhile
            rate.observe(hwi, link, t)
            t += 0.01
        return t

    t = exchanges(6, 0.0, 0)
    link.stats["unmatched"] += 2  # the first late replies: the rest are still on their way
    rate.stall(hwi, link, 1, t)  # 2 late: too few to tell yet
    assert periods == []
    t = exchanges(4, t, 1)
    rate.stall(hwi, link, 1, t)  # 6 late replies in the stretch, 10 misses in the window
    assert periods == [0.02]


def test_late_replies_count_afresh_after_any_change_of_rate_and_after_an_excused_stall():
    """Review: a rate lowered by a full window left the count where the stretch began, so a
    stall at the new rate counted the faster rate's late replies (and slowed again for a link
    that had turned lossy); a stall excused by the process's own hold-up must not leave the
    late replies of its held-up exchanges (left out of the window) to the next one."""
    health, rate, link, periods = _usable_rate()
    hwi = SimpleNamespace(
        names=["segment_1", "segment_2"], raw_states=[{}, None], exchange_s=0.008,
        reply_timeout=0.008, wait_overrun_s=0.0, exchanges=0,
    )  # fmt: skip
    t = 0.0
    for _ in range(30):  # slow: every reply late; the window slows the loop to 50 Hz
        hwi.exchanges += 1
        link.stats["unmatched"] += 1
        rate.observe(hwi, link, t)
        t += 0.01
    assert periods == [0.02]
    for _ in range(5):  # now lossy: replies missing, none late
        hwi.exchanges += 1
        rate.observe(hwi, link, t)
        t += 0.02
    rate.stall(hwi, link, 1, t)
    assert periods == [0.02]  # (before: slowed to 25 Hz, "its replies come late")
    # a stall excused by a hold-up moves the count past its late replies
    health2, rate2, link2, periods2 = _usable_rate()
    hwi.exchanges = 0
    for k in range(8):
        hwi.exchanges += 1
        link2.stats["unmatched"] += 1
        hwi.wait_overrun_s = 0.01 if k == 7 else 0.0  # the last one held up
        rate2.observe(hwi, link2, 0.01 * k)
    rate2.stall(hwi, link2, 1, 0.08)  # excused
    hwi.wait_overrun_s = 0.0
    for k in range(4):  # no late reply since
        hwi.exchanges += 1
        rate2.observe(hwi, link2, 0.7 + 0.01 * k)
    rate2.stall(hwi, link2, 1, 0.75)
    assert periods2 == []


def test_a_stall_at_the_floor_rate_reports_the_link_too_slow():
    """A link too slow for the floor keeps the chain silent: supervision's stalls (and rebuilds)
    may never leave a full window at the floor. Before: the stall path did nothing there, and
    only a full window could report the link too slow."""
    health = LinkHealth(0.01, 0.8, min_rate_hz=10.0)
    health.period = health.min_period  # slowed to the floor already
    for k in range(9):
        health.observe([True, False], 0.08, 0.1 * k, lambda k=k: [0, k + 1], reply_timeout=0.08)
    assert health.stall(1, 5, 0.9) is None  # under a second at the floor: a backlog may drain
    health.observe([True, False], 0.08, 0.9, lambda: [0, 10], reply_timeout=0.08)
    change = health.stall(1, 5, 1.0)
    assert change is not None and change["change"] == "too_slow" and change["link"] == 2
    assert health.too_slow is not None and health.stall(1, 5, 1.1) is None  # once
