"""The serial side cannot kill or stall the host (issue 13, finding 1).

Every byte from the chain is untrusted: a frame whose payload has the wrong shape (a float +inf
as an EVENT code, huge ints, NaN, wrong types, deep nesting, a non-map ERROR) is counted as a bad
payload and dropped; the link's reader thread never dies from it, and if it ends for any other
reason that is a link failure the daemon's reopen path handles.
"""

from __future__ import annotations

import os
import threading
import time
import tty

import cbor2
import pytest
from daemon_helpers import wait_for
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from host.daemon import Daemon
from host.link import ChainLink, LinkError, SegmentError
from protocol import constants as C
from protocol.frame import encode_frame

pytestmark = pytest.mark.timeout(300)

NAMES = ["segment_1", "segment_2", "segment_3"]
_ENDED = ("succeeded", "aborted", "canceled")


# ------------------------------------------------------------------ a link on a bare pty
class _PtyChain:
    """A ChainLink on one end of a pty; the test writes the 'segments' bytes on the other."""

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        self._slave = slave
        self.link = ChainLink(self.path, exclusive=False)

    def send(self, mtype: int, payload: object, *, hop: int = 0, seq: int = 0) -> None:
        raw = payload if isinstance(payload, bytes) else cbor2.dumps(payload)
        os.write(self.master, encode_frame(C.FLAG_UP, hop, mtype, seq, raw))

    def close(self) -> None:
        self.link.close()
        os.close(self.master)
        os.close(self._slave)


@pytest.fixture()
def pty_chain():
    pc = _PtyChain()
    yield pc
    pc.close()


def _wait_count(link: ChainLink, key: str, n: int, timeout: float = 5.0) -> bool:
    return wait_for(lambda: link.stats[key] >= n, timeout)


def test_event_with_an_infinite_code_is_a_bad_payload_and_the_reader_lives(pty_chain):
    link = pty_chain.link
    pty_chain.send(C.T_EVENT, {C.KE_CODE: float("inf"), C.KE_DETAIL: 0, C.KE_T_MS: 1})
    assert _wait_count(link, "bad_payloads", 1)
    pty_chain.send(C.T_EVENT, {C.KE_CODE: C.EV_BOOT, C.KE_DETAIL: 0, C.KE_T_MS: 1})
    assert wait_for(lambda: link.stats["events"] >= 1, 5.0)
    assert link._thread.is_alive()
    (ev,) = link.events()
    assert ev["name"] == "BOOT"


@pytest.mark.parametrize(
    "payload",
    [
        {C.KE_CODE: float("nan")},
        {C.KE_CODE: 10**30},  # a CBOR bignum (tag 2): the decoder refuses tags
        {C.KE_CODE: -1},
        {C.KE_CODE: "BOOT"},
        {C.KE_CODE: True},
        {C.KE_CODE: [1]},
        [C.EV_BOOT, 0, 0],
        "text",
        {C.KE_CODE: C.EV_BOOT, C.KE_DETAIL: float("inf"), C.KE_T_MS: [[[[[[[[[[0]]]]]]]]]]},
    ],
    ids=repr,
)
def test_events_of_the_wrong_shape_never_stop_the_reader(pty_chain, payload):
    link = pty_chain.link
    pty_chain.send(C.T_EVENT, payload)
    pty_chain.send(C.T_EVENT, {C.KE_CODE: C.EV_WATCHDOG_CLEARED, C.KE_DETAIL: 0, C.KE_T_MS: 2})
    assert wait_for(lambda: link.stats["events"] >= 1, 5.0)
    assert link._thread.is_alive()
    for ev in link.events():
        assert isinstance(ev["code"], int)
        assert ev["detail"] is None or isinstance(ev["detail"], int)
        assert ev["t_ms"] is None or isinstance(ev["t_ms"], int)


