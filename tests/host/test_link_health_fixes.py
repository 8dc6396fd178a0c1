"""Link health, review defects (docs/daemon.md "Degrade, don't stall"):

- a DISCOVER is sent again no sooner than one descriptor's time at the configured baud rate
  (a healthy chain at a low baud rate answers once, not twice) and never while bytes arrive;
- the line's byte-rate samples are appended under the link's lock (line_rate_bps iterates
  them: "deque mutated during iteration" otherwise);
- a discovery never outlasts the caller's timeout, also on a line measured slow;
- ``too_slow`` is re-evaluated: a link partly restored climbs to the rate it now carries;
- ``lossy`` is cleared (with ``link_loss_cleared``) when its link leaves the chain or the chain
  is rebuilt;
- while a position misses, the link's counters are read at most every 100 ms;
- a frame that fails its check takes its streamed read samples with it (they never make the
  next good frame's source position look slow).
"""

from __future__ import annotations

import threading
import time
import types
from collections import deque

import pytest

from host.link import ChainLink
from host.link_health import DEGRADE_WINDOW, LinkHealth
from host.usable_rate import UsableRate
from tools.emulator import EmulatedChain

pytestmark = [pytest.mark.timeout(120), pytest.mark.alone]  # recovery times: conftest.py


def _tx_during_discover(link: ChainLink, timeout: float) -> tuple[int, float]:
    before = link.stats["tx_frames"]
    t = time.monotonic()
    try:
        link.discover(timeout=timeout)
    except OSError:
        pass
    return link.stats["tx_frames"] - before, time.monotonic() - t


def test_discover_resend_waits_one_descriptor_time_at_the_configured_baud():
    with ChainLink("loop://", baudrate=19200) as link:  # nothing answers on a loop
        sent, _ = _tx_during_discover(link, 0.3)
    # one descriptor at 19200 baud is ~104 ms: at most the first send and one resend
    assert sent <= 2
    with ChainLink("loop://") as link:  # 921600: a lost DISCOVER is still resent promptly
        sent, _ = _tx_during_discover(link, 0.3)
    assert sent >= 3


def test_no_discover_resend_while_bytes_arrive():
    with ChainLink("loop://") as link:
        stop = threading.Event()

        def stream() -> None:  # bytes of a frame under way, every 5 ms
            while not stop.is_set():
                with link._write_lock:
                    link._ser.write(b"\x05\x01\x02\x03")
                time.sleep(0.005)

        th = threading.Thread(target=stream)
        th.start()
        try:
            time.sleep(0.05)
            sent, _ = _tx_during_discover(link, 0.3)
        finally:
            stop.set()
            th.join()
    assert sent == 1


def test_a_healthy_chain_at_a_low_baud_rate_answers_one_discover():
    with EmulatedChain(3) as ch:
        time.sleep(1.5)
        ch.set_all_links(baud=19200)
        with ChainLink(ch.host_port, baudrate=19200) as link:
            time.sleep(0.3)
            for _ in range(3):
                sent, _ = _tx_during_discover(link, 2.0)
                time.sleep(0.5)
                assert sent == 1
            descs = link.discover(timeout=2.0)
            states = link.sync([None] * len(descs), timeout=0.3)
    assert len(descs) == 3
    assert all(s is not None for s in states)  # no duplicate descriptors queued before it


def test_rate_samples_are_appended_under_the_lock():
    class Checked(deque):
        def append(self, item) -> None:
            owned.append(link._cond._is_owned())
            super().append(item)

    owned: list[bool] = []
    with ChainLink("loop://") as link:
        link._rate_samples = Checked(maxlen=32)
        for _ in range(5):  # a frame's bytes in pieces 2 ms apart: mid-frame reads
            for _ in range(10):
                with link._write_lock:
                    link._ser.write(b"\x07\x01\x02")
                time.sleep(0.002)
            with link._write_lock:
                link._ser.write(b"\x00")
    assert owned, "no stream sample was taken"
    assert all(owned)


def test_discover_never_outlasts_its_timeout_on_a_line_measured_slow():
    with ChainLink("loop://") as link:
        link.discover_need_s = lambda: 1.0  # measured slow: its descriptors would need 1 s
        _, took = _tx_during_discover(link, 0.12)
    assert took < 0.3


def _health_at_floor_too_slow() -> LinkHealth:
    h = LinkHealth(0.01, 0.8, min_rate_hz=10.0)
    h.period = h.min_period
    h.too_slow_now(0, 0.6)
    return h


def test_too_slow_is_cleared_and_the_rate_climbs_when_the_line_carries_more():
    h = _health_at_floor_too_slow()
    changes = []
    t = 0.0
    for _ in range(20):  # 2 s of complete exchanges of 37 ms: fit 10 Hz, not 100 Hz
        t += h.period
        c = h.observe([True] * 3, 0.037, t, lambda: [0, 0, 0], reply_timeout=0.8 * h.period)
        if c is not None:
            changes.append(c)
    assert [c["change"] for c in changes] == ["eased"]
    assert changes[0]["too_slow_cleared"] is True
    assert h.too_slow is None
    assert 0.04 < h.period < 0.07  # ~17 Hz: what 37 ms exchanges need, a quarter to spare


