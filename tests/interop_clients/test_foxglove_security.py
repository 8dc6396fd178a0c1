"""The Foxglove server's door (interop/guard.py) under attack: it is the only listener (nothing
behind it to bypass), it bounds client frames and connections, backs off failed tokens with the
API's code, and answers every client message per the Foxglove protocol without an exception."""

from __future__ import annotations

import base64
import itertools
import json
import logging
import os
import socket
import struct
import sys

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from websockets.exceptions import InvalidStatus, WebSocketException
from websockets.sync.client import connect

from interop.foxglove import FoxgloveSink
from interop.sinks import Fanout
from interop.topics import Message
from tests.raw_http import IdleFlood, read_head
from tests.tls_files import self_signed

PROTO = ["foxglove.sdk.v1"]
TOKEN = "s3cret-token-42-foxglove"


@pytest.fixture
def sink_factory():
    made = []

    def make(**kw):
        sink = FoxgloveSink(port=0, **{"host": "127.0.0.1", **kw})
        out = Fanout([sink])
        out.publish(Message("/ucr/events", "std_msgs/msg/String", {"data": "x"}, 1))
        out.publish(Message("/robot_description", "std_msgs/msg/String", {"data": "<r/>"}, 5))
        made.append(sink)
        return sink

    yield make
    for s in made:
        s.close()


def _channels(ws) -> dict[str, int]:
    """Read up to the advertise message: {topic: channel id}."""
    for _ in range(10):
        msg = ws.recv(timeout=10)
        if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
            return {c["topic"]: c["id"] for c in json.loads(msg)["channels"]}
    raise AssertionError("no advertise")


def _next_text(ws) -> dict:
    """The next text (JSON) message, skipping message data."""
    for _ in range(100):
        msg = ws.recv(timeout=10)
        if isinstance(msg, str):
            return json.loads(msg)
    raise AssertionError("no text message")


def _raw_upgrade(port: int, path: str = "/", headers: tuple[str, ...] = ()) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    key = base64.b64encode(os.urandom(16)).decode()
    lines = [f"GET {path} HTTP/1.1", "Upgrade: websocket", "Connection: Upgrade",
             f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13",
             "Sec-WebSocket-Protocol: foxglove.sdk.v1", *headers]  # fmt: skip
    s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
    return s


def _response_head(s: socket.socket) -> bytes:
    return read_head(s, b"\r\n\r\n")


