"""The live view's page moves hardware, so its controls need a credential (security review item 4):
the view prints a URL with a secret made at each start (``?token=…``, as Jupyter does); the page
opened from it is redirected to a path holding it (``/t/<secret>/``), its WebSocket presents it
in its own path and the page has controls (never a cookie: a browser sends cookies to every port
of the host). Any other page client (a
browser tab on the plain URL, a local process speaking viser's protocol) gets the scene and a line
saying why it has no controls, and cannot move the robot. Every motion command from a page is in
the view's audit log with that page client's id and address."""

from __future__ import annotations

import logging
import re
import time

import pytest
from view_helpers import RawPage, page_controls, wait_for

pytestmark = pytest.mark.timeout(240)


class _Audit(logging.Handler):
    """Collects the lines of the ``ucr.audit`` logger (it does not propagate)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def __enter__(self) -> _Audit:
        from host.api.audit import audit_logger

        audit_logger().addHandler(self)
        return self

    def __exit__(self, *exc) -> None:
        from host.api.audit import audit_logger

        audit_logger().removeHandler(self)


def _settle(daemon, view) -> None:
    view.stop_motion("test cleanup")
    if daemon.status()["manual_control"]:
        daemon.hand_back("ffc")


def test_a_page_without_the_token_is_view_only_and_cannot_move_the_robot(rig, live_view, browser):
    """Defect: any local process (no token) set the 'segment_1 κ' slider through viser's protocol
    and the view bent segment_1 with its control token; a tab on the plain URL had every control."""
    _, daemon, _ = rig
    with _Audit() as audit:
        # a local process speaking viser's protocol, as in the review's view_control.py
        raw = RawPage(live_view.port)
        try:

            def note_or_slider(m: dict) -> bool:
                note = "view only:" in str(m.get("props", {}).get("_markdown", ""))
                return note or m.get("type") == "GuiSliderMessage"

            assert raw.read_until(note_or_slider, 30), raw.seen[-5:]
            assert raw.labels("GuiSliderMessage") == []
            assert raw.labels("GuiButtonMessage") == []
            # a browser tab on the page without the token: the scene, no controls, and why
            ctx = browser.new_context(viewport={"width": 1000, "height": 700})
            try:
                pg = ctx.new_page()
                pg.goto(live_view.page_url)
                pg.get_by_text("tubes: 3").wait_for(timeout=60000)
                pg.get_by_text("view only:").wait_for(timeout=20000)
                assert pg.locator("input[inputmode='decimal'], input[type='number']").count() == 0
                for name in ("Stop (hold)", "Execute move", "Hand back control"):
                    assert pg.get_by_role("button", name=name).count() == 0, name
                # the URL with the token, in the same tab: now it has controls
                assert "?token=" in live_view.url and live_view.url.startswith(pg.url)
                pg.goto(live_view.url)
                pg.get_by_text("tubes: 3").wait_for(timeout=60000)
                pg.get_by_role("button", name="Stop (hold)").wait_for(timeout=20000)
                # even knowing the uuid of that page's slider, the raw client's update is not
                # taken: viser hands a page's own controls only that page's messages
                slider = page_controls(live_view).sliders["segment_1"][0]
                frames = page_controls(live_view).toggles["frames"]
                shown = live_view.show["frames"]
                raw.send({"type": "GuiUpdateMessage", "uuid": slider._impl.uuid,
                          "updates": {"value": 2.0}})  # fmt: skip
                # nor a forged update of that page's display toggle (a viewer has none)
                raw.send({"type": "GuiUpdateMessage", "uuid": frames._impl.uuid,
                          "updates": {"value": not shown}})  # fmt: skip
                time.sleep(1.5)
                assert live_view.show["frames"] == shown
                assert live_view.driver.targets == {}
                assert float(slider.value) != 2.0
            finally:
                ctx.close()
        finally:
            raw.close()
    assert daemon.status()["manual_control"] == []
    assert not any("op=slider" in line for line in audit.lines), audit.lines
    assert any(re.search(r"page=\d+ peer=127\.0\.0\.1:\d+ op=connect without the page token", ln)
               for ln in audit.lines), audit.lines  # fmt: skip


def test_the_printed_url_gives_controls_and_each_page_command_is_audited(rig, live_view, browser):
    """The URL the view prints works: its token is exchanged for the page's path (no cookie), the
    page has controls, and a slider set there is audited with that page's id/peer."""
    _, daemon, _ = rig
    with _Audit() as audit:
        ctx = browser.new_context(viewport={"width": 1000, "height": 700})
        try:
            pg = ctx.new_page()
            pg.goto(live_view.url)
            pg.get_by_text("tubes: 3").wait_for(timeout=60000)
            assert "token=" not in pg.url, pg.url  # redirected to the page under its path
            assert pg.url.startswith(f"{live_view.page_url}t/{live_view.page_token.secret}/")
            assert ctx.cookies() == []
            pg.get_by_role("button", name="Stop (hold)").wait_for(timeout=20000)
            assert pg.get_by_text("view only:").count() == 0
            box = pg.locator("input[inputmode='decimal'], input[type='number']").nth(0)
            box.fill("1.2")  # segment_1 κ
            box.press("Enter")
            page = page_controls(live_view)
            want = f"view page={page.id} peer={page.peer} op=slider segment_1 κ 1.20 1/m φ 0°"
            assert wait_for(lambda: want in audit.lines, 20), audit.lines
            assert re.fullmatch(r"127\.0\.0\.1:\d+", page.peer)
            assert "segment_1" in live_view.driver.targets
            # ... and the daemon's own audit line for the input says which page it was for
            daemon_for = f"client='ucr view' for='view page={page.id} peer={page.peer}' op="
            inputs = [daemon_for + "ffc.input"]
            assert wait_for(lambda: any(inputs[0] in ln for ln in audit.lines), 20), audit.lines
            pg.get_by_role("button", name="Stop (hold)").click()
            stop = f"view page={page.id} peer={page.peer} op=stop stop button"
            assert wait_for(lambda: stop in audit.lines, 20), audit.lines
            assert live_view.driver.targets == {}
            # the stop's zero input too (the sticks deflected changed: audited)
            assert wait_for(lambda: sum(inputs[0] in ln for ln in audit.lines) >= 2, 20), (
                audit.lines
            )
        finally:
            ctx.close()
            _settle(daemon, live_view)


