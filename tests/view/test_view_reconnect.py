"""`ucr view` outlives its daemon: when the daemon restarts, the page says "daemon disconnected"
(segments grey) while the view reconnects with back-off, then shows the robot again and follows
the new daemon's motion. Its own module: the test restarts the module's daemon."""

from __future__ import annotations

import time

import pytest
from view_helpers import wait_for

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


def test_view_reconnects_after_the_daemon_restarts_and_the_page_recovers(rig, live_view, page):
    chain, daemon, srv = rig
    page.get_by_text("tubes: 3").wait_for(timeout=60000)
    source = live_view.source
    version = source.snap.robot_version
    robot, port = daemon.robot, srv.port
    srv.stop()
    daemon.stop()
    new = None
    try:
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
        tip0 = list(live_view.facts["tip"])
        gid = d2.send_trajectory(
            [{"time_from_start": 1.5, "segments": {"segment_1": {"kappa": 1.5, "phi": 0.0}}}]
        )
        assert wait_for(lambda: d2.trajectory_status(gid)["done"], 30)
        assert wait_for(lambda: abs(source.snap.state["segment_1"]["kappa"] - 1.5) < 0.1, 20), (
            source.snap.state
        )
        assert wait_for(lambda: live_view.facts["tip"] != tip0, 10)
        page.get_by_text("segment_1: ok").wait_for(timeout=10000)
    finally:
        if new is not None:
            new[1].stop()
            new[0].stop()
