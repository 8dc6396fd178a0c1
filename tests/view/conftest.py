"""Fixtures for the view tests: an emulated chain with a daemon and its API, the view process's
app on it, and headless Chromium (Debian's /usr/bin/chromium) driven by Playwright."""

from __future__ import annotations

import pytest
from view_helpers import ROBOT


@pytest.fixture(scope="session")
def browser(browser):
    """The suite's headless Chromium (tests/conftest.py), for pages of the view extra (viser)."""
    pytest.importorskip("viser", reason="the view extra (viser) is not installed")
    return browser


@pytest.fixture(scope="module")
def rig():
    """(chain, daemon, api server) on an emulated softrobot3 chain (real firmware, MicroPython)."""
    from tools.rig import EmulatedRig

    with EmulatedRig(ROBOT, boot_timeout_s=20) as r:
        yield r.chain, r.daemon, r.srv


@pytest.fixture(scope="module")
def live_view(rig, browser):
    """The view app (as `ucr view` runs it) connected to the rig's API, sending 10 scene
    updates/s: less of the 2 shared cores for the view and the page than its default 40/s. (Not
    a cure for a page that shows an old state: a headless Chromium with software WebGL on a
    crowded machine draws nothing for seconds at times, at 10/s as at 40/s, docs/view.md "A page
    on an overloaded machine"; a test waits for a line on the page 30-60 s.)"""
    from view.app import ViewApp
    from view.source import LiveSource

    _, _, srv = rig
    app = ViewApp(LiveSource(srv.url, None).start(), port=0, rate_hz=10.0).start()
    yield app
    app.stop()


@pytest.fixture
def page(browser, live_view):
    ctx = browser.new_context(viewport={"width": 1000, "height": 700})
    pg = ctx.new_page()
    pg.goto(live_view.url)
    yield pg
    ctx.close()