def test_eased_is_reported_and_applied():
    events, periods = [], []
    h = _health_at_floor_too_slow()
    ur = UsableRate(h, 100.0, lambda name, **kw: events.append((name, kw)), periods.append)
    hwi = types.SimpleNamespace(
        raw_states=[{}] * 3, exchange_s=0.037, reply_timeout=0.08, names=["a", "b", "c"]
    )
    link = types.SimpleNamespace(stats={}, baudrate=921600)
    t = 0.0
    for _ in range(20):
        t += 0.1
        ur.observe(hwi, link, t)
    assert periods and periods[-1] == h.period < 0.1
    assert [e[0] for e in events] == ["link_recovered"]
    assert "no longer too slow" in events[0][1]["message"]
    assert h.snapshot()["too_slow"] is None


def _lossy_health() -> tuple[LinkHealth, float]:
    h = LinkHealth(0.01, 0.8, min_rate_hz=10.0)
    t = 0.0
    for _ in range(2 * DEGRADE_WINDOW + 1):
        t += 0.01
        h.observe([True, True, False], 0.002, t, lambda: [0, 0, 0], reply_timeout=0.008)
    assert h.lossy is not None and h.lossy["link"] == 3
    return h, t


def test_lossy_is_cleared_when_its_link_leaves_the_chain():
    h, t = _lossy_health()
    c = h.observe([True, True], 0.002, t + 0.01, lambda: [0, 0], reply_timeout=0.008)
    assert c is not None and c["change"] == "loss_cleared" and c["link"] == 3
    assert c["reason"] == "left_chain"
    assert h.lossy is None and h.snapshot()["lossy"] is None


def test_lossy_is_cleared_by_reset_with_the_cleared_event():
    h, t = _lossy_health()
    events = []
    ur = UsableRate(h, 100.0, lambda name, **kw: events.append((name, kw)), lambda p: None)
    h.lossy["segment"] = "segment_3"
    ur.reset()  # a rebuild
    assert h.lossy is None
    hwi = types.SimpleNamespace(
        raw_states=[{}] * 2, exchange_s=0.002, reply_timeout=0.008, names=["a", "b"]
    )
    ur.observe(hwi, types.SimpleNamespace(stats={}), t + 0.01)
    assert [e[0] for e in events] == ["link_loss_cleared"]
    assert events[0][1]["segment"] == "segment_3"


def test_a_missing_position_reads_the_link_counters_at_most_every_100_ms():
    reads = {"stats": 0, "late": 0}

    class Link:
        baudrate = 921600

        @property
        def stats(self):
            reads["stats"] += 1
            return {"crc_errors": 0, "framing_errors": 0}

        def late_by_position(self):
            reads["late"] += 1
            return [0] * 8

    h = LinkHealth(0.01, 0.8, min_rate_hz=10.0)
    ur = UsableRate(h, 100.0, lambda *a, **k: None, lambda p: None)
    link = Link()
    ur.start(link)
    hwi = types.SimpleNamespace(
        raw_states=[{}] * 7 + [None], exchange_s=0.002, reply_timeout=0.008, names=list("abcdefgh")
    )
    t = 0.0
    for _ in range(100):  # 1 s at 100 Hz
        t += 0.01
        ur.observe(hwi, link, t)
    assert reads["stats"] <= 12
    assert reads["late"] <= 13  # + the one look per stretch of misses


def test_a_short_discovery_on_a_slow_line_leaves_its_answers_to_the_next_try():
    with ChainLink("loop://") as link:
        link.discover_need_s = lambda: 1.0  # measured slow: its descriptors would need 1 s
        _tx_during_discover(link, 0.05)
        sent, took = _tx_during_discover(link, 0.05)  # the next try: the same DISCOVER
        assert sent == 0 and took < 0.2
        assert link._discover_open is not None  # still collecting


def test_a_frame_that_fails_its_check_lends_no_read_samples_to_the_next_frame():
    """A slow link corrupting frames from position 3 must not make position 1 (whose frames
    come whole, fast) look slow: the corrupted frame's streamed reads are discarded with it,
    not counted for the next good frame's source position."""
    import os

    from protocol import constants as C
    from protocol.frame import encode_frame

    master, slave = os.openpty()
    link = ChainLink(os.ttyname(slave), 115200)
    try:
        boot = {0: C.EV_BOOT, 1: 0, 2: 5}
        for _ in range(8):
            bad = bytearray(encode_frame(C.FLAG_UP, 2, C.T_EVENT, 0, boot))
            bad[5] ^= 0x55  # corrupted on its way: fails its check
            for b in bad:  # trickles in, a byte every 2 ms (a slow link)
                os.write(master, bytes([b]))
                time.sleep(0.002)
            os.write(master, encode_frame(C.FLAG_UP, 0, C.T_EVENT, 0, boot))  # whole, at once
            time.sleep(0.05)
        deadline = time.monotonic() + 5
        while link.stats["events"] < 8 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert link.stats["events"] == 8  # the 8 good frames; the 8 bad ones dropped
        rates = link.line_rate_by_position(at_least=1)
        assert all(r is None or r > 100_000 for r in rates), rates
    finally:
        link.close()
        os.close(master)
        os.close(slave)
