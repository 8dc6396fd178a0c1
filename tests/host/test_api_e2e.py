"""End to end: API client -> API server -> real Daemon -> emulated 3-segment chain (the real
firmware on the MicroPython VM). Trajectories, subscriptions, teleop replay with deadman,
disconnect cleanup and malformed requests that must not disturb the control loop."""

from __future__ import annotations

import contextlib
import json
import math
import socket
import time
from pathlib import Path

import pytest
from websockets.sync.client import connect as ws_connect

from host.api import schema
from host.api.client import ApiError, connect, on_behalf_of
from host.teleop import ReplaySource, Teleop

pytestmark = pytest.mark.timeout(120)
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def rig():
    """(daemon, server) on an emulated chain of softrobot3; everything torn down afterwards."""
    from tools.rig import EmulatedRig

    with EmulatedRig(ROOT / "robots" / "softrobot3.ucrdf", boot_timeout_s=15) as r:
        yield r.daemon, r.srv


@pytest.fixture
def client(rig):
    _, srv = rig
    c = connect(srv.url)
    yield c
    c.close()


def joint(c, name: str, timeout: float = 3.0) -> dict:
    """Measured joint state of one segment; waits out a moment where it is not valid (e.g. the
    daemon rebuilding after a segment missed replies on a heavily loaded machine)."""
    deadline = time.monotonic() + timeout
    while True:
        st = c.status()
        js = st["joint_states"].get(name)
        if js is not None and js["valid"] and st["state"] == "connected":
            return js
        if time.monotonic() > deadline:
            raise AssertionError(f"no valid state for {name}: {st}")
        time.sleep(0.02)


def kappa_of(c, name: str) -> float:
    return joint(c, name)["kappa"]


def ensure_jtc(c) -> None:
    """Give control back to the trajectory controller if a teleop test took it."""
    if c.status()["manual_control"]:
        c.hand_back()


def test_status_and_topology_report_three_controlled_segments(client):
    st = client.status()
    assert st["state"] == "connected" and st["hwi"] == "active"
    assert client.topology()["controlled"] == ["segment_1", "segment_2", "segment_3"]
    assert client.loop_stats()["cycles"] > 0
    assert {c["name"] for c in client.controllers()} >= {"jtc", "ffc", "jsb"}


def test_subscribe_receives_joint_states_of_every_segment(client):
    with client.subscribe(["joint_states"], max_rate=20) as sub:
        msgs = [sub.get(timeout=3) for _ in range(5)]
        # every segment measured: a host stalled under load marks states invalid for a moment
        # (a gap in them: docs/daemon.md "No motion without a command"), so wait that out
        valid = next((m for m in msgs if m and all(m["valid"])), None)
        for _ in range(60):
            if valid is not None:
                break
            m = sub.get(timeout=3)
            valid = m if m and all(m["valid"]) else None
    assert all(m is not None and m["kind"] == "joint_states" for m in msgs)
    assert msgs[0]["names"] == ["segment_1", "segment_2", "segment_3"]
    assert len(msgs[0]["kappa"]) == 3 and valid is not None, msgs[-1]
    stamps = [m["t"] for m in msgs]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] >= 4 * 0.05 * 0.8  # <= 20 Hz


def test_trajectory_through_the_client_reaches_the_goal(client):
    ensure_jtc(client)
    seen = []
    points = [
        {"time_from_start": 0.6, "segments": {"segment_1": {"kappa": 2.0, "phi": 0.5}}},
        {
            "time_from_start": 1.2,
            "segments": {
                "segment_1": {"kappa": 3.0, "phi": 0.5},
                "segment_3": {"kx": 0.0, "ky": -1.5},
            },
        },
    ]
    with on_behalf_of("operator at bench 2"):
        result = client.send_trajectory(points, progress=seen.append, timeout=20)
    assert result["state"] == "succeeded", result
    assert len(seen) >= 5 and seen[-1]["progress"] == pytest.approx(1.0)
    # the goal names who sent it, through the API's bridge into the real daemon
    me = client.session()
    sender = {"peer": me["peer"], "client": me["agent"], "for": "operator at bench 2"}
    assert result["from"] == sender
    assert client.trajectory_status(result["id"])["from"] == sender
    # `status` comes from the API process's snapshot (every 50 ms, docs/api.md): the one read
    # right after the success may predate the measurement the success was judged on
    deadline = time.monotonic() + 1.0
    while True:
        s1, s3 = joint(client, "segment_1"), joint(client, "segment_3")
        if abs(s3["kappa"] - 1.5) <= 0.05 and abs(s1["kappa"] - 3.0) <= 0.05:
            break
        if time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert s1["kappa"] == pytest.approx(3.0, abs=0.05)
    assert s1["phi"] == pytest.approx(0.5, abs=0.02)
    assert s3["kappa"] == pytest.approx(1.5, abs=0.05)


