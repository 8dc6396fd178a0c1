"""Issue 12: the daemon rides through link faults (emulated chain, real firmware, fault injection
with ``chain.unplug/plug/set_link``) and never moves a segment on its own.

One chain and one daemon for the module; every test leaves the links clean and plugged. Times
are generous (the machine is shared): the 500 ms rejoin figure is measured by
benchmarks/bench_soak.py, not asserted here.
"""

from __future__ import annotations

import math
import queue
import time

import pytest
from daemon_helpers import NAMES, all_back, wait_for

from host.client_cli import format_status

pytestmark = [pytest.mark.timeout(240), pytest.mark.alone]  # recovery times: conftest.py


@pytest.fixture()
def ready(daemon, chain):
    for k in range(3):
        chain.plug(k)
        chain.set_link(k, latency=0.0, corrupt_rate=0.0, baud=None)
    assert wait_for(lambda: all_back(daemon), 10.0)
    return daemon


def health_loss(d) -> list[float]:
    return d.status()["link_health"]["loss"]


def kappa_of(d, name: str) -> float:
    """Measured kappa of ``name``, waiting out a moment it is not controlled (a rebuild)."""
    assert wait_for(lambda: (d.status()["joint_states"].get(name) or {}).get("valid"), 10.0)
    return d.status()["joint_states"][name]["kappa"]


def sample_kappa(d, name: str, seconds: float) -> list[float]:
    """Measured kappa of ``name`` (only fresh, valid states) every 20 ms for ``seconds``."""
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        js = d.status()["joint_states"].get(name)
        if js is not None and js["valid"]:
            out.append(js["kappa"])
        time.sleep(0.02)
    return out


def check_abort_is_coherent(status: dict) -> None:
    """Finding 3: an aborted goal names a cause, and never a NaN, "?" or an error below the
    tolerance it claims to exceed."""
    if status["state"] != "aborted":
        return
    reason, ab = status["reason"], status["abort"]
    assert ab is not None and ab["cause"] in {
        "path_tolerance",
        "goal_tolerance",
        "topology_change",
        "segment_fault",
        "link_loss",
        "replaced",
        "stopped",
    }, status
    assert "nan" not in reason.lower() and "?" not in reason, reason
    if ab["error"] is not None:
        assert math.isfinite(ab["error"]) and ab["error"] > ab["tolerance"], status
        assert ab["segment"] in NAMES


# -- finding 1: rejoin by itself ------------------------------------------------------------
def test_a_short_glitch_never_loses_a_segment_for_good(ready, chain):
    d = ready
    # each glitch ends while the daemon rediscovers — after it noticed the silence, before the
    # segments' own 150 ms neighbour timeout — so no DOWNSTREAM event tells that the cable came
    # back (today the segments behind it are then lost until a re-plug)
    for link in (2, 1, 2, 1):
        chain.unplug(link)
        t_unplug = time.monotonic()
        wait_for(lambda: d.hwi is not None and max(d.hwi.missing) >= 7, 0.12, step=0.002)
        time.sleep(max(0.0, min(0.015, 0.13 - (time.monotonic() - t_unplug))))
        chain.plug(link)
        t_plug = time.monotonic()
        assert wait_for(lambda: all_back(d), 10.0), (link, d.status(), d.topology()["cut"])
        assert time.monotonic() - t_plug < 10.0
    # a segment that came back is held where it is measured: nothing moves without a command
    time.sleep(0.3)
    before = {n: kappa_of(d, n) for n in NAMES}
    time.sleep(0.5)
    for n in NAMES:
        assert abs(kappa_of(d, n) - before[n]) < 0.01, n


def test_segments_rejoin_by_themselves_after_a_corruption_burst(ready, chain):
    d = ready
    # 1 % of the bytes into segment_2, then 5 % into segment_3 (its replies and descriptor are
    # lost, while its short keep-alives still tell segment_2 it is there)
    for link, rate in ((1, 0.01), (2, 0.05), (1, 0.01)):
        chain.set_link(link, corrupt_rate=rate)
        time.sleep(2.0)
        chain.set_link(link, corrupt_rate=0.0)
        assert wait_for(lambda: all_back(d), 10.0), (d.status(), d.topology()["cut"])
    assert d.topology()["cut"] is None


# -- finding 2: no motion without a command ---------------------------------------------------
def _tip_states(q: queue.Queue, name: str, seconds: float) -> list[tuple[float, bool, float]]:
    """(t, valid, kappa) of ``name`` from every joint_states message for ``seconds``."""
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            m = q.get(timeout=0.1)
        except queue.Empty:
            continue
        if name in m["names"]:
            i = m["names"].index(name)
            out.append((m["t"], bool(m["valid"][i]), float(m["kappa"][i])))
    return out


