"""The Foxglove server's door (interop/guard.py): browser origins, non-loopback Host headers and
missing tokens are refused at the handshake; accepted clients get the Foxglove protocol."""

from __future__ import annotations

import json
import socket

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

pytest.importorskip("foxglove", reason="the 'record' extra (foxglove-sdk) is not installed")

from interop.foxglove import FoxgloveSink  # noqa: E402
from interop.guard import GuardError  # noqa: E402
from interop.topics import Message  # noqa: E402

PROTO = ["foxglove.sdk.v1"]
TOKEN = "s3cret-token-42-foxglove"  # the API's rule: 16+ characters


@pytest.fixture
def sink_factory():
    made = []

    def make(**kw):
        sink = FoxgloveSink(port=0, **{"host": "127.0.0.1", **kw})
        from interop.sinks import Fanout

        Fanout([sink]).publish(Message("/ucr/events", "std_msgs/msg/String", {"data": "x"}, 1))
        made.append(sink)
        return sink

    yield make
    for s in made:
        s.close()


def _hello(url: str, **kw) -> dict:
    """Connect, return the first advertise message."""
    with connect(url, subprotocols=PROTO, open_timeout=10, **kw) as ws:
        for _ in range(10):
            msg = json.loads(ws.recv(timeout=10))
            if msg.get("op") == "advertise":
                return msg
    raise AssertionError("no advertise")


def _status(exc: pytest.ExceptionInfo) -> int:
    return exc.value.response.status_code


def test_client_without_origin_gets_the_protocol(sink_factory):
    sink = sink_factory()
    adv = _hello(sink.url)
    assert [c["topic"] for c in adv["channels"]] == ["/ucr/events"]
    assert adv["channels"][0]["schemaName"] == "std_msgs/msg/String"


def test_browser_origin_is_refused_unless_allowed(sink_factory):
    sink = sink_factory()
    with pytest.raises(InvalidStatus) as exc:
        _hello(sink.url, origin="https://evil.example")
    assert _status(exc) == 403
    allowed = sink_factory(allowed_origins=["https://app.foxglove.dev"])
    assert _hello(allowed.url, origin="https://app.foxglove.dev")["channels"]


def test_non_loopback_host_header_is_refused_on_loopback(sink_factory):
    """A DNS-rebinding page reaches 127.0.0.1 under a foreign name: its Host header gives it
    away."""
    sink = sink_factory()
    with socket.create_connection(("127.0.0.1", sink.port), timeout=10) as s:
        s.sendall(
            b"GET / HTTP/1.1\r\nHost: rebind.example:80\r\nUpgrade: websocket\r\n"
            b"Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            b"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
        )
        assert s.recv(100).startswith(b"HTTP/1.1 421")  # host.api.guard: not a name of ours


def test_token_is_required_when_set_as_header_or_query(sink_factory):
    sink = sink_factory(token=TOKEN)
    with pytest.raises(InvalidStatus) as exc:
        _hello(sink.url)
    assert _status(exc) == 401
    with pytest.raises(InvalidStatus) as exc:
        _hello(sink.url, additional_headers={"Authorization": "Bearer wrong-token-00"})
    assert _status(exc) == 401
    assert _hello(sink.url, additional_headers={"Authorization": f"Bearer {TOKEN}"})["channels"]
    assert _hello(f"{sink.url}/?token={TOKEN}")["channels"]


def test_non_loopback_address_needs_a_token_and_tls_or_insecure(sink_factory):
    with pytest.raises(GuardError, match="without a token"):
        sink_factory(host="0.0.0.0")
    with pytest.raises(GuardError, match="at least 16 characters"):
        sink_factory(host="0.0.0.0", token="short")
    with pytest.raises(GuardError, match="without TLS.*--insecure"):
        sink_factory(host="0.0.0.0", token=TOKEN)
    sink = sink_factory(host="0.0.0.0", token=TOKEN, insecure=True)
    url = f"ws://127.0.0.1:{sink.port}"
    with pytest.raises(InvalidStatus):
        _hello(url)
    assert _hello(url, additional_headers={"Authorization": f"Bearer {TOKEN}"})["channels"]


def test_a_token_on_the_command_line_is_refused(tmp_path):
    """Like every ucr command: a token in argv is visible in /proc; a 0600 file is the way."""
    import argparse
    import os

    from interop.foxglove import sink_from_args

    args = argparse.Namespace(serve_token=TOKEN, serve_token_file=None, allow_origin=[])
    with pytest.raises(GuardError, match="--serve-token-file"):
        sink_from_args("127.0.0.1", 0, args)
    f = tmp_path / "tok"
    f.write_text(TOKEN + "\n")
    os.chmod(f, 0o644)
    args = argparse.Namespace(serve_token=None, serve_token_file=str(f), allow_origin=[])
    with pytest.raises(GuardError, match="chmod 600"):
        sink_from_args("127.0.0.1", 0, args)
    os.chmod(f, 0o600)
    sink = sink_from_args("127.0.0.1", 0, args)
    try:
        with pytest.raises(InvalidStatus):
            _hello(sink.url)
    finally:
        sink.close()
