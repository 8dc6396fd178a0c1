"""ChainLink against a scripted fake chain on a pty: matching, decoding, errors, stats."""

from __future__ import annotations

import os
import threading
import time

import pytest

from host.link import (
    ChainLink,
    LinkError,
    LinkTimeoutError,
    SegmentError,
)
from protocol import constants as C
from protocol import messages as M
from protocol.cbor import loads
from protocol.frame import FrameReader, encode_frame

UP = C.FLAG_UP
#: required DESCRIPTOR fields (uid, firmware, protocol version, model) and a complete STATE
DESC = {0: "uid", 1: "0.1.0", 2: C.VERSION, 3: "pcc"}


def _state(cycle: int, kappa: float, phi: float, status: int) -> dict:
    """A complete STATE payload (version 2: one packed report under key 0)."""
    return M.state_payload(
        cycle=cycle, t_ms=10, kappa=kappa, phi=phi, servo_angles=[0, 0, 0], status=status
    )


class FakeChain:
    """Answers like two segments: DISCOVER, HEARTBEAT, PARAM_GET (position 1 answers ERROR)."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self.stop = False
        self.received: list = []
        self.truncate_state = False
        self.cycle_shift = 0  # answer with another cycle than the request's (a late answer)
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def send(self, hop: int, mtype: int, seq: int, payload, flags: int = UP) -> None:
        os.write(self.master, encode_frame(flags, hop, mtype, seq, payload))

    def run(self) -> None:
        reader = FrameReader()
        while not self.stop:
            try:
                data = os.read(self.master, 512)
            except OSError:
                return
            for f in reader.feed(data):
                self.received.append(f)
                body = loads(f.payload) if f.payload else {}
                if f.mtype == C.T_DISCOVER:
                    self.send(0, C.T_EVENT, 0, {0: C.EV_BOOT, 1: 0, 2: 5})
                    self.send(1, C.T_DESCRIPTOR, f.seq, {**DESC, 0: "b1", 12: "two", 15: False})
                    self.send(0, C.T_DESCRIPTOR, f.seq, {**DESC, 0: "a0", 12: "one", 15: True})
                elif f.mtype == C.T_HEARTBEAT:
                    self.send(0, C.T_STATE, (f.seq + 1) & 0xFF, {0: 99})  # stale seq: ignored
                    self.send(0, C.T_ALIVE, 0, {}, flags=UP | C.FLAG_LOCAL)
                    cycle = (body[0] - self.cycle_shift) % C.TIME_WRAP
                    state = _state(cycle, 1.2345, -0.5, 0x11)
                    if self.truncate_state:
                        state[0] = state[0][:14]  # cut inside the fixed part: not a valid STATE
                    self.send(0, C.T_STATE, f.seq, state)
                elif f.mtype == C.T_PARAM_GET and f.hop == 1:
                    self.send(1, C.T_ERROR, f.seq, {0: C.ERR_UNKNOWN_PARAM, 1: f.mtype, 2: "no"})
                elif f.mtype == C.T_PARAM_GET and f.hop == 0:
                    self.send(0, C.T_PARAM_VALUE, f.seq, {0: body[0], 1: 42})
                elif f.mtype == C.T_SYNC:
                    cycle = (body[0] - self.cycle_shift) % C.TIME_WRAP
                    self.send(0, C.T_STATE, f.seq, _state(cycle, 0.5, 0.0, 0))

    def close(self) -> None:
        self.stop = True
        os.close(self.master)
        os.close(self.slave)


@pytest.fixture
def fake():
    chain = FakeChain()
    link = ChainLink(chain.path)
    yield chain, link
    link.close()
    chain.close()


def test_discover_sorts_by_source_position_and_stops_at_the_tip(fake) -> None:
    chain, link = fake
    descs = link.discover(timeout=2.0)
    assert [(d["position"], d["uid"], d["name"]) for d in descs] == [
        (0, "a0", "one"),
        (1, "b1", "two"),
    ]
    assert descs[1]["downstream_present"] is False
    # the BOOT position 0 sent before its DESCRIPTOR began the life this first discovery found:
    # not a restart after it (a topology change that aborted the first goal), dropped, counted
    assert link.events() == []
    assert link.stats["boots_before_discovery"] == 1
    chain.send(0, C.T_EVENT, 0, {0: C.EV_BOOT, 1: 0, 2: 7})  # a BOOT after it is a restart
    chain.send(0, C.T_EVENT, 0, {0: C.EV_LIMIT_CLAMPED, 1: 1, 2: 8})
    deadline = time.monotonic() + 2.0
    while link.stats["events"] < 3 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert [e["name"] for e in link.events()] == ["BOOT", "LIMIT_CLAMPED"]
    assert link.events() == []  # drained
    link.discover(timeout=2.0)  # a later discovery drops nothing: a BOOT then is news
    assert [e["name"] for e in link.events()] == ["BOOT"]


def test_heartbeat_matches_by_seq_and_decodes_to_si(fake) -> None:
    chain, link = fake
    states = link.heartbeat(timeout=0.5, expected=1)
    s = states[0]
    assert s["kappa"] == pytest.approx(1.2345) and s["phi"] == pytest.approx(-0.5)
    assert s["status"] == {"HOLD", "DOWNSTREAM"} and s["raw_status"] == 0x11
    stats = link.stats
    assert stats["unmatched"] == 1 and stats["alive"] == 1 and stats["frames_ok"] >= 3


def test_an_incomplete_state_is_counted_and_dropped_not_passed_on(fake) -> None:
    chain, link = fake
    chain.truncate_state = True
    assert link.heartbeat(timeout=0.2, expected=1) == [None]
    assert link.stats["bad_payloads"] == 1


@pytest.mark.parametrize("pipelined", [False, True])
def test_a_state_with_the_seq_but_another_cycle_is_stale_never_this_cycles_state(
    fake, pipelined
) -> None:
    """seq wraps after 256 requests: a STATE answering an older request with the same seq must
    not pass as this cycle's measurement (docs/protocol.md 8.4: the cycle echo tells them apart).
    """
    chain, link = fake
    chain.cycle_shift = 256
    if pipelined:
        states = link.sync_collect(link.sync_send([(1.0, 0.0)]), timeout=0.2)
    else:
        states = link.heartbeat(timeout=0.2, expected=1)
    assert states == [None]
    assert link.stats["stale"] == 1 and link.stats["timeouts"] == 1
    chain.cycle_shift = 0  # the same link goes on matching current answers
    assert link.sync([(1.0, 0.0)], timeout=0.5)[0]["kappa"] == pytest.approx(0.5)


def test_missing_answers_are_none_and_counted_as_timeouts(fake) -> None:
    chain, link = fake
    states = link.heartbeat(timeout=0.1, expected=2)
    assert states[0] is not None and states[1] is None
    assert link.stats["timeouts"] == 1


def test_param_errors_and_timeouts_raise_typed_exceptions(fake) -> None:
    chain, link = fake
    assert link.param_get(0, 6) == 42
    with pytest.raises(SegmentError) as info:
        link.param_get(1, 99)
    assert info.value.code_name == "UNKNOWN_PARAM" and isinstance(info.value, OSError)
    with pytest.raises(LinkTimeoutError):
        link.param_set(2, 0, 5, timeout=0.05)


def test_opening_a_missing_port_raises_link_error() -> None:
    with pytest.raises(LinkError) as info:
        ChainLink("/dev/ttyUSB_does_not_exist")
    assert isinstance(info.value, OSError)


def test_closed_link_refuses_requests(fake) -> None:
    chain, link = fake
    link.close()
    with pytest.raises(LinkError, match="closed"):
        link.discover()


def test_a_discovery_that_finds_nobody_leaves_the_boot_drop_to_the_first_that_finds_some():
    # review: an empty first discovery (a chain still unpowered) used up the one-time drop
    from host.link_frames import _FramePlumbing

    link = _FramePlumbing.__new__(_FramePlumbing)
    link._cond = threading.Condition()
    link._discovered = False
    link._counters = {"boots_before_discovery": 0}
    link._events = __import__("collections").deque([{"name": "BOOT", "position": 0, "t": 1.0}])
    link._drop_boots_before({})  # found nobody
    link._drop_boots_before({0: 2.0})  # found position 0 after its BOOT
    assert list(link._events) == [] and link._counters["boots_before_discovery"] == 1
