"""Each part of the daemon works alone, without a daemon, a chain or a loop thread: the
publication fan-out, the publisher thread, the per-cycle supervision (SMCS) and motion."""

from __future__ import annotations

import threading
from types import SimpleNamespace

import pytest

from host.config import DaemonConfig, WatchdogConfig
from host.controllers.base import RobotState
from host.errors import DaemonError, GoalNotFound
from host.motion import Motion
from host.publisher import Fanout, PublisherThread
from host.supervision import Supervisor, describe_event, is_news


def test_fanout_delivers_by_kind_and_a_full_queue_drops_its_oldest_message():
    f = Fanout()
    q = f.subscribe(["events"], maxsize=2)
    js = f.subscribe("joint_states")
    for k in range(3):
        f.emit_event("e", message=str(k))
    got = [q.get_nowait()["message"] for _ in range(q.qsize())]
    assert got == ["1", "2"] and f.dropped == 1
    assert js.empty() and len(f.recent_events) == 3
    f.unsubscribe(q)
    f.publish({"kind": "event"})
    assert q.empty()
    with pytest.raises(ValueError, match="unknown subscription kind"):
        f.subscribe(["nonsense"])


def test_publisher_thread_runs_work_inline_until_started_then_in_its_thread():
    p = PublisherThread()
    seen: list[str] = []
    p.submit(lambda: seen.append(threading.current_thread().name))
    assert seen == [threading.current_thread().name]
    p.start()
    done = threading.Event()
    p.submit(lambda: (seen.append(threading.current_thread().name), done.set()))
    assert done.wait(10.0)
    p.stop()
    assert seen[-1] == "ucr-publisher" and p.stats()["done"] == 1


def _hwi(n: int, status: set[str] | None = None, missing: int = 0) -> SimpleNamespace:
    names = [f"segment_{i + 1}" for i in range(n)]
    st = {"status": status or set()}
    return SimpleNamespace(
        names=names,
        missing=[missing] * n,
        raw_states=[st] * n,
        resume_pending=False,
        extra_states=[],
    )


def _supervisor(events: list, reheld: list) -> Supervisor:
    return Supervisor(
        WatchdogConfig(missed_cycles=3, silence_s=0.0),
        0.01,
        lambda ev, message="", **kw: events.append((ev, message)),
        lambda state, msg, segments=None: reheld.append(msg),
    )


def test_supervisor_reports_a_silent_segment_as_a_topology_change_to_verify():
    events: list = []
    sup = _supervisor(events, [])
    descs = [{"name": "a"}, {"name": "b"}]
    reason = sup.check(_hwi(2, missing=3), RobotState.zeros([]), [], descs)
    assert reason.startswith("no STATE from segment_1 (position 1), segment_2") and sup.silent


def test_supervisor_tells_news_from_duplicate_events_and_re_holds_holding_segments():
    descs = [{"name": "a"}, {"name": "b", "downstream_present": False}]
    assert not is_news("DOWNSTREAM_DOWN", 1, descs)  # the tip lost nobody we knew of
    assert is_news("DOWNSTREAM_DOWN", 0, descs) and is_news("BOOT", 1, descs)
    assert describe_event({"name": "BOOT", "position": 1}, descs) == "b (position 2): booted"
    events: list = []
    reheld: list = []
    sup = _supervisor(events, reheld)
    hwi = _hwi(2, status={"HOLD"})
    ev = [{"name": "WATCHDOG_TRIPPED", "position": 1, "detail": 2}]
    assert sup.check(hwi, RobotState.zeros([]), ev, descs) is None
    assert len(reheld) == 1 and hwi.resume_pending
    assert [e for e, _ in events] == ["watchdog_tripped", "segments_held"]
    assert sup.check(hwi, RobotState.zeros([]), [], descs) is None and len(reheld) == 1


def test_motion_without_controllers_refuses_through_ready_and_knows_no_goals():
    def not_ready() -> None:
        raise DaemonError("daemon is not running")

    m = Motion(DaemonConfig(), threading.RLock(), lambda *a, **k: None, not_ready, 0.01)
    assert m.abort_goals("test") == [] and m.controllers() == []
    assert m.summary() == {"active_controllers": [], "running_goals": [], "manual_control": []}
    with pytest.raises(DaemonError, match="not running"):
        m.send_trajectory([])
    with pytest.raises(GoalNotFound):
        m.trajectory_status("nope")
