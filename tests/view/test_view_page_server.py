"""The page server's own limits (security review items 6 and 10).

Item 6: a view off loopback (view only) is open to unauthenticated clients, and non-browser
clients send no Origin: a page message is at most MAX_FRAME_BYTES (viser asked for 50 MiB: a
dozen clients each sending 49 MiB grew the view by 640 MiB) and page WebSockets without the page
token are capped (MAX_CONNECTIONS in total, MAX_PER_ADDRESS from one remote address).

Item 10: off loopback the view refused its own page's WebSocket (allowed origins were built from
loopback names and the bind address only); the page's own origin, the Host it was served under,
is allowed now, a foreign one is not."""

from __future__ import annotations

import asyncio
import base64
import os
import socket

import pytest

pytest.importorskip("viser", reason="the view extra (viser) is not installed")

from view_helpers import ROBOT, wait_for  # noqa: E402

from tests.raw_http import read_head

pytestmark = pytest.mark.timeout(180)


@pytest.fixture
def offline_app():
    from view.app import ViewApp
    from view.source import OfflineSource

    app = ViewApp(OfflineSource(ROBOT).start(), port=0).start()
    yield app
    app.stop()


def _ws(port: int, **kw):
    import viser
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{port}/", subprotocols=[f"viser-v{viser.__version__}"],
                   max_size=None, open_timeout=20, **kw)  # fmt: skip


def _close_code(ws, timeout: float = 20.0) -> int | None:
    """Read until the view closes the connection; its close code (None: still open)."""
    from websockets.exceptions import ConnectionClosed

    try:
        while True:
            ws.recv(timeout=timeout)
    except ConnectionClosed as exc:
        return exc.rcvd.code if exc.rcvd is not None else None
    except TimeoutError:
        return None


def test_a_page_message_above_the_frame_limit_closes_that_connection(offline_app):
    """Defect: viser's 50 MiB limit was left; the view read (and kept) each message whole."""
    for size in (1024 * 1024, 64 * 1024 + 1):  # the page's own messages are a few hundred bytes
        ws = _ws(offline_app.port)
        try:
            ws.send(b"\x00" * size)
            assert _close_code(ws) == 1009, size  # message too big, its payload never read
        finally:
            ws.close()
    ws = _ws(offline_app.port)  # the view serves on
    ws.close()
    from view.guard import MAX_FRAME_BYTES

    assert MAX_FRAME_BYTES <= 64 * 1024


def test_page_connections_without_the_token_are_capped(offline_app):
    """Defect: no cap: every unauthenticated client got a connection (and its buffers)."""
    from websockets.exceptions import InvalidStatus

    conns: list = []
    try:
        with pytest.raises(InvalidStatus) as exc:
            while len(conns) < 64:
                conns.append(_ws(offline_app.port))
        assert exc.value.response.status_code == 503
        assert b"too many page connections" in exc.value.response.body
        from view.guard import MAX_CONNECTIONS

        assert len(conns) == MAX_CONNECTIONS
        conns.pop().close()  # one leaves: there is room again
        assert wait_for(lambda: offline_app.gate.open_without_token < MAX_CONNECTIONS, 10)
        conns.append(_ws(offline_app.port))
    finally:
        for c in conns:
            c.close()


class _Conn:
    """A connection as PageGate sees it: its peer, closing, answering."""

    def __init__(self, ip: str):
        self.remote_address = (ip, 40000)
        self.closed = asyncio.Event()

    async def wait_closed(self) -> None:
        await self.closed.wait()

    def respond(self, status, text: str):
        return int(status), text


class _Request:
    def __init__(self, path: str = "/"):
        from websockets.datastructures import Headers

        self.path = path
        self.headers = Headers({"Upgrade": "websocket", "Host": "192.0.2.2:8080"})