def test_a_segment_invalid_during_latency_does_not_move_to_a_stale_target(ready, chain):
    # End to end, the sequence. On this machine the code before the rule (29bcaa3,
    # 342e390) passes it too: the motion the issue saw did not reproduce here, in process or
    # through `ucr emulate` + `ucr daemon` + `ucr move`. The rule itself is pinned at the HWI by
    # test_review_fixes.py::test_a_segment_silent_for_a_gap_gets_hold_entries_then_is_held_...,
    # which fails on that code.
    d = ready
    chain.set_link(1, latency=0.005)  # link 2 (into segment_2): replies from 2 and 3 come late
    time.sleep(0.3)
    gid = d.send_trajectory(
        [{"time_from_start": 2.0, "segments": {"segment_3": {"kappa": 1.0, "phi": 0.0}}}]
    )
    assert wait_for(lambda: d.trajectory_status(gid)["done"], 15.0)
    check_abort_is_coherent(d.trajectory_status(gid))
    time.sleep(0.5)
    # every state from the moment the link is clean: no command is sent from here on, so
    # segment_3 must stay where it is first measured again (the issue saw it move to the
    # stale target, kappa ~ 1, within the first few hundred ms, then back)
    q = d.subscribe(["joint_states"])
    try:
        chain.set_link(1, latency=0.0)
        states = _tip_states(q, "segment_3", 3.0)
    finally:
        d.unsubscribe(q)
    valid = [k for _, ok, k in states if ok]
    assert valid, "segment_3 never valid again"
    first = valid[0]
    assert max(abs(k - first) for k in valid) < 0.05, (first, min(valid), max(valid))


# -- finding 5: degrade, don't stall --------------------------------------------------------
def _events(q: queue.Queue) -> list[dict]:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


@pytest.mark.parametrize(
    ("fault", "clean"),
    [({"latency": 0.005}, {"latency": 0.0}), ({"baud": 115200}, {"baud": None})],
    ids=["latency_5ms", "baud_115200"],
)
def test_a_slow_link_lowers_the_rate_keeps_control_and_recovers(ready, chain, fault, clean):
    d = ready
    # at the nominal rate first (an earlier test may have left it lowered)
    assert wait_for(lambda: not d.status()["link_health"]["degraded"], 40.0)
    q = d.subscribe(["event"])
    try:
        chain.set_link(1, **fault)
        assert wait_for(lambda: d.status()["link_health"]["degraded"], 10.0)
        health = d.status()["link_health"]
        assert health["usable_rate_hz"] < health["nominal_rate_hz"]
        # status and `ucr status` show the rate the loop runs at, and the degraded link
        assert wait_for(lambda: d.status()["rate_hz"] < d.status()["nominal_rate_hz"], 10.0)
        text = "\n".join(format_status(d.status()))
        assert "slowed from 100 Hz" in text and "link degraded: link " in text, text
        # the whole chain stays under control at the usable rate: a goal on the tip succeeds
        # (a reply the slow link still loses now and then aborts a goal by the gap rule, with
        # cause link_loss: the goal is sent again, at most 3 times)
        for _ in range(3):
            assert wait_for(lambda: all_back(d) and not any(health_loss(d)), 15.0)
            gid = d.send_trajectory(
                [{"time_from_start": 1.0, "segments": {"segment_3": {"kappa": 0.8, "phi": 0.0}}}]
            )
            assert wait_for(lambda g=gid: d.trajectory_status(g)["done"], 15.0)
            st = d.trajectory_status(gid)
            check_abort_is_coherent(st)
            if st["state"] != "aborted" or st["abort"]["cause"] != "link_loss":
                break
        assert st["state"] == "succeeded", st
        assert abs(kappa_of(d, "segment_3") - 0.8) < 0.1
        chain.set_link(1, **clean)
        assert wait_for(lambda: not d.status()["link_health"]["degraded"], 40.0)
        assert d.status()["link_health"]["usable_rate_hz"] == 100.0
        gid = d.send_trajectory(
            [{"time_from_start": 1.0, "segments": {"segment_3": {"kappa": 0.0, "phi": 0.0}}}]
        )
        assert wait_for(lambda: d.trajectory_status(gid)["done"], 15.0)
        msgs = _events(q)
    finally:
        d.unsubscribe(q)
        chain.set_link(1, **clean)
    # the slow link is named (a loaded machine may add others: the emulated segments are
    # processes that share its CPU)
    # (with a throughput limit the replies of segment_2 may still fit: then the first late
    # ones are segment_3's, and the daemon names the link into it)
    links = (2,) if "latency" in fault else (2, 3)
    degraded = [m for m in msgs if m["event"] == "link_degraded" and m["link"] in links]
    assert degraded and degraded[0]["segment"] == NAMES[degraded[0]["link"] - 1], msgs
    assert degraded[0]["position"] == degraded[0]["link"]  # the same cable, counted from 1
    assert "slowed to" in degraded[0]["message"] and degraded[0]["usable_rate_hz"] < 100
    assert any(m["event"] == "link_recovered" for m in msgs)
