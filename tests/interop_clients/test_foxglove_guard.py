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


def _subscribe_all(ws, sub_base: int = 100) -> dict[int, str]:
    """Read up to the advertise message, subscribe to every channel; {subscription id: topic}."""
    for _ in range(10):
        msg = json.loads(ws.recv(timeout=10))
        if msg.get("op") == "advertise":
            subs = {sub_base + c["id"]: (c["id"], c["topic"]) for c in msg["channels"]}
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": sid, "channelId": cid} for sid, (cid, _) in subs.items()]}))  # fmt: skip
            return {sid: topic for sid, (_, topic) in subs.items()}
    raise AssertionError("no advertise")


def _received(ws, subs: dict[int, str], seconds: float, sink=None) -> list[tuple[str, int]]:
    """(topic, log time) of every message data frame within ``seconds`` (ticking ``sink`` as a
    live feed or a replay does)."""
    import struct
    import time

    from websockets.exceptions import ConnectionClosed

    got = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if sink is not None:
            sink.tick()
        try:
            m = ws.recv(timeout=0.05)
        except TimeoutError:
            continue
        except ConnectionClosed:
            break
        if isinstance(m, bytes) and m[0] == 1:
            sid, t_ns = struct.unpack_from("<IQ", m, 1)
            got.append((subs[sid], t_ns))
    return got


def test_a_client_leaving_is_clean(sink_factory, caplog):
    """Defect (with foxglove-sdk's server, before the door spoke the protocol itself): a client
    leaving logged "Callback failed: AttributeError ... 'on_unsubscribe'" once per channel.
    A client that subscribed and left still leaves no error or exception in the log."""
    import logging
    import time

    caplog.set_level(logging.DEBUG)
    sink = sink_factory()
    with connect(sink.url, subprotocols=PROTO, open_timeout=10) as ws:
        subs = _subscribe_all(ws)
        assert _received(ws, subs, 0.5) is not None
    time.sleep(0.5)  # the server sees the close and unsubscribes
    sink.close()
    failed = [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert failed == []


def test_latched_topics_go_to_the_new_subscriber_only(sink_factory):
    """Defect: a new subscriber made every connected client get the latched topics again (with
    their old log time: the first client's stream stepped back)."""
    from interop.sinks import Fanout

    sink = sink_factory()
    out = Fanout([sink])
    out.publish(Message("/robot_description", "std_msgs/msg/String", {"data": "<robot/>"}, 5))
    with connect(sink.url, subprotocols=PROTO, open_timeout=10) as a:
        subs_a = _subscribe_all(a)
        got_a = _received(a, subs_a, 1.0, sink)
        assert got_a == [("/robot_description", 5)]  # latched: sent on subscribing
        out.publish(Message("/ucr/events", "std_msgs/msg/String", {"data": "y"}, 10))
        with connect(sink.url, subprotocols=PROTO, open_timeout=10) as b:
            subs_b = _subscribe_all(b, sub_base=500)
            got_b = _received(b, subs_b, 1.0, sink)
            got_a = _received(a, subs_a, 0.5, sink)
        assert ("/robot_description", 5) in got_b and len(got_b) == 1, got_b
        assert got_a == [("/ucr/events", 10)], got_a  # nothing latched again, no step back


_UPGRADE = (
    "GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
)


@pytest.mark.parametrize(
    "request_text",
    [
        "GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUser-Agent: curl/8\r\nAccept: */*\r\n\r\n",
        _UPGRADE + "Sec-WebSocket-Protocol: bogus\r\n\r\n",
        _UPGRADE + "Sec-WebSocket-Protocol: \r\n\r\n",
        "hello, this is not HTTP\r\n\r\n",
    ],
    ids=["curl", "bogus-subprotocol", "empty-subprotocol", "not-http"],
)
def test_a_malformed_handshake_is_one_line_not_a_traceback(sink_factory, request_text):
    """Defect: websockets refused these itself and logged a full traceback (InvalidUpgrade,
    NegotiationError) on the server's terminal."""
    import subprocess
    import sys

    from .conftest import REPO

    script = (
        "import socket, sys, time\n"
        "from interop.foxglove import FoxgloveSink\n"
        "s = FoxgloveSink(port=0)\n"
        "c = socket.create_connection(('127.0.0.1', s.port), timeout=10)\n"
        f"c.sendall({request_text!r}.format(port=s.port).encode())\n"
        "print(c.recv(200).split(b'\\r\\n')[0].decode(), flush=True)\n"
        "c.close(); time.sleep(0.3); s.close()\n"
    )
    res = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True,
                         text=True, timeout=120)  # fmt: skip
    assert res.returncode == 0, res.stderr
    if request_text.startswith("GET"):  # not HTTP: the connection is just closed
        assert res.stdout.startswith("HTTP/1.1 4"), res.stdout
    lines = res.stderr.strip().splitlines()
    assert "Traceback" not in res.stderr, res.stderr
    assert len(lines) == 1 and lines[0].startswith("Foxglove: refused ('127.0.0.1', "), lines
