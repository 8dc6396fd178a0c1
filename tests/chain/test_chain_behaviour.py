"""Cyclic I/O, hot-plug events, corruption, watchdog and restarts on an emulated 3-segment chain.

One chain (configured from robots/softrobot3.ucrdf, watchdog 200 ms) serves the whole module; each
test leaves it plugged, unthrottled and running.
"""

from __future__ import annotations

import math
import os
import signal
import time
from pathlib import Path

import pytest
from chain_helpers import chain_and_link, events_until, sync_until, wait_discover

from host.link import LinkTimeoutError
from protocol import constants as C
from protocol.frame import encode_frame
from tools.segment_config import configs
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"
P_FRAMES_OK, P_CRC_ERRORS, P_FRAMING_ERRORS = 6, 7, 8  # docs/firmware.md parameter ids


@pytest.fixture(scope="module")
def chain3():
    cfgs = configs(load(ROBOT))
    with chain_and_link(3, config_for=cfgs) as (chain, link):
        wait_discover(link, 3)
        yield chain, link


def _angle_close(a: float, b: float, tol: float) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) < tol


def _reached(targets):
    def cond(states) -> bool:
        return all(
            abs(s["kappa"] - k) < 0.03 and _angle_close(s["phi"], p, 0.03)
            for s, (k, p) in zip(states, targets, strict=True)
        )

    return cond


def test_each_segment_converges_to_its_own_setpoint(chain3) -> None:
    chain, link = chain3
    targets = [(1.0, 0.5), (2.0, -1.0), (0.5, 2.5)]
    states = sync_until(link, targets, _reached(targets), timeout=6.0)
    assert [s["position"] for s in states] == [0, 1, 2]
    for s, (k, p) in zip(states, targets, strict=True):
        assert s["kx"] == pytest.approx(k * math.cos(p), abs=0.05)
        assert s["ky"] == pytest.approx(k * math.sin(p), abs=0.05)


def test_states_return_measured_tendons_servos_and_status(chain3) -> None:
    chain, link = chain3
    states = link.heartbeat(timeout=0.2, expected=3)
    assert all(s is not None for s in states)
    cycle = states[0]["cycle"]
    assert all(s["cycle"] == cycle for s in states)  # every answer echoes this request's cycle
    for s in states:
        assert len(s["tendon_lengths"]) == 3 and len(s["servo_angles"]) == 3
        assert all(0.25 < length < 0.38 for length in s["tendon_lengths"])
        assert "UNCONFIGURED" not in s["status"]
    assert "DOWNSTREAM" in states[0]["status"] and "DOWNSTREAM" in states[1]["status"]
    assert "DOWNSTREAM" not in states[2]["status"]


def test_unplug_and_replug_produce_downstream_events_from_the_upstream_neighbour(chain3) -> None:
    chain, link = chain3
    link.events()
    hold = [(0.0, 0.0)] * 3
    chain.unplug(2)
    seen = events_until(
        link,
        lambda e: e["name"] == "DOWNSTREAM_DOWN" and e["position"] == 1,
        keep_alive=lambda: link.sync(hold, timeout=0.02),
    )
    assert not any(e["name"] == "DOWNSTREAM_DOWN" and e["position"] == 0 for e in seen)
    assert [d["position"] for d in link.discover(timeout=0.5)] == [0, 1]
    chain.plug(2)
    events_until(
        link,
        lambda e: e["name"] == "DOWNSTREAM_UP" and e["position"] == 1,
        keep_alive=lambda: link.sync(hold, timeout=0.02),
    )
    assert len(wait_discover(link, 3)) == 3


