"""From a real browser (headless Debian Chromium driven by Playwright): a page loaded from a local
file, as Lichtblick / Foxglove desktop load theirs, connects to `ucr foxglove` the way their
worker does (``new WebSocket(url, ["foxglove.websocket.v1"])``) once its origin is allowed
(docs/recording.md, desktop viewers), and is refused by default."""

from __future__ import annotations

import json
import re

import pytest

from host.api.server import ApiServer

from .conftest import ucr, wait_for
from .stub_daemon import ROBOT_FILE, StubDaemon

pytestmark = pytest.mark.timeout(180)

pytest.importorskip("mcap_ros2", reason="the 'record' extra (mcap-ros2-support) is not installed")

TOKEN = "desktop-viewer-token-0123"
PAGE = """<!doctype html><meta charset="utf-8"><title>desktop</title><script>
window.result = undefined;
const ws = new WebSocket(%s, ["foxglove.websocket.v1"]);
ws.onmessage = (e) => {
  const m = JSON.parse(e.data);
  if (window.result === undefined) window.result = m.op + " " + ws.protocol;
};
ws.onerror = () => { if (window.result === undefined) window.result = "refused"; };
ws.onclose = () => { if (window.result === undefined) window.result = "refused"; };
</script>"""


@pytest.fixture
def daemon_url():
    stub = StubDaemon()
    api = ApiServer(stub, "127.0.0.1", 0).start()
    try:
        yield api.url
    finally:
        api.stop()
        stub.close()


def _foxglove(url: str, *options: str):
    """`ucr foxglove` on a free port; (process, its ws:// URL)."""
    proc = ucr("foxglove", "--port", "0", "--url", url, "--robot", str(ROBOT_FILE), *options)
    lines: list[str] = []

    def served() -> bool:
        line = proc.stderr.readline()
        lines.append(line)
        return "Foxglove WebSocket server on" in line or not line

    assert wait_for(served, 60), lines
    m = re.search(r"(ws://\S+)", lines[-1])
    assert m, lines
    return proc, m.group(1)


def _visit(browser, tmp_path, ws_url: str) -> str:
    page_file = tmp_path / "viewer.html"
    page_file.write_text(PAGE % json.dumps(ws_url))
    page = browser.new_page()
    try:
        page.goto(page_file.as_uri())  # file:///tmp/...: the page's origin is a local file's
        page.wait_for_function("window.result !== undefined", timeout=30000)
        return page.evaluate("window.result")
    finally:
        page.close()


def _stop(proc) -> None:
    proc.terminate()
    try:
        proc.wait(15)
    except Exception:  # noqa: BLE001
        proc.kill()
        proc.wait(5)


def test_a_local_file_page_reaches_ucr_foxglove_only_when_its_origin_is_allowed(
    browser, daemon_url, tmp_path, monkeypatch
):
    monkeypatch.delenv("UCR_FOXGLOVE_TOKEN", raising=False)
    token_file = tmp_path / "fox.token"
    token_file.write_text(TOKEN + "\n")
    token_file.chmod(0o600)
    proc, ws_url = _foxglove(daemon_url)
    try:
        assert _visit(browser, tmp_path, ws_url) == "refused"  # default: no page from a file
    finally:
        _stop(proc)
    # Chromium's opaque origin "null" for a file:// page: allowed with a token (in the URL,
    # as a desktop viewer that cannot set headers gives it); Electron's "file://" as well
    proc, ws_url = _foxglove(daemon_url, "--allow-origin", "null", "--allow-origin",
                             "file://", "--serve-token-file", str(token_file))  # fmt: skip
    try:
        assert _visit(browser, tmp_path, ws_url) == "refused"  # still the token
        assert _visit(browser, tmp_path, f"{ws_url}/?token={TOKEN}") == (
            "serverInfo foxglove.websocket.v1"
        )
    finally:
        _stop(proc)
