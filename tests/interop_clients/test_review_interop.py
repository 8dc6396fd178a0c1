"""Review of the interop clients: desktop viewers whose page is a local file (Origin ``file://``
or ``null``), one clock for every topic across a wall-clock step, the recorder and the Foxglove
server outliving a daemon restart, and SIGTERM while a command starts."""

from __future__ import annotations

import json

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from host.api.guard import GuardConfigError, WebGuard, normalize_origin

pytest.importorskip("mcap_ros2", reason="the 'record' extra (mcap-ros2-support) is not installed")

from interop.foxglove import FoxgloveSink  # noqa: E402
from interop.guard import GuardError  # noqa: E402

PROTO = ["foxglove.websocket.v1"]  # what Lichtblick / Foxglove desktop ask for
TOKEN = "desktop-viewer-token-0123"


@pytest.fixture
def sinks():
    made: list[FoxgloveSink] = []

    def make(**kw) -> FoxgloveSink:
        sink = FoxgloveSink("127.0.0.1", 0, **kw)
        made.append(sink)
        return sink

    yield make
    for s in made:
        s.close()


def _server_info(url: str, origin: str | None) -> dict:
    with connect(url, subprotocols=PROTO, origin=origin, open_timeout=10) as ws:
        return json.loads(ws.recv(timeout=10))


def _refused(url: str, origin: str | None) -> int:
    with pytest.raises(InvalidStatus) as exc:
        _server_info(url, origin)
    return exc.value.response.status_code


# -- finding 1: desktop viewers (Electron pages from file://) ---------------------------------
def test_local_file_origins_are_refused_by_default(sinks):
    sink = sinks()
    assert _refused(sink.url, "null") == 403
    assert _refused(sink.url, "file://") == 403
    assert _server_info(sink.url, None)["op"] == "serverInfo"  # no Origin: as before


def test_allow_origin_file_lets_a_desktop_app_in(sinks):
    sink = sinks(allowed_origins=["file://"])
    assert _server_info(sink.url, "file://")["op"] == "serverInfo"
    assert _refused(sink.url, "null") == 403  # a sandboxed iframe's origin: not by file://
    assert _refused(sink.url, "https://evil.example") == 403


def test_allow_origin_null_needs_a_token_and_then_the_token_is_checked(sinks):
    with pytest.raises(GuardError, match="sandboxed iframe") as exc:
        sinks(allowed_origins=["null"])  # refused when configured, before serving
    assert "--serve-token-file" in str(exc.value)
    sink = sinks(allowed_origins=["null"], token=TOKEN)
    assert _server_info(f"{sink.url}/?token={TOKEN}", "null")["op"] == "serverInfo"
    assert _refused(sink.url, "null") == 401  # no token: a web page's iframe stays out
    assert _refused(f"{sink.url}/?token={TOKEN}", "file://") == 403  # not configured


def test_the_guard_rule_is_one_for_every_surface():
    assert normalize_origin("file://") == normalize_origin("FILE:///") == "file://"
    assert normalize_origin(" null ") == "null"
    with pytest.raises(GuardConfigError, match="sandboxed iframe"):
        WebGuard.build(bind="127.0.0.1", origins=["null"])  # the API, the view: no token known
    with pytest.raises(GuardConfigError):
        normalize_origin("file:///home/me/page.html")  # an origin has no path
    g = WebGuard.build(bind="127.0.0.1", origins=["null", "file://"], token_required=True)
    assert g.check("/", {"Host": "127.0.0.1", "Origin": "null"}) is None
    assert g.check("/", {"Host": "127.0.0.1", "Origin": "file://"}) is None
    plain = WebGuard.build(bind="127.0.0.1", origins=["https://app.foxglove.dev"])
    for origin in ("null", "file://"):
        refusal = plain.check("/", {"Host": "127.0.0.1", "Origin": origin})
        assert refusal is not None and refusal.status == 403


# -- finding 4: SIGTERM while a command starts ------------------------------------------------
#: Runs ``ucr`` with the first import of one heavy module (``sys.argv[1]``) made 3 s slow, so a
#: SIGTERM surely lands during the command's heavy imports, before the command takes signals
SLOW_IMPORT = r"""
import importlib.abc, runpy, sys, time
slow = sys.argv.pop(1)
class Slow(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == slow:
            sys.meta_path.remove(self)
            print("slow import", flush=True)
            time.sleep(3)
        return None
sys.meta_path.insert(0, Slow())
sys.argv[0] = "ucr"
runpy.run_module("tools.cli", run_name="__main__", alter_sys=True)
"""