@pytest.mark.parametrize(
    "payload",
    [["not", "a", "map"], "text", 7, {C.KR_CODE: float("inf")}, {C.KR_CODE: 2**63, C.KR_TEXT: 5}],
    ids=repr,
)
def test_param_get_answered_by_a_malformed_error_raises_segment_error(pty_chain, payload):
    link = pty_chain.link
    result: dict = {}

    def ask() -> None:
        try:
            link.param_get(0, 1, timeout=5.0)
        except Exception as exc:  # noqa: BLE001 - the test inspects it
            result["exc"] = exc

    t = threading.Thread(target=ask)
    t.start()
    assert wait_for(lambda: link.stats["tx_frames"] >= 1, 5.0)
    pty_chain.send(C.T_ERROR, payload, seq=link._seq)
    t.join(10)
    assert isinstance(result.get("exc"), SegmentError), result
    assert link._thread.is_alive()


def test_an_unexpected_reader_exit_is_a_link_failure(pty_chain):
    link = pty_chain.link

    def broken_read(*_a: object) -> bytes:
        raise RuntimeError("driver bug")

    link._ser.read = broken_read  # an exception of a type nobody expected
    assert wait_for(lambda: not link._thread.is_alive(), 5.0)
    with pytest.raises(LinkError):
        link.heartbeat(timeout=0.05, expected=1)


# ------------------------------------------------------------------ the daemon on a real chain
def _controls_the_chain(d: Daemon, attempts: int = 5) -> None:
    """The daemon is connected and drives all three segments through a slow trajectory to a bend
    and back (retried a few times: on a loaded machine a goal may abort on path tolerance)."""
    for attempt in range(attempts):
        assert wait_for(
            lambda: d.status()["state"] == "connected" and d.status()["segments"] == NAMES, 20.0
        ), d.status()
        try:
            for kappa in (1.0, 0.0):
                gid = d.send_trajectory(
                    [{"time_from_start": 1.5, "segments": {n: {"kappa": kappa} for n in NAMES}}]
                )
                assert wait_for(lambda g=gid: d.trajectory_status(g)["state"] in _ENDED, 20.0)
                status = d.trajectory_status(gid)
                assert status["state"] == "succeeded", status
        except Exception:  # noqa: BLE001 - a hot-plug settling or a tolerance abort: try again
            if attempt == attempts - 1:
                raise
            time.sleep(0.5)
            continue
        js = d.status()["joint_states"]
        assert all(abs(js[n]["kappa"]) < 0.1 for n in NAMES), js
        return


def test_event_with_an_infinite_code_does_not_disable_the_daemon(daemon, chain):
    frame = encode_frame(C.FLAG_UP, 1, C.T_EVENT, 0, {C.KE_CODE: float("inf")})
    chain.inject(0, frame, direction="up")
    assert wait_for(lambda: daemon.link.stats["bad_payloads"] >= 1, 5.0)
    time.sleep(0.3)
    assert daemon.link._thread.is_alive()
    _controls_the_chain(daemon)


_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=8),
    st.binary(max_size=8),
)
_values = st.recursive(
    _scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.integers(0, 20), inner, max_size=4)
    ),
    max_leaves=12,
)


def _deep(n: int) -> object:
    v: object = 0
    for _ in range(n):
        v = [v]
    return v


_payloads = st.one_of(
    st.dictionaries(st.integers(0, 16), _values, max_size=10),
    _values,
    st.integers(2, 200).map(_deep),
)
_frames = st.tuples(
    st.sampled_from([C.T_EVENT, C.T_STATE, C.T_ERROR, C.T_DESCRIPTOR, C.T_PARAM_VALUE, 0x42]),
    st.integers(0, 3),  # hop: positions of the chain and one beyond
    st.integers(0, 255),  # seq: sometimes the one the host waits for
    _payloads,
)


@settings(
    max_examples=60,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(frames=st.lists(_frames, min_size=1, max_size=8))
def test_fuzzed_frames_from_the_chain_never_stop_the_host_link(daemon, chain, frames):
    link = daemon.link
    for mtype, hop, seq, payload in frames:
        try:
            raw = cbor2.dumps(payload)
        except (ValueError, TypeError, OverflowError, RecursionError):
            continue
        if len(raw) > 200:
            continue
        chain.inject(0, encode_frame(C.FLAG_UP, hop, mtype, seq, raw), direction="up")
    time.sleep(0.02)
    current = daemon.link
    assert current is None or current is not link or link._thread.is_alive()


def test_after_the_fuzz_the_daemon_still_controls_the_chain(daemon):
    _controls_the_chain(daemon)
    assert daemon.link._thread.is_alive()
