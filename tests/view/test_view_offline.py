"""Offline `ucr view FILE`: sliders drive FK only, the file reloads on save and its check errors
(path:line) show on the page; and the page's web server refuses foreign Hosts and Origins."""

from __future__ import annotations

import shutil
import time
import urllib.error
import urllib.request

import pytest
from view_helpers import ROBOT, wait_for

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def offline(tmp_path, browser):
    from view.app import ViewApp
    from view.source import OfflineSource

    path = tmp_path / "robot.ucrdf"
    shutil.copy(ROBOT, path)
    app = ViewApp(OfflineSource(path, poll_s=0.1).start(), port=0).start()
    yield app, path
    app.stop()


def test_offline_slider_drives_fk_and_a_broken_save_shows_its_check_error(offline, browser):
    app, path = offline
    ctx = browser.new_context(viewport={"width": 900, "height": 650})
    page = ctx.new_page()
    try:
        page.goto(app.url)
        page.get_by_text("tubes: 3").wait_for(timeout=60000)
        tip0 = list(app.facts["tip"])
        box = page.locator("input[inputmode='decimal']").nth(0)
        box.fill("2")
        box.press("Enter")
        assert wait_for(lambda: app.facts.get("tip") != tip0, 10)
        assert app.source.snap.state["segment_1"]["kappa"] == pytest.approx(2.0)
        # break the file: kappa_max beyond pi/length is a semantic error on a known line
        text = path.read_text()
        broken = text.replace('kappa_max="3.313916301255056"', 'kappa_max="-1"', 1)
        assert broken != text, "the fixture robot changed: update this test"
        line = text[: text.index('kappa_max="3.313916301255056"')].count("\n") + 1
        path.write_text(broken)
        page.get_by_text(f"{path}:{line}:").wait_for(timeout=20000)
        page.get_by_text("check errors").wait_for(timeout=5000)
        # the last good robot stays drawn; fixing the file clears the error
        assert app.facts["tubes"] == ["segment_1", "segment_2", "segment_3"]
        path.write_text(text)
        assert wait_for(lambda: not app.source.snap.errors, 10)
        # (a page on a crowded machine can go seconds without updating its DOM: docs/view.md
        # "A page on an overloaded machine"; 10 s was not always enough in CI)
        page.get_by_text("check errors").wait_for(state="detached", timeout=30000)
    finally:
        ctx.close()


def _get(url: str, **headers: str) -> int:
    req = urllib.request.Request(url, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status
    except urllib.error.HTTPError as exc:
        return exc.code


def test_page_server_refuses_foreign_host_and_origin(offline):
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    app, _ = offline
    port = app.port
    assert _get(app.url) == 200
    assert _get(app.url, Host=f"localhost:{port}") == 200
    # DNS rebinding: a foreign name resolving to 127.0.0.1
    assert _get(app.url, Host=f"evil.example:{port}") == 403
    # cross-site WebSocket hijacking: a page of another site opening the view's socket
    ws = app.url.replace("http", "ws")
    with pytest.raises(InvalidStatus) as exc:
        connect(ws, origin="http://evil.example", subprotocols=["viser-v1.1.1"])
    assert exc.value.response.status_code == 403
    with pytest.raises(InvalidStatus):
        connect(ws, origin=f"http://127.0.0.1:{port + 1}", subprotocols=["viser-v1.1.1"])
    c = connect(ws, origin=f"http://127.0.0.1:{port}", subprotocols=["viser-v1.1.1"])
    c.close()
    time.sleep(0.1)