@pytest.mark.parametrize(
    ("slow", "argv"),
    [
        ("mcap_ros2", ["record", "-o", "{tmp}/r.mcap", "--duration", "5"]),
        ("mcap_ros2", ["foxglove", "--port", "0", "--duration", "5"]),
        ("mcap_ros2", ["replay", "{tmp}/none.mcap", "--port", "0"]),
        ("zenoh", ["zenoh", "--duration", "5"]),
    ],
    ids=["record", "foxglove", "replay", "zenoh"],
)
def test_sigterm_during_the_heavy_imports_exits_0(slow, argv, tmp_path):
    import signal
    import subprocess
    import sys

    from .conftest import REPO

    if slow == "zenoh":
        pytest.importorskip("zenoh", reason="the 'ros2' extra (eclipse-zenoh) is not installed")
    args = [a.format(tmp=tmp_path) for a in argv] + ["--url", "ws://127.0.0.1:9"]
    proc = subprocess.Popen([sys.executable, "-c", SLOW_IMPORT, slow, *args], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "slow import"  # in the heavy imports now
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, (proc.returncode, err)
    assert not (tmp_path / "r.mcap").exists()  # stopped before it began: no file


# -- finding 2: one clock for every topic, across a wall-clock step ----------------------------
def _feed():
    from interop.live import LiveFeed

    return LiveFeed(client=None, topics=None, out=None)


@pytest.mark.parametrize("daemon_clock", [0.0, 12345.0], ids=["same host", "remote daemon"])
def test_every_topic_follows_a_wall_clock_step(monkeypatch, daemon_clock):
    """NTP steps the wall clock (a Pi without RTC, an hour off): the streamed topics (/joint_states,
    /tf, /ucr/arcs, /rosout: stamped from the daemon's monotonic time) and the polled ones
    (goals, /ucr/segments, /ucr/loop_stats, static: the wall clock now) keep one clock."""
    import time

    feed = _feed()
    mono = time.monotonic()
    first = feed._t_ns(mono + daemon_clock)  # the first joint state: the clocks are mapped
    assert abs(first / 1e9 - time.time()) < 0.5
    real = time.time
    monkeypatch.setattr(time, "time", lambda: real() - 3600.0)  # the step
    streamed = feed._t_ns(time.monotonic() + daemon_clock)  # a later joint state
    polled = feed._t_ns(None)  # /ucr/segments of the same moment
    assert abs(streamed - polled) / 1e9 < 0.5, (streamed - polled) / 1e9
    assert abs(streamed / 1e9 - time.time()) < 0.5
    later = feed._t_ns(time.monotonic() + daemon_clock + 2.0)  # still on the daemon's clock
    assert abs((later - streamed) / 1e9 - 2.0) < 0.1


def test_a_slewing_clock_keeps_the_daemons_spacing(monkeypatch):
    """Below a step (NTP slewing the clock, the jitter of reading two clocks) the stamps keep
    the daemon's own spacing exactly: the joint states' velocities are computed on it."""
    import time

    feed = _feed()
    t = time.monotonic()
    first = feed._t_ns(t)
    real = time.time
    monkeypatch.setattr(time, "time", lambda: real() + 0.02)
    assert feed._t_ns(t + 0.02) - first == pytest.approx(20_000_000, abs=2_000)


def test_the_bridge_service_starts_once_the_clock_is_set():
    from .conftest import REPO

    lines = (REPO / "host" / "ucr-zenoh.service").read_text().splitlines()
    unit = lines[: lines.index("[Service]")]
    assert "Wants=time-sync.target" not in unit  # consumers only order after it
    assert "After=time-sync.target" in unit


# -- finding 3: the recorder and the Foxglove server outlive a daemon restart -------------------
def test_record_and_foxglove_go_on_after_a_daemon_restart(tmp_path, monkeypatch):
    """The daemon's API goes away (systemd restarts a failed daemon after 3 s) and comes back on
    the same port: `ucr record` goes on in the same file, `ucr foxglove` keeps its clients, and
    both mark the gap with a daemon_lost and a daemon_reconnected event."""
    import re
    import signal
    import struct
    import time

    from host.api.server import ApiServer
    from interop import ros2
    from interop.replay import read_recording

    from .conftest import ucr, wait_for
    from .stub_daemon import ROBOT_FILE, StubDaemon

    monkeypatch.delenv("UCR_FOXGLOVE_TOKEN", raising=False)
    stub = StubDaemon()
    api = ApiServer(stub, "127.0.0.1", 0).start()
    port, url = api.port, api.url
    path = tmp_path / "run.mcap"
    procs = [
        ucr("record", "-o", str(path), "--url", url, "--robot", str(ROBOT_FILE),
            "--flush-interval", "0.2"),
        ucr("foxglove", "--port", "0", "--url", url, "--robot", str(ROBOT_FILE)),
    ]  # fmt: skip
    rec, fox = procs
    try:
        line = fox.stderr.readline()
        m = re.search(r"(ws://\S+)", line)
        assert m, line
        with connect(m.group(1), subprotocols=PROTO, open_timeout=10) as ws:
            channels: dict[str, int] = {}
            while "/ucr/events" not in channels:
                msg = json.loads(ws.recv(timeout=10))
                if msg["op"] == "advertise":
                    channels.update({c["topic"]: c["id"] for c in msg["channels"]})
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": 1, "channelId": channels["/joint_states"]},
                {"id": 2, "channelId": channels["/ucr/events"]}]}))  # fmt: skip
            got: dict[int, list[bytes]] = {1: [], 2: []}

            def drain(seconds: float) -> None:
                end = time.monotonic() + seconds
                while (left := end - time.monotonic()) > 0:
                    try:
                        frame = ws.recv(timeout=left)
                    except TimeoutError:
                        return
                    if isinstance(frame, bytes) and frame[0] == 1:
                        got[struct.unpack_from("<I", frame, 1)[0]].append(frame[13:])

            drain(2.0)
            assert got[1], "no joint states before the restart"
            api.stop()  # the daemon goes away ...
            drain(2.0)
            before = len(got[1])
            api = ApiServer(stub, "127.0.0.1", port).start()  # ... and comes back
            assert wait_for(lambda: (drain(0.2), len(got[2]) >= 2)[1], 20), got[2]
            drain(1.0)
            assert len(got[1]) > before  # the same connection gets the live robot again
            events = [json.loads(ros2.codec("std_msgs/msg/String").decode(d).data)["event"]
                      for d in got[2]]  # fmt: skip
            assert events[:2] == ["daemon_lost", "daemon_reconnected"]
        assert fox.poll() is None and rec.poll() is None
        rec.send_signal(signal.SIGTERM)
        assert rec.wait(20) == 0, rec.stderr.read()
        err = rec.stderr.read()
        assert "lost the daemon" in err and "reconnected to the daemon" in err, err
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                p.wait(20)
        api.stop()
        stub.close()
    msgs = list(read_recording(path))  # one file, closed cleanly, across the restart
    ev = [(m.t_ns, json.loads(ros2.codec(m.typename).decode(m.data).data))
          for m in msgs if m.topic == "/ucr/events"]  # fmt: skip
    names = [e["event"] for _, e in ev]
    assert names == ["daemon_lost", "daemon_reconnected"], names
    assert ev[1][1]["gap_s"] > 1.0
    js = [m.t_ns for m in msgs if m.topic == "/joint_states"]
    assert any(t < ev[0][0] for t in js) and any(t > ev[1][0] for t in js)


