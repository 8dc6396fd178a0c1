"""Pipelined cycles (docs/protocol.md 8.4): the host sends the next SYNC before the STATEs of the
previous one are in; every segment still applies the setpoints in the order sent (emulated chain,
real firmware)."""

from __future__ import annotations

import time

import pytest

from host.link import MAX_IN_FLIGHT, LinkError
from tests.chain.chain_helpers import chain_and_link, sync_until, wait_discover

N = 3
CYCLES = 60


def _settles_on(
    link, target: float, others: list[float], tol: float = 0.02, timeout: float = 10.0
) -> None:
    """HEARTBEATs only (they feed the watchdog and change no setpoint) until every segment's
    measured kappa stays at ``target``: the setpoint applied last. It must be ``target``, never
    one of ``others`` (the cycles sent before it)."""
    end = time.monotonic() + timeout
    states: list[dict | None] = []
    steady = 0
    while time.monotonic() < end:
        states = link.heartbeat(timeout=0.1, expected=N)
        if all(s is not None and abs(s["kappa"] - target) < tol for s in states):
            steady += 1
            if steady >= 5:  # held there for 5 heartbeats
                return
        else:
            steady = 0
        time.sleep(0.02)
    raise AssertionError(f"not settled on the last setpoint {target} (others {others}): {states}")


def _pipelined(link, values: list[float], got: dict[int, list[dict | None]]) -> list[int]:
    """Send one cycle per value, each before the STATEs of the previous one are collected (two
    cycles in flight); return the cycles sent."""
    sent: list[int] = []
    pending = []
    for k in values:
        p = link.sync_send([(k, 0.0)] * N)  # before the last STATE of the previous cycle
        sent.append(p.cycle)
        pending.append(p)
        if len(pending) == 2:
            first = pending.pop(0)
            got[first.cycle] = link.sync_collect(first, timeout=0.5)
    for p in pending:
        got[p.cycle] = link.sync_collect(p, timeout=0.5)
    return sent


def test_pipelined_cycles_apply_setpoints_in_the_order_sent() -> None:
    """Observed on what the segments do, not only on their clocks: after pipelined cycles with
    distinct setpoints (and then only HEARTBEATs, which change no setpoint), every segment
    settles on the setpoint sent LAST; a segment that applied any earlier cycle after it would
    settle there instead. Bursts in changing order (up, down, back) each check their last."""
    with chain_and_link(N) as (_chain, link):
        wait_discover(link, N)
        sync_until(link, [(0.0, 0.0)] * N, lambda s: True, timeout=10.0)
        # a ramp of kappa: cycle i asks 0.02 * i 1/m, two cycles in flight at any time
        got: dict[int, list[dict | None]] = {}
        ramp = [0.02 * i for i in range(1, CYCLES + 1)]
        sent = _pipelined(link, ramp, got)
        complete = [c for c in sent if all(s is not None for s in got[c])]
        assert len(complete) >= CYCLES - 3, "pipelined cycles lost their STATEs"
        for c in complete:
            assert all(s["cycle"] == c for s in got[c])  # each STATE answers its own cycle
        for pos in range(N):
            stamps = [got[c][pos]["t_ms"] for c in complete]
            # the segment handled the cycles in the order sent (its clock never runs back)
            assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))
        # the ramp's last setpoint is where every segment stays (not re-sent: HEARTBEATs only)
        _settles_on(link, ramp[-1], ramp[:-1], tol=0.01)  # half a ramp step
        # bursts whose last setpoint is neither their largest nor their smallest
        for burst in ([0.3, 2.2, 0.9], [2.6, 0.2, 1.5], [0.5, 1.9, 0.1, 2.4, 1.2]):
            sent = _pipelined(link, burst, got)
            assert all(s is None or s["cycle"] == c for c in sent for s in got[c])
            _settles_on(link, burst[-1], burst[:-1])


def test_too_many_open_cycles_are_refused() -> None:
    with chain_and_link(1) as (_chain, link):
        wait_discover(link, 1)
        open_cycles = [link.sync_send([(0.0, 0.0)]) for _ in range(MAX_IN_FLIGHT)]
        with pytest.raises(LinkError, match="pipelined"):
            link.sync_send([(0.0, 0.0)])
        for p in open_cycles:
            link.sync_collect(p, timeout=0.5)
        link.sync_collect(link.sync_send([(0.0, 0.0)]), timeout=0.5)  # room again