def test_the_page_secret_never_reaches_another_local_web_server(rig, live_view, browser):
    """Defect (audit 15.1): the secret was a cookie (``ucr_view_PORT``); cookies are not scoped by
    port, so the browser sent it to every other web server on 127.0.0.1. Now it travels only in
    the page's path: another port's server, reached from a tab of the same browser and by the
    view's own page (an image, a fetch with credentials), never receives it."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    seen: list[str] = []

    class Other(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            seen.append(f"{self.requestline}\n{self.headers}")
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(b"another local app")

        def log_message(self, *args) -> None:
            pass

    other = ThreadingHTTPServer(("127.0.0.1", 0), Other)
    threading.Thread(target=other.serve_forever, daemon=True).start()
    there = f"http://127.0.0.1:{other.server_port}"
    secret = live_view.page_token.secret
    ctx = browser.new_context(viewport={"width": 1000, "height": 700})
    try:
        pg = ctx.new_page()
        pg.goto(live_view.url)
        pg.get_by_role("button", name="Stop (hold)").wait_for(timeout=60000)  # the token works
        pg.evaluate("(u) => fetch(u, {credentials: 'include', mode: 'no-cors'})", f"{there}/f")
        pg.evaluate("(u) => { const i = new Image(); i.src = u; document.body.append(i); }",
                    f"{there}/img")  # fmt: skip
        tab = ctx.new_page()
        tab.goto(f"{there}/tab")
        assert wait_for(lambda: len(seen) >= 3, 20), seen
        assert not [s for s in seen if secret in s], seen
        # a reload keeps the controls (the path holds the token)
        pg.reload()
        pg.get_by_role("button", name="Stop (hold)").wait_for(timeout=60000)
        tab.goto(f"{there}/again")
        assert wait_for(lambda: len(seen) >= 4, 20), seen
        assert not [s for s in seen if secret in s], seen
    finally:
        ctx.close()
        other.shutdown()
        other.server_close()


def test_the_demo_prints_the_url_that_gives_controls(rig, browser):
    """`./run.sh demo` starts the view with view.launch and prints the URL it read from the view:
    that URL has the page token and gives controls; viser's own banner (a URL without the token)
    is not printed."""
    from view.launch import start_view_process

    _, _, srv = rig
    view = start_view_process(srv.url)
    try:
        assert re.fullmatch(r"http://127\.0\.0\.1:\d+/\?token=[\w-]{40,}", view.url), view.url
        ctx = browser.new_context(viewport={"width": 1000, "height": 700})
        try:
            pg = ctx.new_page()
            pg.goto(view.url)
            pg.get_by_text("tubes: 3").wait_for(timeout=60000)
            pg.get_by_role("button", name="Stop (hold)").wait_for(timeout=20000)
            boxes = pg.locator("input[inputmode='decimal'], input[type='number']")
            boxes.nth(5).wait_for(timeout=20000)  # (a loaded page draws its panel in parts)
            assert boxes.count() == 6
        finally:
            ctx.close()
    finally:
        view.stop()
    printed = [ln for ln in view.lines if "http" in ln]
    assert printed == [f"ucr view: {view.url}  (live; Ctrl-C to stop)"], view.lines
