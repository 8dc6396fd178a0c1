"""The daemon's side of segment safety (issue 11, findings 3 and 7): a segment in FAULT shows in
``status`` (name, reason), as events, and in `ucr status`; the API op ``faults.clear`` and
`ucr clear-fault` send CLEAR_FAULT, after which the segment holds and is resumed; a STATE whose
applied position is not its own (a misaddressed SYNC) makes the daemon hold and report it."""

from __future__ import annotations

import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from host.config import WatchdogConfig
from host.controllers.base import RobotState
from host.supervision import Supervisor

pytestmark = pytest.mark.timeout(120)
ROOT = Path(__file__).resolve().parents[2]


def _supervisor(events: list) -> Supervisor:
    return Supervisor(
        WatchdogConfig(missed_cycles=3, silence_s=0.0),
        0.01,
        lambda ev, message="", **kw: events.append((ev, message, kw)),
        lambda state, msg, segments=None: None,
    )


def _hwi(states: list[dict]) -> SimpleNamespace:
    n = len(states)
    return SimpleNamespace(
        names=[f"segment_{i + 1}" for i in range(n)],
        missing=[0] * n,
        raw_states=states,
        resume_pending=False,
    )


def test_supervisor_holds_and_reports_a_misaddressed_setpoint():
    events: list = []
    sup = _supervisor(events)
    ok = {"status": set(), "applied_position": 0}
    hwi = _hwi([ok, {"status": set(), "applied_position": 2}])
    reason = sup.check(hwi, RobotState.zeros([]), [], [{"name": "a"}, {"name": "b"}])
    assert reason and "segment_2 (position 2) applied the setpoint of position 3" in reason
    assert [e[0] for e in events] == ["misaddressed"]
    # the daemon turns a reason into hold + rediscovery (topology follower); a correct chain
    # (or an old firmware without key 9) is not news
    hwi = _hwi([ok, {"status": set(), "applied_position": 1}, {"status": set()}])
    assert sup.check(hwi, RobotState.zeros([]), [], [{}, {}, {}]) is None


def test_supervisor_keeps_a_fault_until_the_state_shows_it_cleared():
    events: list = []
    sup = _supervisor(events)
    faulty = {"status": {"FAULT", "HOLD"}}
    ev = [{"name": "FAULT", "position": 0, "detail": 1, "text": "tick: RuntimeError: boom"}]
    sup.check(_hwi([faulty]), RobotState.zeros([]), ev, [{"name": "a"}])
    assert sup.faults["segment_1"]["name"] == "TICK_EXCEPTION"
    assert sup.faults["segment_1"]["position"] == 1  # counted from 1, as users read it
    assert "boom" in sup.faults["segment_1"]["text"]
    assert "boom" in events[0][1] and events[0][2]["text"].endswith("boom")
    sup.check(_hwi([faulty]), RobotState.zeros([]), [], [{"name": "a"}])
    assert "segment_1" in sup.faults
    sup.check(_hwi([{"status": {"HOLD"}}]), RobotState.zeros([]), [], [{"name": "a"}])
    assert sup.faults == {}


@pytest.fixture(scope="module")
def rig():
    from tools.rig import EmulatedRig

    with EmulatedRig(ROOT / "robots" / "softrobot3.ucrdf", boot_timeout_s=15) as r:
        yield r.daemon, r.srv


def _wait(pred, timeout: float = 10.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def test_a_segment_fault_is_surfaced_and_cleared_through_the_api_and_the_cli(rig, capsys):
    from host.api.client import connect
    from tools.cli import main as ucr

    daemon, srv = rig
    c = connect(srv.url)
    try:
        assert _wait(lambda: c.status()["state"] == "connected")
        # an exception in segment_2's control tick (fault injection on the emulated servos)
        daemon.link.param_set(1, 5, "0:raise")
        # the FAULT status bit may arrive first; the EVENT then names the fault and its reason
        assert _wait(
            lambda: c.status()["faults"].get("segment_2", {}).get("name") == "TICK_EXCEPTION"
        )
        f = c.status()["faults"]["segment_2"]
        assert f["name"] == "TICK_EXCEPTION" and "injected" in f["text"]
        evs = [e for e in daemon.fanout.recent_events if e["event"] == "fault"]
        assert evs and "segment_2" in evs[-1]["message"] and "injected" in evs[-1]["message"]
        assert ucr(["status", "--url", srv.url]) == 0
        out = capsys.readouterr().out
        assert "FAULT TICK_EXCEPTION" in out and "ucr clear-fault" in out
        # the cause goes away, but only an explicit clear ends FAULT
        daemon.link.param_set(1, 5, "none")
        time.sleep(0.5)
        assert "segment_2" in c.status()["faults"]
        res = c.clear_fault("segment_2")
        assert res["sent_to"] == ["segment_2"] and "segment_2" in res["faults"]
        assert _wait(lambda: "segment_2" not in c.status()["faults"])
        # a second fault, cleared with the CLI this time
        daemon.link.param_set(1, 5, "0:raise")
        assert _wait(lambda: "segment_2" in c.status()["faults"])
        daemon.link.param_set(1, 5, "none")
        assert ucr(["clear-fault", "segment_2", "--url", srv.url]) == 0
        assert "CLEAR_FAULT sent to segment_2" in capsys.readouterr().out
        assert _wait(lambda: c.status()["faults"] == {})
        # and it moves again: the daemon resumes a held segment
        gid = c.send_trajectory(
            [{"time_from_start": 0.5, "segments": {"segment_2": {"kappa": 1.0, "phi": 0.0}}}]
        )
        assert gid
        assert _wait(lambda: abs(c.status()["joint_states"]["segment_2"]["kappa"] - 1.0) < 0.05)
        assert ucr(["clear-fault", "no_such_segment", "--url", srv.url]) != 0
    finally:
        c.close()


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan")])
def test_the_daemon_refuses_a_robot_with_an_invalid_kappa_max(bad):
    from host.errors import ConfigError
    from host.limits import bendable_limits
    from ucrdf.parser import load

    robot = load(ROOT / "robots" / "softrobot3.ucrdf")  # then edited in code, as compose does
    robot.bendables["segment_2"].model.limits.kappa_max = bad
    with pytest.raises(ConfigError, match="kappa_max"):
        bendable_limits(robot)
