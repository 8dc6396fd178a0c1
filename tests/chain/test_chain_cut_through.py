"""Cut-through forwarding on the emulated chain (real firmware, real VM): a corrupted byte anywhere
in a relayed frame is never executed or accepted by anyone downstream of the corruption; clean
frames still reach every segment (docs/protocol.md section 6, "Cut-through")."""

from __future__ import annotations

import math
import time

from host.link import LinkError
from tests.chain.chain_helpers import chain_and_link, wait_discover

P_CRC_ERRORS = 7
P_FRAMING_ERRORS = 8
N = 3
CYCLES = 400
SETPOINTS = [(0.5, 0.25), (1.0, -0.5), (1.5, 1.0)]  # kappa 1/m, phi rad; constant throughout


def _only_sent_setpoints_applied(got: list[dict]) -> None:
    """Every reported pose lies on the way from rest (kappa 0) to the segment's own setpoint: a
    corrupted SYNC that kept its cycle bytes but was executed would show another kappa or phi
    (the cycle echo alone cannot tell, the setpoints being constant)."""
    for s in got:
        k_sp, phi_sp = SETPOINTS[s["position"]]
        assert -1e-3 <= s["kappa"] <= 1.02 * k_sp + 1e-3, s
        if s["kappa"] > 0.05:  # a slew from rest keeps phi near the setpoint's (the emulated
            off = math.remainder(s["phi"] - phi_sp, 2 * math.pi)  # servos lag by ~0.04 rad)
            assert abs(off) < 0.1, s


def _params(link, pos: int) -> tuple[int, int]:
    return link.param_get(pos, P_CRC_ERRORS), link.param_get(pos, P_FRAMING_ERRORS)


def _counters_after_clean_traffic(link) -> list[tuple[int, int]]:
    """(crc errors, framing errors) per segment, read once the links are clean again."""
    end = time.monotonic() + 20.0
    while True:
        try:
            return [_params(link, p) for p in range(N)]
        except LinkError:  # a reply lost to the last corrupted bytes in flight: ask again
            if time.monotonic() > end:
                raise
            time.sleep(0.05)


def _fuzz(link, chain, k: int, direction: str, seed: int):
    """SYNC cycles with link ``k`` corrupting bytes in ``direction``; returns (sent cycles,
    states received) after the corruption was switched off again."""
    sps = SETPOINTS
    sent: set[int] = set()
    got: list[dict] = []
    chain.set_link(k, corrupt_rate=0.004, direction=direction, seed=seed)
    try:
        for _ in range(CYCLES):
            states = link.sync(sps, timeout=0.05)
            sent.add(link._cycle)
            got.extend(s for s in states if s is not None)
    finally:
        chain.set_link(k, corrupt_rate=0.0, direction=direction)
    return sent, got


def test_corrupted_bytes_in_relayed_frames_are_dropped_downstream_and_never_executed() -> None:
    with chain_and_link(N) as (chain, link):
        wait_discover(link, N)
        before = _counters_after_clean_traffic(link)
        # (1) broadcasts corrupted between segment 0 and 1: segment 1 drops what it cannot check,
        # and ends the frame it was relaying as invalid COBS, so segment 2 sees framing errors only
        sent, got = _fuzz(link, chain, 1, "down", seed=11)
        after = _counters_after_clean_traffic(link)
        crc1, fr1 = (after[1][0] - before[1][0], after[1][1] - before[1][1])
        crc2, fr2 = (after[2][0] - before[2][0], after[2][1] - before[2][1])
        assert crc1 + fr1 > 0, "no corruption reached segment 1: the test proves nothing"
        assert fr2 > 0, "segment 1 relayed no corrupted frame: cut-through is not active"
        assert crc2 == 0, "a relayed frame reached segment 2 with valid COBS and a bad CRC"
        assert all(s["cycle"] in sent for s in got)  # no STATE answers a SYNC never sent
        assert all(s["applied_position"] == s["position"] for s in got)  # no corrupted hop
        assert len(got) > CYCLES  # clean cycles still served
        _only_sent_setpoints_applied(got)
        # (2) STATEs corrupted between segment 2 and 1 on their way up: relayed by segments 1
        # and 0, the host drops them (framing errors), never accepts one with a bad CRC
        host_before = link.stats
        sent, got = _fuzz(link, chain, 2, "up", seed=12)
        host_after = link.stats
        assert host_after["framing_errors"] > host_before["framing_errors"]
        assert host_after["crc_errors"] == host_before["crc_errors"]
        assert all(s["cycle"] in sent for s in got)
        assert all(s["applied_position"] == s["position"] for s in got)
        _only_sent_setpoints_applied(got)