def test_the_cap_per_remote_address_and_the_operators_page():
    """MAX_PER_ADDRESS from one remote address (loopback peers count only in the total); a page
    presenting the page token is admitted whatever the crowd."""
    from view.guard import MAX_CONNECTIONS, MAX_PER_ADDRESS, PageGate, PageToken

    async def run() -> None:
        token = PageToken()
        token.port = 8080
        gate = PageGate(token)
        said: list[str] = []
        remote = [_Conn("192.0.2.9") for _ in range(MAX_PER_ADDRESS)]
        assert [gate.admit(c, _Request(), said.append) for c in remote] == [None] * len(remote)
        status, why = gate.admit(_Conn("192.0.2.9"), _Request(), said.append)
        assert status == 503 and "from 192.0.2.9" in why and said
        assert gate.admit(_Conn("192.0.2.10"), _Request(), said.append) is None  # another host
        local = MAX_CONNECTIONS - MAX_PER_ADDRESS - 1
        assert all(gate.admit(_Conn("127.0.0.1"), _Request(), said.append) is None
                   for _ in range(local))  # fmt: skip
        assert gate.admit(_Conn("127.0.0.1"), _Request(), said.append)[0] == 503  # the total
        operator = _Request(f"/t/{token.secret}")
        assert gate.admit(_Conn("127.0.0.1"), operator, said.append) is None
        wrong = _Request(f"/t/{token.secret[:-1]}x")
        assert gate.admit(_Conn("127.0.0.1"), wrong, said.append)[0] == 503
        remote[0].closed.set()  # one leaves
        await asyncio.sleep(0.05)
        assert gate.admit(_Conn("192.0.2.9"), _Request(), said.append) is None

    _run_apart(run)


def _run_apart(coro_fn) -> None:
    """asyncio.run in a thread of its own (Playwright's sync API keeps a loop running here)."""
    import threading

    failed: list[BaseException] = []

    def main() -> None:
        try:
            asyncio.run(coro_fn())
        except BaseException as exc:  # noqa: BLE001 - re-raised in the test's thread
            failed.append(exc)

    t = threading.Thread(target=main)
    t.start()
    t.join(60)
    assert not t.is_alive()
    if failed:
        raise failed[0]


def _handshake(port: int, *headers: str) -> str:
    """Status line of a raw WebSocket handshake with these headers (as the review's hs.py)."""
    import viser

    key = base64.b64encode(os.urandom(16)).decode()
    lines = ["GET / HTTP/1.1", "Upgrade: websocket", "Connection: Upgrade",
             f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
             f"Sec-WebSocket-Protocol: viser-v{viser.__version__}", *headers]  # fmt: skip
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"))
        data = read_head(s)
    return data.split(b"\r\n", 1)[0].decode("latin-1")


@pytest.fixture
def all_interfaces():
    """The view served on every interface (`ucr view --host 0.0.0.0`), on the file."""
    from view.app import ViewApp
    from view.source import OfflineSource

    app = ViewApp(OfflineSource(ROBOT).start(), host="0.0.0.0", port=0).start()
    yield app
    app.stop()


def test_off_loopback_the_page_may_open_its_websocket_from_its_own_origin(all_interfaces):
    """Defect: the page served under Host 192.0.2.2:P got 200 but its WebSocket (Origin
    http://192.0.2.2:P) 403. Its own origin is allowed now; other origins are not."""
    p = all_interfaces.port
    own = _handshake(p, f"Host: 192.0.2.2:{p}", f"Origin: http://192.0.2.2:{p}")
    assert own.split()[1] == "101", own
    for host, origin in [
        (f"192.0.2.2:{p}", f"http://192.0.2.3:{p}"),  # another machine's page
        (f"192.0.2.2:{p}", f"http://192.0.2.2:{p + 1}"),  # another port there
        (f"127.0.0.1:{p}", f"http://192.0.2.2:{p}"),  # a page elsewhere opening this one
        (f"evil.example:{p}", f"http://evil.example:{p}"),  # DNS rebinding: Host refused
        ("192.0.2.2", "http://192.0.2.2"),  # port 80, not this server's
        (f"192.0.2.2:{p}", "null"),
    ]:
        status = _handshake(p, f"Host: {host}", f"Origin: {origin}")
        assert status.split()[1] == "403", (host, origin, status)