def test_trajectory_beyond_limits_is_rejected_and_nothing_moves(client):
    ensure_jtc(client)
    before = kappa_of(client, "segment_2")
    with pytest.raises(ApiError) as info:
        client.send_trajectory(
            [{"time_from_start": 1.0, "segments": {"segment_2": {"kappa": 1e4, "phi": 0.0}}}]
        )
    assert info.value.code == schema.REJECTED and "kappa_max" in info.value.message
    time.sleep(0.2)
    assert kappa_of(client, "segment_2") == pytest.approx(before, abs=1e-3)


def test_bad_requests_get_errors_and_do_not_disturb_the_loop(rig, client):
    daemon, srv = rig
    stats0 = client.loop_stats()
    with ws_connect(srv.url, max_size=None) as ws:
        bad = [
            "{",
            "[]",
            '{"id": 1, "op": "nope"}',
            '{"id": 2, "op": "status", "x": 1}',
            json.dumps({"id": 3, "op": "ffc.input", "rates": {"segment_1": [5, 0]}}),
            json.dumps({"id": 4, "pad": "x" * 70000}),
            b"\x00\x01",
        ]
        for _ in range(20):
            for frame in bad:
                ws.send(frame)
                reply = json.loads(ws.recv(timeout=5))
                assert reply["ok"] is False
    # Errors the daemon itself reports come back as error replies too.
    with pytest.raises(ApiError) as info:
        client.ffc_input({"no_such_segment": (0.5, 0.0)})
    assert info.value.code == schema.REJECTED and "no_such_segment" in info.value.message
    with pytest.raises(ApiError) as info:
        client.trajectory_status("jtc-999-nope")
    assert info.value.code == schema.NOT_FOUND
    time.sleep(0.3)
    stats1 = client.loop_stats()
    assert stats1["cycles"] > stats0["cycles"] + 20  # the loop kept running
    assert client.status()["state"] == "connected"


def _stable(c, name: str, settle: float = 0.3) -> tuple[float, float]:
    a = kappa_of(c, name)
    time.sleep(settle)
    return a, kappa_of(c, name)


def test_teleop_replay_moves_a_segment_and_deadman_stops_it(client, tmp_path):
    rec = tmp_path / "stick.jsonl"
    # Full deflection on segment_2 for 0.6 s, then the input just stops (no release).
    rec.write_text(
        json.dumps({"t": 0.0, "rates": {"segment_2": [0.0, 1.0]}})
        + "\n"
        + json.dumps({"t": 0.6, "end": True})
        + "\n"
    )
    events = client.subscribe(["events"])
    start = kappa_of(client, "segment_2")
    try:
        result = Teleop(client.ffc_input, rate_hz=50).run(ReplaySource(rec))
        t_end = time.monotonic()
        assert result.reason == "end" and result.sent >= 20 and result.zeros_sent == 0
        moved = kappa_of(client, "segment_2")
        assert moved > start + 0.1  # it bent while the stick was held
        time.sleep(max(0.0, t_end + 0.6 - time.monotonic()))  # deadman 0.3 s + margin
        a, b = _stable(client, "segment_2", 0.5)
        assert b == pytest.approx(a, abs=0.01)  # stopped without any further input
        ffc = next(c for c in client.controllers() if c["name"] == "ffc")
        assert ffc["state"] == "active" and ffc["deadman_tripped"] is True
        # who sent the latest input, through the API's bridge into the real daemon's cFFC
        me = client.session()
        assert ffc["input_from"] == {"peer": me["peer"], "client": me["agent"]}
        names = []
        while (m := events.get(timeout=0.5)) is not None:
            names.append(m.get("event"))
        assert "manual_takeover" in names
    finally:
        events.close()
        ensure_jtc(client)


def test_client_vanishing_mid_ffc_stream_stops_motion_and_is_cleaned_up(rig, client):
    daemon, srv = rig
    subs_before = len(daemon._subs)
    ws = ws_connect(srv.url)
    ws.send(json.dumps({"id": 0, "op": "subscribe", "kinds": ["joint_states", "transforms"]}))
    for i in range(15):
        ws.send(json.dumps({"id": i + 1, "op": "ffc.input", "rates": {"segment_3": [0.8, 0.0]}}))
        time.sleep(0.02)
    assert len(daemon._subs) == subs_before + 1
    ws.socket.shutdown(socket.SHUT_RDWR)  # killed client: no closing handshake
    ws.socket.close()
    deadline = time.monotonic() + 5
    while (srv.stats()["clients"] > 1 or len(daemon._subs) > subs_before) and (
        time.monotonic() < deadline
    ):
        time.sleep(0.02)
    assert srv.stats()["clients"] == 1  # only the test's own client remains
    assert len(daemon._subs) == subs_before
    # The server zeroed its cFFC input; once the segment has caught up with its last command
    # (the firmware slews at kappa_rate_max) nothing moves any more.
    time.sleep(0.5)
    a, b = _stable(client, "segment_3", 0.3)
    assert b == pytest.approx(a, abs=0.01)
    ensure_jtc(client)


