"""From a real browser (headless Debian Chromium driven by Playwright): a page on another origin
cannot talk to the API; the configured origin can (issue 13, finding 2)."""

from __future__ import annotations

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from host.api.server import ApiServer

pytestmark = pytest.mark.timeout(120)

from test_api_protocol import FacadeStub  # noqa: E402 - the in-memory facade

PAGE = """<!doctype html><meta charset="utf-8"><title>page</title><script>
window.result = undefined;
const ws = new WebSocket("%(url)s");
ws.onopen = () => ws.send(JSON.stringify({id: 1, op: "trajectory.send", points: [
  {time_from_start: 0.2, segments: {s1: {kappa: 1.0}}}]}));
ws.onmessage = (e) => { const m = JSON.parse(e.data); if (m.id === 1) window.result = m; };
ws.onerror = () => { if (window.result === undefined) window.result = "refused"; };
ws.onclose = () => { if (window.result === undefined) window.result = "refused"; };
</script>"""


def _page_server(page: dict[str, bytes]) -> ThreadingHTTPServer:
    """An HTTP server on a port of its own (its own origin) serving ``page["body"]``."""

    class Page(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            body = page["body"]
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    srv = ThreadingHTTPServer(("127.0.0.1", 0), Page)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    return srv


def _visit(browser, url: str):
    page = browser.new_page()
    try:
        page.goto(url)
        page.wait_for_function("window.result !== undefined", timeout=20000)
        return page.evaluate("window.result")
    finally:
        page.close()


def test_only_the_configured_origin_can_command_the_robot_from_a_browser(browser):
    stub = FacadeStub()
    page: dict[str, bytes] = {"body": b""}
    allowed_page, other_page = _page_server(page), _page_server(page)
    allowed_origin = f"http://127.0.0.1:{allowed_page.server_port}"
    api = ApiServer(stub, "127.0.0.1", 0, origins=(allowed_origin,)).start()
    page["body"] = (PAGE % {"url": api.url}).encode()  # both pages talk to the API
    try:
        # another site the user happens to visit: no connection, nothing sent
        for url in (
            f"http://127.0.0.1:{other_page.server_port}/",
            f"http://localhost:{allowed_page.server_port}/",  # same port, other origin
        ):
            assert _visit(browser, url) == "refused", url
        assert stub.goals == {}
        assert api.stats()["refused_handshakes"] >= 2

        # the configured origin (e.g. the project's live view) works
        result = _visit(browser, f"{allowed_origin}/")
        assert result["ok"] is True and result["result"]["goal"] == "g1", result
        assert list(stub.goals) == ["g1"]
    finally:
        api.stop()
        allowed_page.shutdown()
        other_page.shutdown()
        stub.close()
