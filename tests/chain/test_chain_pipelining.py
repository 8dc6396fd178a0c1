"""Pipelined cycles (docs/protocol.md 8.4): the host sends the next SYNC before the STATEs of the
previous one are in; every segment still applies the setpoints in the order sent (emulated chain,
real firmware)."""

from __future__ import annotations

import pytest

from host.link import MAX_IN_FLIGHT, LinkError
from tests.chain.chain_helpers import chain_and_link, sync_until, wait_discover

N = 3
CYCLES = 60


def test_pipelined_cycles_apply_setpoints_in_the_order_sent() -> None:
    with chain_and_link(N) as (_chain, link):
        wait_discover(link, N)
        sync_until(link, [(0.0, 0.0)] * N, lambda s: True, timeout=10.0)
        # a ramp of kappa: cycle i asks 0.02 * i 1/m, so an older setpoint applied late would pull
        # a segment back; two cycles in flight at any time
        sent: list[int] = []
        got: dict[int, list[dict | None]] = {}
        ramp = [0.02 * i for i in range(1, CYCLES + 1)]
        pending = [link.sync_send([(ramp[0], 0.0)] * N)]
        sent.append(pending[0].cycle)
        for k in ramp[1:]:
            p = link.sync_send([(k, 0.0)] * N)  # before the last STATE of the previous cycle
            sent.append(p.cycle)
            pending.append(p)
            first = pending.pop(0)
            got[first.cycle] = link.sync_collect(first, timeout=0.5)
        last = pending.pop(0)
        got[last.cycle] = link.sync_collect(last, timeout=0.5)
        complete = [c for c in sent if all(s is not None for s in got[c])]
        assert len(complete) >= CYCLES - 3, "pipelined cycles lost their STATEs"
        for c in complete:
            assert all(s["cycle"] == c for s in got[c])  # each STATE answers its own cycle
        for pos in range(N):
            stamps = [got[c][pos]["t_ms"] for c in complete]
            # the segment handled the cycles in the order sent (its clock never runs back)
            assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))
        # after the ramp, every segment heads for the LAST setpoint, never an older one
        final = ramp[-1]
        states = sync_until(
            link,
            [(final, 0.0)] * N,
            lambda s: all(abs(x["kappa"] - final) < 0.02 for x in s),
            timeout=10.0,
        )
        assert all(abs(x["kappa"] - final) < 0.02 for x in states)


def test_too_many_open_cycles_are_refused() -> None:
    with chain_and_link(1) as (_chain, link):
        wait_discover(link, 1)
        open_cycles = [link.sync_send([(0.0, 0.0)]) for _ in range(MAX_IN_FLIGHT)]
        with pytest.raises(LinkError, match="pipelined"):
            link.sync_send([(0.0, 0.0)])
        for p in open_cycles:
            link.sync_collect(p, timeout=0.5)
        link.sync_collect(link.sync_send([(0.0, 0.0)]), timeout=0.5)  # room again
