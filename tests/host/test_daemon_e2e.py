"""End-to-end: the daemon against an emulated 3-segment chain running the real firmware on the
MicroPython VM. One chain and one daemon are shared by the module; every test leaves the chain
plugged, the trajectory controller active and the robot near straight."""

from __future__ import annotations

import math
import queue
import time

import numpy as np
import pytest
from daemon_helpers import (
    assert_succeeded,
    retry_if_the_link_was_disturbed,
    wait_for,
)

from host.controllers.base import ControllerError
from host.daemon import GoalNotFound

pytestmark = pytest.mark.timeout(120)

NAMES = ["segment_1", "segment_2", "segment_3"]


@pytest.fixture()
def ready(daemon, chain):
    """Before each test: 3 segments, jtc active, at rest near straight."""
    for k in range(3):
        chain.plug(k)
    assert wait_for(lambda: len(daemon.status()["segments"]) == 3, 5.0)
    if "ffc" in daemon.status()["manual_control"]:
        daemon.hand_back("ffc")
    if "jtc" not in daemon.status()["active_controllers"]:
        daemon.switch_controllers(
            ["jtc"], [n for n in ("ffc",) if n in daemon.status()["active_controllers"]]
        )
    js = daemon.status()["joint_states"]
    if any(v["kappa"] > 0.05 for v in js.values()):
        straighten(daemon)
    return daemon


def straighten(daemon, t=0.8):
    names = daemon.status()["segments"]
    gid = daemon.send_trajectory(
        [{"time_from_start": t, "segments": {n: {"kappa": 0.0, "phi": 0.0} for n in names}}]
    )
    assert wait_for(lambda: daemon.trajectory_status(gid)["done"], 10.0)


def windowed_speed(t, kx, ky, window: float = 0.05) -> np.ndarray:
    """|d(kx, ky)/dt| (1/m/s) over windows of >= ``window`` s of the segment's own clock (its
    measurement stamps), so host scheduling noise does not enter; a command jump would drive
    the segment at its slew limit for much longer than one window."""
    out = []
    j = 0
    for i in range(len(t)):
        while j < len(t) and t[j] - t[i] < window:
            j += 1
        if j == len(t):
            break
        out.append(math.hypot(kx[j] - kx[i], ky[j] - ky[i]) / (t[j] - t[i]))
    return np.array(out)


def record(q: queue.Queue, seconds: float) -> list[dict]:
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            out.append(q.get(timeout=0.05))
        except queue.Empty:
            pass
    return out


def test_discovers_three_segments_matching_the_description(daemon, chain):
    topo = daemon.topology()
    assert topo["ok"] and topo["controlled"] == NAMES
    assert [s["uid"] for s in topo["segments"]] == [chain.uid(k) for k in range(3)]
    assert [s["bendable"] for s in topo["segments"]] == NAMES
    st = daemon.status()
    assert st["hwi"] == "active" and st["state"] == "connected"
    assert set(st["active_controllers"]) == {"jtc", "jsb", "rsp"}


def test_jtc_trajectory_converges_to_goal_within_tolerance(ready):
    d = ready
    retry_if_the_link_was_disturbed(d, lambda: _converges(d), before=lambda: straighten(d))
    with pytest.raises(GoalNotFound):
        d.trajectory_status("no-such-goal")


def _converges(d):
    target = {"segment_1": (2.0, 0.5), "segment_2": (1.0, -2.0), "segment_3": (1.5, 2.5)}
    gid = d.send_trajectory(
        [
            {"time_from_start": 0.6, "segments": {"segment_1": {"kappa": 1.0, "phi": 0.5}}},
            {
                "time_from_start": 1.5,
                "segments": {n: {"kappa": k, "phi": p} for n, (k, p) in target.items()},
            },
        ]
    )
    assert wait_for(lambda: d.trajectory_status(gid)["done"], 10.0)
    assert_succeeded(d, gid)
    js = d.status()["joint_states"]
    for n, (k, p) in target.items():
        err = math.hypot(
            js[n]["kappa"] * math.cos(js[n]["phi"]) - k * math.cos(p),
            js[n]["kappa"] * math.sin(js[n]["phi"]) - k * math.sin(p),
        )
        assert err <= 0.05, (n, err)