# -- 3: the door is the only way in ------------------------------------------------------------
def _listening_ports() -> set[int]:
    """TCP ports this process listens on (Linux: /proc)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    ports = set()
    for table in ("/proc/self/net/tcp", "/proc/self/net/tcp6"):
        try:
            with open(table) as f:
                rows = f.read().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN, ours
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_the_door_is_the_only_listener_and_refuses_a_web_page(sink_factory):
    """Defect: foxglove-sdk's own server listened on a second loopback port with no token, Origin
    or Host check: a rebinding page (foreign Host, foreign Origin) got 101 there and read the
    robot. Now the door is the server: one listening port, and it refuses such a handshake."""
    before = _listening_ports()
    sink = sink_factory(token=TOKEN)
    opened = _listening_ports() - before
    for port in opened:  # every port the server opened, not only the one it announces
        with _raw_upgrade(
            port,
            f"/?token={TOKEN}",
            (f"Host: rebind.example:{port}", "Origin: http://evil.example"),
        ) as s:
            head = _response_head(s)
        assert not head.startswith(b"HTTP/1.1 101"), (port, sink.port, head[:40])
    assert opened == {sink.port}


# -- 5: limits -----------------------------------------------------------------------------------
def _read_frames_until_close(s: socket.socket) -> int | None:
    """Read the server's (unmasked) frames; the close code of its close frame, None if the
    connection ends without one."""
    buf = b""

    def need(n: int) -> bool:
        nonlocal buf
        while len(buf) < n:
            chunk = s.recv(65536)
            if not chunk:
                return False
            buf += chunk
        return True

    while need(2):
        opcode, n = buf[0] & 0x0F, buf[1] & 0x7F
        head = 2
        if n == 126:
            if not need(4):
                return None
            n, head = struct.unpack_from(">H", buf, 2)[0], 4
        elif n == 127:
            if not need(10):
                return None
            n, head = struct.unpack_from(">Q", buf, 2)[0], 10
        if not need(head + n):
            return None
        payload, buf = buf[head : head + n], buf[head + n :]
        if opcode == 0x8:
            return struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 1005
    return None


def test_a_frame_above_the_limit_closes_the_connection_before_it_is_read(sink_factory):
    """Defect: max_size=None: one 400 MiB frame took the server from 61 MiB to 2 GiB. Now the
    frame's header alone (no payload is ever sent here) gets close code 1009 (message too big):
    the server never buffers it."""
    sink = sink_factory(token=TOKEN)
    with _raw_upgrade(sink.port, f"/?token={TOKEN}", (f"Host: 127.0.0.1:{sink.port}",)) as s:
        assert _response_head(s).startswith(b"HTTP/1.1 101")
        # a masked text frame announcing 400 MiB; the payload never follows
        s.sendall(bytes([0x81, 0x80 | 127]) + struct.pack(">Q", 400 << 20) + os.urandom(4))
        s.settimeout(10)
        assert _read_frames_until_close(s) == 1009
    # a client's ordinary messages (subscribe) are far below the limit and still work
    with connect(f"{sink.url}/?token={TOKEN}", subprotocols=PROTO, open_timeout=10) as ws:
        ids = _channels(ws)
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": ids["/ucr/events"]} for i in range(1)]}))  # fmt: skip
        ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": list(range(2000))}))
        assert _next_text(ws)["message"].startswith("Unknown subscription ID: 1 (and 1998 more)")


def test_connections_above_the_cap_are_refused(sink_factory):
    """Defect: nothing counted connections: 400 of 400 were accepted (1217 fds). Now at most
    MAX_CONNECTIONS are open at once; one more is refused (503), and a slot that
    frees up is usable again."""
    from interop import guard as door

    sink = sink_factory(token=TOKEN)
    url = f"{sink.url}/?token={TOKEN}"
    held = [connect(url, subprotocols=PROTO, open_timeout=10) for _ in range(door.MAX_CONNECTIONS)]
    try:
        with pytest.raises((WebSocketException, OSError, EOFError)):
            with connect(url, subprotocols=PROTO, open_timeout=5) as extra:
                extra.recv(timeout=5)  # (on a server without a cap: serverInfo arrives)
        assert sink.guard.refused_connections >= 1
        held.pop().close()
        for _ in range(100):  # the server sees the close as it arrives
            try:
                with connect(url, subprotocols=PROTO, open_timeout=5) as again:
                    assert _next_text(again)["op"] == "serverInfo"
                break
            except (WebSocketException, OSError, EOFError):
                continue
        else:
            raise AssertionError("a freed slot was not usable again")
    finally:
        for ws in held:
            ws.close()


def test_an_idle_socket_flood_cannot_keep_a_viewer_out(sink_factory):
    """Defect (the API's, found in its audit; the door counted the same way): idle TCP sockets
    counted against the 32 connections before any handshake, so 40 of them, reopened as the
    server dropped them after its 5 s handshake timeout, kept every viewer out. Now sockets in
    their handshake are capped apart and a full pending cap evicts the oldest idle one."""
    from interop import guard as door

    sink = sink_factory(token=TOKEN)
    url = f"{sink.url}/?token={TOKEN}"
    flood = IdleFlood(sink.port, door.MAX_CONNECTIONS + 8)
    try:
        for _ in range(3):
            with connect(url, subprotocols=PROTO, open_timeout=5) as ws:
                assert _next_text(ws)["op"] == "serverInfo"
        assert sink.guard.evicted_pending > 0
    finally:
        flood.close()


def test_failed_tokens_back_off_with_429_and_a_valid_token_still_gets_in(sink_factory):
    """Defect: 12 wrong ?token= attempts all got 401, never 429. Now the API's back-off
    (host.api.auth.Backoff, in the API's order): after a few failures a wrong token gets 429 with
    Retry-After; a valid token from the same address still gets in."""
    from host.api.auth import Backoff

    sink = sink_factory(token=TOKEN)
    sink.guard.backoff = Backoff(base_s=60.0)  # a back-off that outlasts the test
    sink.guard.auth_hold_s = 0.0  # (the hold while it is on: not this test's business)
    statuses = []
    for _ in range(6):
        with pytest.raises(InvalidStatus) as exc:
            connect(f"{sink.url}/?token=wrong-token-000000", subprotocols=PROTO, open_timeout=10)
        statuses.append(exc.value.response.status_code)
        if statuses[-1] == 429:
            assert int(exc.value.response.headers["Retry-After"]) >= 1
    assert 401 in statuses and statuses[-2:] == [429, 429], statuses
    assert statuses == sorted(statuses)  # 401 until the back-off is on, then 429
    with connect(f"{sink.url}/?token={TOKEN}", subprotocols=PROTO, open_timeout=10) as ws:
        assert _next_text(ws)["op"] == "serverInfo"


def test_a_slow_client_queue_is_bounded():
    """What waits for one client is bounded in messages and bytes; the oldest data is dropped and
    counted, and a client that leaves too many replies unread is marked to be closed."""
    import asyncio

    from interop import guard as door

    loop = asyncio.new_event_loop()
    try:
        c = door._Client(None, loop)  # type: ignore[arg-type]
        for i in range(door.DATA_BACKLOG * 3):
            c.push_data(1, i, b"x" * 10)
        assert len(c.data) == door.DATA_BACKLOG and c.dropped == door.DATA_BACKLOG * 2
        big = b"y" * (door.DATA_BACKLOG_BYTES // 4)
        for i in range(20):
            c.push_data(1, i, big)
        assert c.data_bytes <= door.DATA_BACKLOG_BYTES
        for _ in range(door.CONTROL_BACKLOG + 1):
            c.push_control("{}")
        assert len(c.control) == door.CONTROL_BACKLOG and c.pop() is True
    finally:
        loop.close()


# -- 11: client messages -------------------------------------------------------------------------
def test_a_subscription_id_beyond_u32_gets_a_status_and_the_connection_lives(sink_factory):
    """Defect: subscribing to a latched topic with id >= 2**32 made the door's struct.pack raise:
    the connection was torn down with a traceback. Now: an error status, and the connection goes
    on (a valid subscription then gets the latched message)."""
    sink = sink_factory(token=TOKEN)
    with connect(f"{sink.url}/?token={TOKEN}", subprotocols=PROTO, open_timeout=10) as ws:
        cid = _channels(ws)["/robot_description"]
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 2**32, "channelId": cid}]}))
        st_ = _next_text(ws)
        assert st_["op"] == "status" and st_["level"] == 2, st_
        ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": cid}]}))
        frame = ws.recv(timeout=10)
        assert isinstance(frame, bytes) and struct.unpack_from("<BIQ", frame) == (1, 7, 5)
    assert sink.guard.invalid_messages == 1


_ids = st.one_of(
    st.integers(min_value=-1, max_value=2**64),
    st.sampled_from([0, 1, 2, 2**31, 2**32 - 1, 2**32, 2**63, 2**64, -(2**31)]),
    st.floats(allow_nan=True),
    st.booleans(),
    st.none(),
    st.text(max_size=5),
    st.lists(st.integers(), max_size=2),
)
_json = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=10),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4)
    ),
    max_leaves=12,
)
_ops = st.sampled_from(["subscribe", "unsubscribe", "advertise", "getParameters", "fetchAsset",
                        "subscribeConnectionGraph", "bogus", ""])  # fmt: skip
_subscription = st.fixed_dictionaries({"id": _ids, "channelId": st.one_of(_ids, st.integers(1, 3))})
CLIENT_MESSAGES = st.one_of(
    st.builds(
        lambda subs: json.dumps({"op": "subscribe", "subscriptions": subs}),
        st.lists(_subscription, max_size=4),
    ),
    st.builds(
        lambda ids: json.dumps({"op": "unsubscribe", "subscriptionIds": ids}),
        st.lists(_ids, max_size=4),
    ),
    st.builds(
        lambda op, rest: json.dumps({"op": op, **rest}),
        _ops,
        st.dictionaries(
            st.sampled_from(["subscriptions", "subscriptionIds", "channels", "id"]),
            _json,
            max_size=3,
        ),
    ),
    st.builds(json.dumps, _json),
    st.text(max_size=64),
    st.binary(max_size=32),
    st.just("[" * 5000 + "]" * 5000),  # nesting too deep for the JSON parser
    st.just('{"op": "subscribe", "subscriptions": [{"id": 1' + "0" * 5000 + ', "channelId": 1}]}'),
)


@settings(max_examples=400, deadline=None)
@given(CLIENT_MESSAGES)
def test_parsing_any_client_message_never_raises(msg):
    from interop import foxglove_protocol as P

    req = P.parse_client(msg)
    if isinstance(req, P.Subscribe):
        assert all(0 <= s < 2**32 and 0 <= c < 2**32 and type(s) is int and type(c) is int
                   for s, c in req.subscriptions)  # fmt: skip
    elif isinstance(req, P.Unsubscribe):
        assert all(type(i) is int and 0 <= i < 2**32 for i in req.ids)
    else:
        assert isinstance(req, P.Invalid) and req.level in (0, 1, 2)
        assert len(req.message) < 200  # never the client's frame echoed back whole


def test_any_client_message_on_a_live_connection_is_answered_not_raised(sink_factory, caplog):
    """Fuzz the door with client messages on one connection: after each, a marker message of
    our own is answered in order, so the connection survived it; nothing logged a traceback."""
    caplog.set_level(logging.DEBUG)
    sink = sink_factory(token=TOKEN)
    marker = itertools.count()
    with connect(f"{sink.url}/?token={TOKEN}", subprotocols=PROTO, open_timeout=10) as ws:
        _channels(ws)

        @settings(max_examples=150, deadline=None,
                  suppress_health_check=[HealthCheck.too_slow])  # fmt: skip
        @given(CLIENT_MESSAGES)
        def check(msg):
            ws.send(msg)
            n = next(marker)
            ws.send(json.dumps({"op": f"marker-{n}"}))
            for _ in range(50):
                m = ws.recv(timeout=10)
                if isinstance(m, str) and f"marker-{n}'" in m:
                    break
            else:
                raise AssertionError("no answer to the marker")

        check()
    assert sink.guard.invalid_messages >= 150  # every marker at least: counted
    assert not [r for r in caplog.records if r.exc_info], "an exception was logged"


def test_the_protocol_matches_foxglove_sdk():
    """The door speaks what foxglove-sdk's server speaks (here as the reference): the same
    serverInfo capabilities and encodings, channel fields, status on a bad subscription, and
    message data bytes."""
    foxglove = pytest.importorskip("foxglove")
    ctx = foxglove.Context()
    ref = foxglove.start_server(name="ucr", host="127.0.0.1", port=0, capabilities=[],
                                supported_encodings=["cdr"], context=ctx)  # fmt: skip
    schema = "string data\n"
    ch = foxglove.Channel("/robot_description", message_encoding="cdr", context=ctx,
                          schema=foxglove.Schema(name="std_msgs/msg/String", encoding="ros2msg",
                                                 data=schema.encode()))  # fmt: skip
    ours = FoxgloveSink(port=0)
    data = b"\x00\x01\x00\x00\x02\x00\x00\x00a\x00"
    ours.write("/robot_description", "std_msgs/msg/String", schema, data, 5)
    got = {}
    try:
        for who, port in (("sdk", ref.port), ("ucr", ours.port)):
            with connect(f"ws://127.0.0.1:{port}", subprotocols=PROTO, open_timeout=10) as ws:
                info = json.loads(ws.recv(timeout=10))
                adv = json.loads(ws.recv(timeout=10))
                cid = adv["channels"][0]["id"]
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": 2**32, "channelId": cid}]}))  # fmt: skip
                bad = json.loads(ws.recv(timeout=10))
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": 3, "channelId": cid}]}))  # fmt: skip
                if who == "sdk":
                    import time

                    time.sleep(0.3)  # the SDK handles the subscribe on its own thread
                    ch.log(data, log_time=5)
                frame = ws.recv(timeout=10)
            got[who] = (info, adv, bad, frame)
    finally:
        ref.stop()
        ours.close()
    (si, sa, sb, sf), (ui, ua, ub, uf) = got["sdk"], got["ucr"]
    assert {k: si[k] for k in ("op", "name", "capabilities", "supportedEncodings")} == {
        k: ui[k] for k in ("op", "name", "capabilities", "supportedEncodings")}  # fmt: skip
    strip = lambda a: [{k: v for k, v in c.items() if k != "id"} for c in a["channels"]]  # noqa: E731
    assert sa["op"] == ua["op"] == "advertise" and strip(sa) == strip(ua)
    assert (sb["op"], sb["level"]) == (ub["op"], ub["level"]) == ("status", 2)
    assert sf == uf == struct.pack("<BIQ", 1, 3, 5) + data


# -- TLS: wss:// with a cert and a private key, as the API -------------------------------------
@pytest.fixture(scope="module")
def tls_files(tmp_path_factory):
    return self_signed(tmp_path_factory.mktemp("tls"))


def test_tls_serves_wss_off_loopback_without_insecure_and_refuses_a_readable_key(
    sink_factory, tls_files, tmp_path
):
    """--tls-cert/--tls-key: the server speaks wss:// (a plain ws:// handshake gets nowhere, the
    token never crosses in clear), so a non-loopback bind needs no --insecure; the key file must
    be private (the API's rule)."""
    import shutil
    import ssl

    from interop.guard import GuardError

    cert, key = tls_files
    sink = sink_factory(host="0.0.0.0", token=TOKEN, tls_cert=str(cert), tls_key=str(key))
    assert sink.url.startswith("wss://")
    ctx = ssl.create_default_context(cafile=str(cert))
    url = f"wss://127.0.0.1:{sink.port}"
    with connect(url, subprotocols=PROTO, ssl=ctx, open_timeout=20,
                 additional_headers={"Authorization": f"Bearer {TOKEN}"}) as ws:  # fmt: skip
        assert "/robot_description" in _channels(ws)
    with pytest.raises((WebSocketException, OSError)):  # plain ws:// to the TLS port
        connect(f"ws://127.0.0.1:{sink.port}", subprotocols=PROTO, open_timeout=3,
                additional_headers={"Authorization": f"Bearer {TOKEN}"}).close()  # fmt: skip
    readable = tmp_path / "key.pem"
    shutil.copy(key, readable)
    readable.chmod(0o644)
    with pytest.raises(GuardError, match="readable by others"):
        sink_factory(host="127.0.0.1", tls_cert=str(cert), tls_key=str(readable))
    with pytest.raises(GuardError, match="both"):
        sink_factory(host="127.0.0.1", tls_cert=str(cert))


def test_the_cli_takes_tls_options_for_every_foxglove_server(tls_files):
    """`ucr foxglove`, `ucr replay` and `ucr record` take --tls-cert/--tls-key (sink_from_args)."""
    import argparse

    from interop.cli import register
    from interop.foxglove import sink_from_args

    cert, key = tls_files
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    for argv in (["foxglove"], ["replay", "x.mcap"], ["record", "-o", "x.mcap"]):
        args = parser.parse_args([*argv, "--tls-cert", str(cert), "--tls-key", str(key)])
        assert (args.tls_cert, args.tls_key) == (str(cert), str(key))
    sink = sink_from_args("127.0.0.1", 0, args)
    try:
        assert sink.url.startswith("wss://127.0.0.1:")
    finally:
        sink.close()
