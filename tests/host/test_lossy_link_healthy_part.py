"""Issue 12 "Degrade, don't stall", audit defect 1: a lossy link at the tip must not take the
healthy part of the chain down with it. On the emulated chain (real firmware, fault injection
with ``chain.set_link`` / ``unplug`` / ``plug``), driving the daemon through its Python
interface:

- a topology change aborts only the goals that move a segment it concerns: a goal on
  segment_1 runs on while segment_3 is unplugged and plugged back (carried over both rebuilds),
  a goal on segment_3 is aborted naming segment_3;
- with 1 % byte corruption on link 3, goals on segment_1 succeed, the topology does not flap
  (rejoin hysteresis) and the watchdogs of segment_1 and segment_2 never trip (the rediscovery
  feeds them);
- the chain cut is reported with 1-based positions (``topology()["cut"]["after_position"]``).
"""

from __future__ import annotations

import queue
import time

import pytest
from daemon_helpers import wait_for

from host.daemon import Daemon

pytestmark = [pytest.mark.timeout(300), pytest.mark.alone]  # recovery times: conftest.py

NAMES = ["segment_1", "segment_2", "segment_3"]


@pytest.fixture()
def ready(daemon, chain):
    for k in range(3):
        chain.plug(k)
        chain.set_link(k, latency=0.0, corrupt_rate=0.0, baud=None)

    def all_back() -> bool:
        st = daemon.status()
        return st["segments"] == NAMES and all(v["valid"] for v in st["joint_states"].values())

    assert wait_for(all_back, 15.0)
    yield daemon
    for k in range(3):
        chain.plug(k)
        chain.set_link(k, corrupt_rate=0.0)
    wait_for(all_back, 15.0)


def drain(q: queue.Queue) -> list[dict]:
    out = []
    while True:
        try:
            out.append(q.get_nowait())
        except queue.Empty:
            return out


def wait_done(d: Daemon, gid: str, timeout: float = 15.0) -> dict:
    assert wait_for(lambda: d.trajectory_status(gid)["done"], timeout)
    return d.trajectory_status(gid)


def test_a_goal_on_healthy_segments_runs_on_while_the_tip_is_unplugged_and_plugged(ready, chain):
    d = ready
    for _attempt in range(3):
        gid = d.send_trajectory(
            [
                {"time_from_start": 1.5, "segments": {"segment_1": {"kappa": 0.6, "phi": 0.2}}},
                {"time_from_start": 3.0, "segments": {"segment_1": {"kappa": 0.2, "phi": 0.2}}},
            ]
        )
        time.sleep(0.5)
        chain.unplug(2)
        assert wait_for(lambda: d.status()["segments"] == NAMES[:2], 3.0)
        during = d.trajectory_status(gid)
        # audit defect 6: positions users see are 1-based (cut after segment_2, position 2)
        assert d.topology()["cut"] == {
            "after_position": 2,
            "after": "segment_2",
            "lost": ["segment_3"],
        }
        chain.plug(2)
        assert wait_for(lambda: d.status()["segments"] == NAMES, 3.0)
        st = wait_done(d, gid)
        abort = st.get("abort") or {}
        if st["state"] == "aborted" and abort.get("segment") != "segment_3":
            # a starved emulated segment_1/2 on a loaded host (its BOOT, a gap): not what is
            # tested here; once more
            time.sleep(1.0)
            continue
        assert during["state"] == "executing", during  # carried over the loss
        assert st["state"] == "succeeded", st  # ... and over the rejoin
        break
    else:
        pytest.fail(f"segment_1/segment_2 disturbed in every attempt: {st}")
    # a goal that moves the segment that is lost is aborted, naming it and an explicit cause
    gid3 = d.send_trajectory(
        [{"time_from_start": 3.0, "segments": {"segment_3": {"kappa": 0.8, "phi": 0.0}}}]
    )
    time.sleep(0.3)
    chain.unplug(2)
    st3 = wait_done(d, gid3, 5.0)
    assert st3["state"] == "aborted", st3
    assert st3["abort"]["segment"] == "segment_3", st3
    assert st3["abort"]["cause"] in ("topology_change", "link_loss"), st3


def test_a_lossy_tip_link_leaves_the_healthy_segments_under_control(ready, chain):
    d = ready
    q = d.subscribe(["event"])
    try:
        changes0 = d.status()["topology_changes"]
        chain.set_link(2, corrupt_rate=0.01)  # `corrupt 3 0.01` on the control socket
        t_end = time.monotonic() + 6.0
        results = []
        while time.monotonic() < t_end:
            gid = d.send_trajectory(
                [
                    {"time_from_start": 0.5, "segments": {"segment_1": {"kappa": 0.5}}},
                    {"time_from_start": 1.0, "segments": {"segment_1": {"kappa": 0.1}}},
                ]
            )
            results.append(wait_done(d, gid))
        changes = d.status()["topology_changes"] - changes0
        chain.set_link(2, corrupt_rate=0.0)
        events = drain(q)
    finally:
        d.unsubscribe(q)
    trips = [
        e for e in events if e.get("event") == "watchdog_tripped" and e.get("position") in (1, 2)
    ]
    aborted = [r for r in results if r["state"] != "succeeded"]
    flaps = [e for e in events if e.get("event") == "topology_changed"]
    # goals naming only segment_1 are never aborted by what happens at segment_3
    assert not [r for r in aborted if r["abort"]["cause"] == "topology_change"], aborted
    assert len(aborted) <= 1, aborted  # (one for a starved emulated segment on a loaded host)
    assert len(results) >= 3
    # segment_1 and segment_2 keep getting their cyclic frames during rebuilds and probes
    assert trips == [], trips
    # no flapping: a few rebuilds in 6 s, not several a second
    assert changes <= 6, [e["message"] for e in flaps]