def test_limits_never_exceeded_even_when_asked(ready):
    d = ready
    kmax = d.hwi.limits["segment_2"].kappa_max
    with pytest.raises(ControllerError, match="exceeds kappa_max"):
        d.send_trajectory(
            [{"time_from_start": 1.0, "segments": {"segment_2": {"kappa": 1.5 * kmax}}}]
        )
    retry_if_the_link_was_disturbed(d, lambda: _full_range_fast(d), before=lambda: straighten(d))


def _full_range_fast(d):
    kmax = d.hwi.limits["segment_2"].kappa_max
    rate = d.hwi.limits["segment_2"].kappa_rate_max
    q = d.subscribe(["joint_states"])
    try:
        # asked for the full range in 0.1 s: far beyond kappa_rate_max -> retimed
        gid = d.send_trajectory(
            [{"time_from_start": 0.1, "segments": {"segment_2": {"kappa": kmax, "phi": 1.0}}}]
        )
        assert d.trajectory_status(gid)["retimed"]
        msgs = record(q, d.trajectory_status(gid)["duration"] + 0.5)
    finally:
        d.unsubscribe(q)
    assert wait_for(lambda: d.trajectory_status(gid)["done"], 5.0)
    goal = d.trajectory_status(gid)
    i = NAMES.index("segment_2")
    t = np.array([m["t_ms"][i] for m in msgs]) / 1000.0  # the segment's clock
    kx = np.array([m["kx"][i] for m in msgs])
    ky = np.array([m["ky"][i] for m in msgs])
    # the limits hold on every attempt (pytest.fail is never retried); only reaching the goal
    # may be spoiled by a disturbed link
    if not np.hypot(kx, ky).max() <= kmax + 1e-3:
        pytest.fail(f"kappa {np.hypot(kx, ky).max()} beyond kappa_max {kmax}")
    speed = windowed_speed(t, kx, ky)
    if not speed.max() <= rate * 1.1:
        pytest.fail(f"speed {speed.max()} beyond kappa_rate_max {rate} * 1.1")
    assert_succeeded(d, gid)
    assert np.hypot(kx[-1], ky[-1]) == pytest.approx(kmax, abs=0.02), goal


def test_replacing_a_trajectory_midway_has_no_jump(ready):
    d = ready
    retry_if_the_link_was_disturbed(d, lambda: _replace_midway(d), before=lambda: straighten(d))


def _replace_midway(d):
    i = NAMES.index("segment_1")
    rate = d.hwi.limits["segment_1"].kappa_rate_max
    q = d.subscribe(["joint_states"])
    try:
        g1 = d.send_trajectory(
            [{"time_from_start": 2.0, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.0}}}]
        )
        msgs = record(q, 1.0)
        g2 = d.send_trajectory(
            [{"time_from_start": 1.5, "segments": {"segment_1": {"kappa": 0.5, "phi": 2.5}}}]
        )
        msgs += record(q, 1.8)
    finally:
        d.unsubscribe(q)
    t = np.array([m["t_ms"][i] for m in msgs]) / 1000.0  # the segment's clock
    kx = np.array([m["kx"][i] for m in msgs])
    ky = np.array([m["ky"][i] for m in msgs])
    speed = windowed_speed(t, kx, ky)
    # Both goals peak below ~2.6 1/m/s. A jump in the command would drive the segment at its
    # slew limit (kappa_rate_max = 5 1/m/s) right after the replacement. (pytest.fail: never
    # retried, whatever the link did)
    if not speed.max() < 0.7 * rate:
        pytest.fail(f"speed {speed.max()} >= 0.7 * {rate}: a jump at the replacement")
    assert d.trajectory_status(g1)["state"] == "aborted"
    assert "replaced by goal" in d.trajectory_status(g1)["reason"]
    assert wait_for(lambda: d.trajectory_status(g2)["done"], 3.0)
    assert d.trajectory_status(g2)["state"] == "succeeded"


