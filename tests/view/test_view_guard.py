"""The view's Host/Origin guard wraps viser internals (the websockets server viser starts): it must
fail closed, never serve an unguarded page, if those internals change under it."""

from __future__ import annotations

import http.server
import socket
import threading
import types

import pytest

pytest.importorskip("viser", reason="the view extra (viser) is not installed")

from view_helpers import ROBOT  # noqa: E402


class _Proxy(types.SimpleNamespace):
    """A module stand-in: ``overrides`` first, everything else from ``real``."""

    def __init__(self, real, **overrides):
        super().__init__(**overrides)
        self._real = real

    def __getattr__(self, name):
        return getattr(self._real, name)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(1.0)
        return s.connect_ex(("127.0.0.1", port)) == 0


def test_view_refuses_to_serve_when_viser_bypasses_the_guarded_server(monkeypatch):
    """A viser that starts its web server some other way than websockets.asyncio.server.serve
    (simulated: its module sees the unwrapped function): GuardError, and nothing listens."""
    import viser.infra._infra as infra
    import websockets
    import websockets.asyncio
    import websockets.asyncio.server as wss

    from view.app import ViewApp
    from view.guard import GuardError
    from view.source import OfflineSource

    unwrapped = wss.serve
    server_mod = _Proxy(wss, serve=lambda *a, **kw: unwrapped(*a, **kw))
    monkeypatch.setattr(
        infra,
        "websockets",
        _Proxy(websockets, asyncio=_Proxy(websockets.asyncio, server=server_mod)),
    )
    port = _free_port()
    src = OfflineSource(ROBOT)
    with pytest.raises(GuardError, match="internals changed"):
        ViewApp(src, port=port)
    assert not _listening(port), "an unguarded page server was left running"


def test_probe_reports_a_server_that_lets_a_foreign_host_through():
    """The start-up probe: a page server answering a foreign Host with 200 is not guarded."""
    from view.guard import probe_refuses_foreign_host

    class Open(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server's name
            self.send_response(200)
            self.end_headers()

        def log_message(self, *args):
            pass

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Open)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        why = probe_refuses_foreign_host("127.0.0.1", srv.server_address[1])
    finally:
        srv.shutdown()
        srv.server_close()
    assert why is not None and "not 403" in why


def test_the_running_view_answers_the_probe_with_403():
    from view.app import ViewApp
    from view.guard import probe_refuses_foreign_host
    from view.source import OfflineSource

    app = ViewApp(OfflineSource(ROBOT), port=0).start()
    try:
        assert probe_refuses_foreign_host("127.0.0.1", app.port) is None
    finally:
        app.stop()


def test_viser_is_the_pinned_version_the_guard_was_written_for():
    import tomllib
    from pathlib import Path

    import viser

    pyproject = tomllib.loads((Path(ROBOT).parents[1] / "pyproject.toml").read_text())
    pins = pyproject["project"]["optional-dependencies"]["view"]
    assert f"viser=={viser.__version__}" in pins, (pins, viser.__version__)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