def test_off_loopback_the_page_works_in_a_browser_under_another_address(all_interfaces, browser):
    """The page opened at http://127.0.0.2:P (an address other than those the old guard listed)
    connects and shows the robot."""
    ctx = browser.new_context(viewport={"width": 900, "height": 650})
    try:
        page = ctx.new_page()
        page.goto(f"http://127.0.0.2:{all_interfaces.port}/")
        page.get_by_text("tubes: 3").wait_for(timeout=60000)
    finally:
        ctx.close()


def test_a_page_client_cannot_open_visers_share_tunnel(offline_app, monkeypatch, caplog):
    """viser lets any page client ask for a public share URL (a tunnel from share.viser.studio to
    this page; its stock page has a Share button): the view refuses and hides the button."""
    import viser._viser as viser_server
    from view_helpers import RawPage

    made: list = []
    monkeypatch.setattr(viser_server, "ViserTunnel", lambda *a, **kw: made.append(a))
    caplog.set_level("WARNING", logger="ucr.view")
    raw = RawPage(offline_app.port)
    try:
        raw.send({"type": "ShareUrlRequest"})

        def handled() -> bool:
            return bool(made) or "public share URL" in caplog.text

        assert wait_for(handled, 20)
        assert made == []
        assert "refused a page's request for a public share URL" in caplog.text
        assert raw.read_until(lambda m: m.get("type") == "ThemeConfigurationMessage", 20)
        theme = [m for m in raw.seen if m.get("type") == "ThemeConfigurationMessage"]
        assert theme[-1]["show_share_button"] is False
    finally:
        raw.close()


def test_the_token_in_the_url_is_exchanged_for_a_path_on_the_page_itself():
    """?token= right: a redirect to the page under the token's path (on this server: never a
    //other-site path), no cookie (a cookie reaches every port of the host); wrong: a redirect
    to the plain page (view only), logged. Under the path, viser is asked for the page itself;
    a wrong secret there is 404."""
    from websockets.datastructures import Headers
    from websockets.http11 import Response

    from view.guard import PageGate, PageToken

    class Conn:
        remote_address = ("127.0.0.1", 40001)

        def respond(self, status, text):
            return Response(int(status), "", Headers(), text.encode())

    class Get:
        def __init__(self, path: str):
            self.path, self.headers = path, Headers({"Host": "127.0.0.1:8080"})

    token = PageToken()
    gate = PageGate(token)
    token.port = 8080
    said: list[str] = []
    assert gate.admit(Conn(), Get("/"), said.append) is None  # the page itself: viser serves it
    ok = gate.admit(Conn(), Get(f"//evil.example/?darkMode&token={token.secret}"), said.append)
    assert ok.status_code == 302 and ok.headers["Location"] == f"/t/{token.secret}/?darkMode="
    assert "Set-Cookie" not in ok.headers and ok.headers["Referrer-Policy"] == "no-referrer"
    assert said == []
    bad = gate.admit(Conn(), Get("/?token=guess"), said.append)
    assert bad.status_code == 302 and bad.headers["Location"] == "/"
    assert "Set-Cookie" not in bad.headers
    assert said == ["a page request from 127.0.0.1:40001 had a wrong token: view only"]
    assert gate.admit(Conn(), Get(f"/t/{token.secret}/?darkMode"), said.append) == "/?darkMode"
    assert gate.admit(Conn(), Get(f"/t/{token.secret}"), said.append).status_code == 302
    assert gate.admit(Conn(), Get("/t/guess/"), said.append).status_code == 404
    assert said[-1] == "a page request from 127.0.0.1:40001 had a wrong token path: 404"
    # (review) on the page with controls, a stale or wrong ?token= does not take them away
    stale = gate.admit(Conn(), Get(f"/t/{token.secret}/?token=old&darkMode"), said.append)
    assert stale == "/?darkMode="
    assert token.presented(Get(f"/t/{token.secret}"))
    assert token.presented(Get(f"/t/{token.secret}/"))
    assert not token.presented(Get(f"/t/{token.secret}/x")) and not token.presented(Get("/"))