def test_corrupted_bytes_are_dropped_and_counted_never_executed(chain3) -> None:
    chain, link = chain3
    before = [
        link.param_get(k, P_CRC_ERRORS) + link.param_get(k, P_FRAMING_ERRORS) for k in range(3)
    ]
    host_before = link.stats["crc_errors"] + link.stats["framing_errors"]
    targets = [(0.3, 0.0), (0.3, 0.0), (0.3, 0.0)]
    sync_until(link, targets, _reached(targets), timeout=6.0)
    chain.set_link(1, corrupt_rate=0.02, seed=7)
    got = 0
    for _ in range(60):
        states = link.sync(targets, timeout=0.05)
        for s in states:
            if s is not None:
                got += 1
                # a corrupted command executed would move a segment away from its target
                assert abs(s["kappa"] - 0.3) < 0.05, s
    chain.set_link(1, corrupt_rate=0.0)
    corrupted = (
        chain.stats()["links"][1]["down"]["corrupted"]
        + chain.stats()["links"][1]["up"]["corrupted"]
    )
    assert corrupted > 0 and got > 0
    after = [
        link.param_get(k, P_CRC_ERRORS) + link.param_get(k, P_FRAMING_ERRORS) for k in range(3)
    ]
    # link 1 joins segments 0 and 1: they are the ones that saw bad frames
    assert after[0] + after[1] > before[0] + before[1]
    # A HOLD with a broken CRC, and random garbage, are not executed by segment 0.
    bad_hold = bytearray(encode_frame(C.FLAG_BCAST, 0, C.T_HOLD, 200, {}))
    bad_hold[-2] ^= 0x5A if bad_hold[-2] ^ 0x5A else 0x33
    link.send_raw(bytes(bad_hold) + bytes(range(1, 200)) + b"\x00")
    time.sleep(0.05)
    assert link.param_get(0, P_CRC_ERRORS) + link.param_get(0, P_FRAMING_ERRORS) > after[0]
    states = link.heartbeat(timeout=0.2, expected=3)
    assert all(s is not None and "HOLD" not in s["status"] for s in states)
    # Garbage travelling up to the host is counted by the host and ignored.
    chain.inject(0, b"\x05\x01\x02\x03\x04\x00" + b"\xff" * 20 + b"\x00", direction="up")
    time.sleep(0.05)
    assert link.stats["crc_errors"] + link.stats["framing_errors"] > host_before


def test_host_silence_makes_every_segment_hold_within_its_watchdog_time(chain3) -> None:
    chain, link = chain3
    targets = [(0.5, 1.0)] * 3
    sync_until(link, targets, _reached(targets), timeout=6.0)
    link.events()
    chain.kill_host_link()
    t0 = time.monotonic()
    seen: list[dict] = []
    try:
        while time.monotonic() < t0 + 0.8:  # events keep arriving: the host still listens
            seen += link.events()
            time.sleep(0.01)
    finally:
        chain.restore_host_link()
    trips = {e["position"]: e for e in seen if e["name"] == "WATCHDOG_TRIPPED"}
    assert sorted(trips) == [0, 1, 2], seen
    for e in trips.values():
        # watchdog 200 ms after the last SYNC (just before t0); margin for one 5 ms tick, event
        # pacing (20 ms per event per segment) and a loaded 2-core CI machine
        assert 0.15 < e["t"] - t0 < 0.2 + 0.15, (e, t0)
    states = link.heartbeat(timeout=0.2, expected=3)
    assert all("WATCHDOG" in s["status"] for s in states)
    sync_until(link, targets, lambda st: all("WATCHDOG" not in s["status"] for s in st))


def test_killed_segment_process_is_restarted_and_rediscovered(chain3) -> None:
    chain, link = chain3
    restarts = chain.stats()["segments"][1]["restarts"]
    uid = chain.uid(1)
    os.kill(chain.pid(1), signal.SIGKILL)
    chain.wait_restarts(1, restarts + 1, timeout=5.0)
    descs = wait_discover(link, 3)
    assert descs[1]["uid"] == uid
    assert chain.stats()["segments"][1]["exit_codes"][-1] == -signal.SIGKILL


def test_param_get_times_out_when_the_segment_is_unreachable(chain3) -> None:
    chain, link = chain3
    chain.unplug(2)
    try:
        with pytest.raises(LinkTimeoutError) as info:
            link.param_get(2, P_FRAMES_OK, timeout=0.1)
        assert isinstance(info.value, TimeoutError) and isinstance(info.value, OSError)
    finally:
        chain.plug(2)
    wait_discover(link, 3)