def test_cli_move_against_the_real_daemon(rig, client, capsys):
    from tools.cli import main as ucr

    _, srv = rig
    ensure_jtc(client)
    rc = ucr(
        [
            "move",
            "--url",
            srv.url,
            "--segment",
            "segment_2",
            "--kappa",
            "1.5",
            "--phi",
            "-90",
            "--duration",
            "0.5",
        ]
    )
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "succeeded" in out
    js = joint(client, "segment_2")
    assert js["kappa"] == pytest.approx(1.5, abs=0.05)
    assert js["phi"] == pytest.approx(-1.5708, abs=0.02)
    assert ucr(["status", "--url", srv.url]) == 0
    assert "segment_2" in capsys.readouterr().out


def test_cli_teleop_replay_drives_a_segment_and_reports(rig, client, capsys, tmp_path):
    from tools.cli import main as ucr

    _, srv = rig
    rec = tmp_path / "stick.jsonl"
    rec.write_text(
        json.dumps({"t": 0.0, "rates": {"segment_1": [-1.0, 0.0]}})
        + "\n"
        + json.dumps({"t": 0.4, "stop": True})
        + "\n"
    )
    before = joint(client, "segment_1")
    changes = client.status()["topology_changes"]
    try:
        rc = ucr(["teleop", "--url", srv.url, "--replay", str(rec)])
        out, err = capsys.readouterr()
        assert rc == 0, err
        assert "teleop ended (end" in out and "1 stops sent" in out
        assert ucr(["controllers", "--url", srv.url]) == 0  # who drove the cFFC last
        listed = capsys.readouterr().out
        assert ucr(["status", "--url", srv.url]) == 0  # and who holds the takeover
        shown = capsys.readouterr().out
        if client.status()["topology_changes"] == changes:  # a rebuild resets the takeover
            assert "hand-back" in out  # tells the user how to give control back
            assert "latest input from API client 'ucr teleop' at 127.0.0.1:" in listed, listed
            assert "setpoint segment_1 κ " in listed, listed  # where the active cFFC commands
            assert "  ffc: latest input from API client 'ucr teleop' at " in shown, shown
        time.sleep(0.4)
        after = joint(client, "segment_1")
        kx_before = before["kappa"] * math.cos(before["phi"])
        kx_after = after["kappa"] * math.cos(after["phi"])
        assert kx_after < kx_before - 0.1  # stick left -> curvature vector moved towards -x
        bad = tmp_path / "bad.jsonl"
        bad.write_text('{"t": 0, "rates": {"no_such": [0.5, 0]}}\n')
        rc = ucr(["teleop", "--url", srv.url, "--replay", str(bad)])
        _, err = capsys.readouterr()
        assert rc == 1 and "no_such not controlled by the daemon" in err
    finally:
        ensure_jtc(client)


def test_cli_goal_shows_and_cancels_a_goal_sent_with_no_wait(rig, client, capsys):
    """Review 2026-11-26: `--no-wait` printed a goal id that no `ucr` command accepted; from
    the CLI such a goal could only be stopped by sending another one."""
    from tools.cli import main as ucr

    _, srv = rig
    ensure_jtc(client)
    gid = client.send_trajectory(
        [{"time_from_start": 20.0, "segments": {"segment_1": {"kappa": 0.3, "phi": 0.0}}}],
        wait=False,
    )
    try:
        assert ucr(["goal", gid, "--url", srv.url]) == 0
        out = capsys.readouterr().out
        assert out.startswith(f"goal {gid}: executing") and "%" in out, out
        me = client.session()  # and who sent it, as the daemon names it
        assert f"; sent by API client 'ucr python client' at {me['peer']}" in out, out
        assert ucr(["goal", "--url", srv.url]) == 0  # every running goal
        assert f"goal {gid}: executing" in capsys.readouterr().out
        assert ucr(["goal", "--cancel", "--url", srv.url]) == 0
        assert "canceled: decelerating to rest" in capsys.readouterr().out
        end = time.monotonic() + 10
        while not client.trajectory_status(gid)["done"] and time.monotonic() < end:
            time.sleep(0.1)
        assert ucr(["goal", "--url", srv.url]) == 0
        assert capsys.readouterr().out.strip() == "no running goal"
        # --json: one JSON object per goal, so none is no line (`| jq` got plain words, a review)
        assert ucr(["goal", "--json", "--url", srv.url]) == 0
        captured = capsys.readouterr()
        assert captured.out == "" and "no running goal" in captured.err
        assert ucr(["goal", "jtc-nope", "--url", srv.url]) == 1
        assert "unknown goal id 'jtc-nope'" in capsys.readouterr().err
    finally:
        with contextlib.suppress(Exception):
            client.cancel(gid)