def test_unplug_tip_mid_trajectory_aborts_holds_rebuilds_and_plug_back(ready, chain):
    d = ready
    topo_q = d.subscribe(["topology", "event"])
    try:
        gid = d.send_trajectory(
            [{"time_from_start": 3.0, "segments": {n: {"kappa": 2.0, "phi": 1.0} for n in NAMES}}]
        )
        time.sleep(0.8)
        t_unplug = time.monotonic()
        chain.unplug(2)
        assert wait_for(lambda: d.status()["segments"] == NAMES[:2], 3.0)
        rebuilt_after = time.monotonic() - t_unplug
        st = d.trajectory_status(gid)
        # the segment is named; the cause is what the daemon saw first: the tip's EVENT (a
        # topology change) or, when its silence came first, a link lost at segment_3 (a pulled
        # cable and a dead link look alike until the segment before reports the cut; host/
        # motion_abort.py)
        assert st["state"] == "aborted", st
        assert st["abort"]["segment"] == "segment_3", st
        assert st["abort"]["cause"] in ("topology_change", "link_loss"), st
        assert st["reason"].startswith(("topology changed at segment_3", "link loss at segment_3"))
        # the remaining segments hold still
        time.sleep(0.1)
        before = d.status()["joint_states"]
        time.sleep(0.4)
        after = d.status()["joint_states"]
        for n in NAMES[:2]:
            assert abs(after[n]["kappa"] - before[n]["kappa"]) < 0.01
        topo = d.topology()
        assert topo["cut"] == {"after_position": 2, "after": "segment_2", "lost": ["segment_3"]}
        # controllable again: a 2-segment goal runs, a segment_3 goal is refused
        with pytest.raises(ControllerError, match="'segment_3' is not commanded"):
            d.send_trajectory([{"time_from_start": 0.5, "segments": {"segment_3": {"kappa": 1}}}])
        straighten(d, 0.6)
        chain.plug(2)
        assert wait_for(lambda: d.status()["segments"] == NAMES, 3.0)
        msgs = record(topo_q, 0.1)
    finally:
        d.unsubscribe(topo_q)
    kinds = [(m["kind"], m.get("event")) for m in msgs]
    assert ("topology", None) in kinds and ("event", "topology_changed") in kinds
    assert rebuilt_after < 2.0
    straighten(d)


def test_unplug_middle_segment_reports_the_chain_cut(ready, chain):
    d = ready
    q = d.subscribe(["event"])
    try:
        chain.unplug(1)
        assert wait_for(lambda: d.status()["segments"] == ["segment_1"], 3.0)
        cut = d.topology()["cut"]
        assert cut == {
            "after_position": 1,  # 1-based, as every position a user sees
            "after": "segment_1",
            "lost": ["segment_2", "segment_3"],
        }
        msgs = record(q, 0.2)
    finally:
        d.unsubscribe(q)
    texts = [m["message"] for m in msgs if m["event"] == "topology_changed"]
    assert any(
        "chain cut after segment_1" in t and "segment_2, segment_3 unreachable" in t for t in texts
    ), texts
    chain.plug(1)
    assert wait_for(lambda: d.status()["segments"] == NAMES, 3.0)


def test_ffc_takes_over_from_trajectory_and_deadman_stops_motion(ready):
    d = ready
    gid = d.send_trajectory(
        [{"time_from_start": 4.0, "segments": {"segment_2": {"kappa": 2.0, "phi": 0.0}}}]
    )
    time.sleep(0.3)
    res = d.ffc_input({"segment_1": [0.0, 1.0]})
    assert res["accepted"] and res["takeover"]["preempted"] == ["jtc"]
    st = d.trajectory_status(gid)
    assert st["state"] == "aborted" and "preempted by manual control" in st["reason"]
    # the reply says where the setpoint starts from: the measured state at the takeover
    assert set(res["setpoint"]) == set(NAMES)
    start = res["setpoint"]["segment_1"]
    for _ in range(15):  # a stick held for 0.3 s, streamed at 50 Hz
        last = d.ffc_input({"segment_1": [0.0, 1.0]})
        time.sleep(0.02)
    # ... and each later reply where the inputs took it: along +ky, at most 5 1/m/s
    moved = last["setpoint"]["segment_1"][1] - start[1]
    assert 0.3 < moved <= 5.0 * 0.32 + 1e-6, (start, last["setpoint"])
    # the stream stops: within the deadman timeout (0.3 s) + the firmware's slew, motion stops
    time.sleep(0.6)
    a = d.status()["joint_states"]["segment_1"]
    time.sleep(0.5)
    b = d.status()["joint_states"]["segment_1"]
    assert a["kappa"] > 0.5  # it did move (5 1/m/s * 0.3 s ~ 1.5 1/m)
    assert abs(b["kappa"] - a["kappa"]) < 0.005
    ffc = next(c for c in d.controllers() if c["name"] == "ffc")
    assert ffc["deadman_tripped"]
    with pytest.raises(ControllerError, match="hand back first"):
        d.send_trajectory([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 0}}}])
    back = d.hand_back()
    assert back["restarted"] == ["jtc"]
    straighten(d)


