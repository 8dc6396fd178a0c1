"""The Python client as a script meets it (review 2026-11-28, each seen failing before):
- a ``progress`` callback that called the client waited out the whole timeout (it ran on the
  reader thread, which delivers the replies) and was told it timed out though the call ran;
- ``wait_trajectory`` on a goal another client sent, or one waited for already, never returned;
- the daemon going away during a wait came back as a "final status" ``{"state": "unknown"}``;
- Ctrl-C while ``send_trajectory`` waited left the robot moving;
- ``subscribe(buffer=0)`` killed the connection at the first message; ``connect(timeout=None)``
  connected, then ``send_trajectory`` raised a raw TypeError;
- ``switch(start="jtc")`` asked for controllers "j", "t" and "c"; ``send_trajectory`` of a
  generator raised TypeError (``len``); ``ffc_input`` of a list raised AttributeError;
- a URL with a path the daemon does not serve raised ApiAuthError (a PermissionError: "check
  your token") instead of naming the wrong path."""

from __future__ import annotations

import threading

import pytest

from host.api.client import ApiConnectionError, ApiError, connect
from host.api.client_goals import final_or_raise

pytestmark = pytest.mark.timeout(60)

POINTS = [{"time_from_start": 0.6, "segments": {"s1": {"kappa": 1.0, "phi": 0.0}}}]


def test_a_progress_callback_may_call_the_client(stub_server) -> None:
    with connect(stub_server.url, timeout=2.0) as c:
        got: list = []

        def progress(status: dict) -> None:
            if not got:  # once: what a script does to look at something else meanwhile
                try:
                    got.append(c.status())
                except Exception as exc:  # noqa: BLE001 - recorded, the test says what
                    got.append(exc)
            got.append(threading.current_thread().name)

        final = c.send_trajectory(POINTS, progress=progress)
        assert final["state"] == "succeeded"
        assert isinstance(got[0], dict), got[0]  # answered, not an ApiTimeoutError
        # every callback ran before send_trajectory returned, on the callbacks' thread
        assert set(got[1:]) == {"ucr-api-callbacks"}, got


def test_wait_trajectory_waits_for_any_goal_and_twice(stub_server) -> None:
    with connect(stub_server.url) as a, connect(stub_server.url) as b:
        goal = a.send_trajectory(POINTS, wait=False)
        assert b.wait_trajectory(goal, timeout=10)["state"] == "succeeded"  # not b's goal
        assert a.wait_trajectory(goal, timeout=10)["state"] == "succeeded"
        assert a.wait_trajectory(goal, timeout=10)["state"] == "succeeded"  # read already


def test_an_unknown_end_is_an_error_not_a_status() -> None:
    with pytest.raises(ApiConnectionError, match="the daemon is not reachable; how the goal"):
        final_or_raise("g1", {"state": "unknown", "error": "the daemon is not reachable"})
    done = {"state": "succeeded", "progress": 1.0}
    assert final_or_raise("g1", done) is done


def test_ctrl_c_while_waiting_cancels_the_goal(stub_server, stub, monkeypatch) -> None:
    cancelled: list[str] = []
    real = stub.cancel_trajectory
    monkeypatch.setattr(stub, "cancel_trajectory", lambda gid: cancelled.append(gid) or real(gid))
    with connect(stub_server.url) as c:

        def interrupted(goal, timeout=None):
            raise KeyboardInterrupt

        monkeypatch.setattr(c, "wait_trajectory", interrupted)
        with pytest.raises(KeyboardInterrupt):
            c.send_trajectory(POINTS)
        assert cancelled == [c.last_goal]


def test_numbers_a_script_passes_are_checked_where_it_passes_them(stub_server) -> None:
    for bad in (None, "5", 0, -1.0, float("nan"), True):
        with pytest.raises(ValueError, match="timeout must be a"):
            connect(stub_server.url, timeout=bad)
    with connect(stub_server.url) as c:
        for bad in (0, -3, 2.5, None):
            with pytest.raises(ValueError, match="buffer must be a whole number"):
                c.subscribe(["joint_states"], buffer=bad)
        with c.subscribe(["joint_states"], buffer=1) as sub:  # the smallest works
            assert sub.get(timeout=5) is not None
        assert c.status()  # and the connection is fine


def test_arguments_of_other_shapes_mean_what_a_script_means(stub_server, stub) -> None:
    with connect(stub_server.url) as c:
        c.switch(start="ffc", stop="jtc")  # one name each
        c.switch(start=("jtc",), stop=(n for n in ["ffc"]))
        assert stub.switch_calls == [(["ffc"], ["jtc"]), (["jtc"], ["ffc"])]
        goal = c.send_trajectory((p for p in POINTS), wait=False)  # a generator: read once
        assert goal in stub.goals and stub.goals[goal]["duration"] == POINTS[-1]["time_from_start"]
        for bad, said in [
            (POINTS[0], "points: expected a list of waypoints, got dict (one waypoint: put it"),
            ("abc", "points: expected a list of waypoints, got str"),
            (3, "points: expected a list of waypoints, got int"),
        ]:
            with pytest.raises(ApiError) as info:
                c.send_trajectory(bad, wait=False)
            assert info.value.code == "invalid_params" and info.value.message.startswith(said)
        with pytest.raises(ApiError) as info:  # the daemon's own words for it
            c.ffc_input([("s1", (0.5, 0.0))])
        assert info.value.code == "invalid_params", info.value
        assert "rates: expected an object {name: [dkx, dky]}, got" in info.value.message
        assert c.status()  # the connection is fine


def test_a_path_the_daemon_does_not_serve_is_a_wrong_url_not_a_refused_token(stub_server) -> None:
    with pytest.raises(ApiConnectionError) as info:
        connect(stub_server.url.rstrip("/") + "/api/v1")
    assert not isinstance(info.value, PermissionError) and info.value.code == "wrong_path"
    assert "serves no API there: nothing at '/api/v1'" in info.value.message
    assert "check --url" in info.value.message
