"""`ucr view` outlives its daemon: when the daemon restarts, the page says "daemon disconnected"
(segments grey) while the view reconnects with back-off, then shows the robot again and follows
the new daemon's motion. The test owns its chain and daemons (it stops one), so it shares no rig
with other tests."""

from __future__ import annotations

import time

import pytest
from view_helpers import ROBOT, wait_for

pytestmark = pytest.mark.timeout(300)


def _start_daemon(chain, robot, port: int):
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError

    deadline = time.monotonic() + 60
    while True:
        try:
            daemon = Daemon(robot, port=chain.host_port).start()
            break
        except DaemonError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)
    deadline = time.monotonic() + 30
    while True:  # the old server's port: free again once its listener closed
        try:
            return daemon, ApiServer(daemon, "127.0.0.1", port).start()
        except OSError:
            if time.monotonic() > deadline:
                daemon.stop()
                raise
            time.sleep(0.2)


def test_view_reconnects_after_the_daemon_restarts_and_the_page_recovers(browser):
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load
    from view.app import ViewApp
    from view.source import LiveSource

    robot = load(ROBOT)
    chain = EmulatedChain(3, config_for=configs(robot))
    first = new = app = ctx = None
    try:
        first = _start_daemon(chain, robot, 0)
        daemon, srv = first
        app = ViewApp(LiveSource(srv.url, None).start(), port=0).start()
        ctx = browser.new_context(viewport={"width": 1000, "height": 700})
        page = ctx.new_page()
        page.goto(app.url)
        page.get_by_text("tubes: 3").wait_for(timeout=60000)
        source = app.source
        version = source.snap.robot_version
        port = srv.port
        srv.stop()
        daemon.stop()
        first = None
        page.get_by_text("daemon disconnected").first.wait_for(timeout=30000)
        assert not source.snap.connected
        assert wait_for(lambda: set(source.snap.status.values()) == {"missing"}, 10)
        time.sleep(2.0)  # a few failed attempts (back-off) while nothing listens
        assert "reconnecting (attempt" in source.snap.errors[0], source.snap.errors
        new = _start_daemon(chain, robot, port)
        d2, _ = new
        page.get_by_text("daemon disconnected").first.wait_for(state="detached", timeout=60000)
        assert source.snap.connected and source.reconnects == 1
        assert source.snap.robot_version > version  # robot re-read, scene rebuilt
        page.get_by_text("tubes: 3").wait_for(timeout=30000)
        # the page follows the new daemon: bend segment_1 there
        assert wait_for(lambda: d2.status()["state"] == "connected", 30)
        tip0 = list(app.facts["tip"])
        for _attempt in range(3):  # a starved emulator may abort a goal on a loaded machine
            gid = d2.send_trajectory(
                [{"time_from_start": 1.5, "segments": {"segment_1": {"kappa": 1.5, "phi": 0.0}}}]
            )
            assert wait_for(lambda g=gid: d2.trajectory_status(g)["done"], 30)
            if d2.trajectory_status(gid)["state"] == "succeeded":
                break
        assert wait_for(lambda: abs(source.snap.state["segment_1"]["kappa"] - 1.5) < 0.1, 20), (
            source.snap.state
        )
        assert wait_for(lambda: app.facts["tip"] != tip0, 10)
        page.get_by_text("segment_1: ok").wait_for(timeout=10000)
    finally:
        if ctx is not None:
            ctx.close()
        if app is not None:
            app.stop()
        for pair in (new, first):
            if pair is not None:
                pair[1].stop()
                pair[0].stop()
        chain.close()