def test_hand_back_stops_only_a_takeover_never_the_controller_it_names(ready):
    """Review 2026-11-26: hand_back(manual='jtc') stopped the trajectory controller mid-goal
    (and 'jsb' the joint state broadcaster) and answered ok. Only a manual takeover is handed
    back; anything else is rejected and nothing stops. A cFFC switched on explicitly blocks
    goals with the CLI command that switches back."""
    d = ready
    gid = d.send_trajectory(
        [{"time_from_start": 3.0, "segments": {"segment_1": {"kappa": 0.4, "phi": 0.0}}}]
    )
    for name in ("jtc", "jsb"):
        with pytest.raises(ControllerError, match=f"{name!r} holds no manual takeover"):
            d.hand_back(name)
    active = d.status()["active_controllers"]
    assert "jtc" in active and "jsb" in active
    assert d.trajectory_status(gid)["state"] in ("executing", "succeeded")
    d.cancel_trajectory(gid)
    d.switch_controllers(["ffc"], ["jtc"])
    try:
        with pytest.raises(ControllerError, match="ucr controllers switch --start jtc --stop ffc"):
            d.send_trajectory([{"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 0}}}])
    finally:
        d.switch_controllers(["jtc"], ["ffc"])
    straighten(d)


def test_host_link_lost_and_back_recovers(ready, chain):
    d = ready
    q = d.subscribe(["event"])
    try:
        chain.kill_host_link()  # the adapter stops carrying the host's bytes
        assert wait_for(lambda: d.status()["state"] != "connected", 3.0)
        chain.restore_host_link()
        assert wait_for(
            lambda: d.status()["state"] == "connected" and d.status()["segments"] == NAMES, 8.0
        )
        msgs = record(q, 0.1)
    finally:
        d.unsubscribe(q)
    events = [m["event"] for m in msgs]
    assert "chain_lost" in events and "link_restored" in events
    straighten(d)


def test_loop_statistics_are_reported(daemon):
    # a loaded machine may have slowed the loop (link health); its statistics restart at the
    # nominal rate once it is back
    assert wait_for(lambda: not daemon.status()["link_health"]["degraded"], 40.0)
    assert wait_for(lambda: daemon.loop_stats()["window"] > 100, 10.0)
    s = daemon.loop_stats()
    assert s["cycles"] > 100 and s["rate_hz"] == 100.0
    for k in ("period_us", "jitter_us", "compute_us"):
        assert set(s[k]) == {"mean", "p99", "max"}
    assert 9000 < s["period_us"]["mean"] < 15000  # loose: a loaded CI machine skips slots
    assert s["link"]["frames_ok"] > 0


def test_transforms_are_published_with_fk_of_every_frame(ready):
    d = ready
    q = d.subscribe(["transforms"])
    try:
        msgs = record(q, 0.3)
    finally:
        d.unsubscribe(q)
    assert msgs
    m = msgs[-1]
    assert set(m["frames"]) >= {"base", "segment_1_tip", "segment_2_tip", "segment_3_tip"}
    assert m["tip"]["xyz"][2] == pytest.approx(3 * 0.316, abs=0.01)  # straight: tip on z
    assert len(m["backbones"]["segment_1"]) == 12


def test_port_failure_reopens_the_port_and_recovers(ready):
    """The OS closes the device under the daemon (an adapter pulled out): the link fails, the
    daemon reports it, reopens the port with back-off and rebuilds."""
    d = ready
    q = d.subscribe(["event"])
    try:
        d.link._ser.close()  # what the kernel does to a vanished USB adapter's file
        assert wait_for(lambda: d.status()["state"] == "reconnecting", 3.0)
        assert wait_for(
            lambda: d.status()["state"] == "connected" and d.status()["segments"] == NAMES, 8.0
        )
        msgs = record(q, 0.1)
    finally:
        d.unsubscribe(q)
    events = [m["event"] for m in msgs]
    assert "link_lost" in events and "link_restored" in events
    straighten(d)