def test_reconnect_survives_a_drop_during_the_robot_check_and_counts_every_feeds_drops(
    monkeypatch,
):
    """Code review of the reconnect loop: a daemon that dropped again while the robot file was
    checked after a reconnect ended `ucr record` / `ucr foxglove` (the error escaped), and the
    stream messages dropped before a reconnect were not counted (7 dropped, 2 reported)."""
    import threading

    import host.api.reconnect as reconnect_mod
    from host.api.client_errors import ApiConnectionError
    from interop import live

    calls = {"robot": 0, "feeds": 0}
    stop = threading.Event()

    def robot_for(client, path):
        calls["robot"] += 1
        if calls["robot"] == 1:
            raise ApiConnectionError("connection closed (the daemon restarts again)")
        return None, "ROBOT"

    class Out:
        def tick(self):
            pass

        def publish(self, m):
            pass

    class Topics:
        def event(self, ev, t_ns):
            return []

    class Feed:
        def __init__(self, client):
            calls["feeds"] += 1
            self.n = calls["feeds"]
            self.out, self.topics = Out(), Topics()
            self.dropped = 5 if self.n == 1 else 2

        def _t_ns(self, t):
            return 0

        def run(self, stop_, duration=None, on_tick=None):
            if self.n == 1:
                raise ApiConnectionError("gone")
            stop.set()

    class Client:
        url = "ws://x"

        def close(self):
            pass

    monkeypatch.setattr(live, "robot_for", robot_for)
    monkeypatch.setattr(reconnect_mod, "RECONNECT_FIRST_S", 0.01)
    said: list[str] = []
    got = live.run_reconnecting(
        live.DaemonLink(Client()), Feed, stop, Client, robot_text="ROBOT", robot_path=None,
        say=said.append,
    )  # fmt: skip
    assert got == 7, said
    assert calls == {"robot": 2, "feeds": 2}
    assert any("lost the daemon again" in line for line in said), said
