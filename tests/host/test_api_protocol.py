"""API protocol handling: validation, error replies, disconnect cleanup, slow clients, auth.

These tests drive the server with a small in-test facade (``FacadeStub``) so that request parsing,
error replies, cleanup and back-pressure can be observed precisely; the end-to-end tests against
the real daemon and the emulated chain are in ``test_api_e2e.py``.
"""

from __future__ import annotations

import base64
import json
import math
import os
import queue
import socket
import threading
import time

import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect as ws_connect

from host.api import schema
from host.api.client import ApiAuthError, ApiConnectionError, ApiError, connect, on_behalf_of
from host.api.server import ApiServer, ApiServerError, check_bind, is_loopback

pytestmark = pytest.mark.timeout(60)


class FacadeStub:
    """Implements the Daemon facade contract in memory and records what the server called."""

    def __init__(self, publish_hz: float = 200.0, pad_bytes: int = 200) -> None:
        self.pad = "x" * pad_bytes
        self.lock = threading.Lock()
        self.subscribers: list[tuple[set[str], queue.Queue]] = []
        self.unsubscribed: list[queue.Queue] = []
        self.ffc_calls: list[dict] = []
        self.ffc_sources: list[dict | None] = []  # who sent each (the API's command_source)
        self.goal_sources: list[dict | None] = []  # who sent each goal
        self.switch_calls: list[tuple[list[str], list[str]]] = []
        self.goals: dict[str, dict] = {}
        self.fail_status = False
        self.period = 1.0 / publish_hz
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._publish_loop, daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)

    def _publish_loop(self) -> None:
        n = 0
        while not self._stop.wait(self.period):
            n += 1
            self.publish(self.joint_state(n))

    def joint_state(self, n: int) -> dict:
        """The ``n``-th joint_states message the publishing loop sends (on the daemon's clock)."""
        return {
            "kind": "joint_states",
            "t": time.monotonic(),
            "seq": n,
            "names": ["s1"],
            "kappa": [0.0],
            "phi": [0.0],
            "pad": self.pad,
        }

    def publish(self, msg: dict) -> None:
        with self.lock:
            subs = list(self.subscribers)
        for kinds, q in subs:
            if msg["kind"] in kinds:
                try:
                    q.put_nowait(msg)
                except queue.Full:
                    pass

    # --- facade
    def status(self) -> dict:
        if self.fail_status:
            raise ZeroDivisionError("boom")
        return {
            "state": "connected",
            "robot": "stub",
            "port": "loop://",
            "rate_hz": 100.0,
            "segments": ["s1"],
            "hwi": "active",
            "active_controllers": ["jtc"],
            "joint_states": {"s1": {"kappa": 2.0, "phi": math.pi / 2, "valid": True}},
            "nan": float("nan"),
        }

    def topology(self) -> dict:
        return {"robot": "stub", "expected": ["s1"], "controlled": ["s1"]}

    def loop_stats(self) -> dict:
        if self.fail_status:
            return {"rate_hz": object()}  # something JSON cannot carry
        return {"rate_hz": 100.0}

    def controllers(self) -> list[dict]:
        return [{"name": "jtc", "state": "active"}]

    def switch_controllers(self, start: list[str], stop: list[str]) -> dict:
        if "nope" in start:
            raise ValueError("unknown controller 'nope'")
        self.switch_calls.append((start, stop))
        return {"active": start}

    def send_trajectory(
        self, points: list[dict], controller: str | None = None, source: dict | None = None
    ) -> str:
        self.goal_sources.append(source)
        for p in points:
            for name, target in p["segments"].items():
                if name != "s1":
                    raise ValueError(f"bendable {name!r} is not commanded by 'jtc'")
                if target.get("kappa", 0.0) > 10.0:
                    raise ValueError("kappa exceeds kappa_max 10 1/m (goal rejected)")
        gid = f"g{len(self.goals) + 1}"
        duration = points[-1]["time_from_start"]
        self.goals[gid] = {"t0": time.monotonic(), "duration": duration}
        return gid

    def trajectory_status(self, gid: str) -> dict:
        g = self.goals[gid]
        progress = min(1.0, (time.monotonic() - g["t0"]) / g["duration"])
        state = "succeeded" if progress >= 1.0 else "executing"
        return {
            "id": gid,
            "state": state,
            "progress": progress,
            "done": progress >= 1.0,
            "reason": "",
            "final_error": {"s1": 0.001},
        }

    def cancel_trajectory(self, gid: str) -> bool:
        return gid in self.goals

    def ffc_input(self, rates: dict, source: dict | None = None) -> None:
        with self.lock:
            self.ffc_calls.append(dict(rates))
            self.ffc_sources.append(source)

    def subscribe(self, kinds: list[str]) -> queue.Queue:
        q: queue.Queue = queue.Queue(maxsize=500)
        with self.lock:
            self.subscribers.append((set(kinds), q))
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self.lock:
            self.subscribers = [(k, x) for k, x in self.subscribers if x is not q]
            self.unsubscribed.append(q)


@pytest.fixture
def stub():
    s = FacadeStub()
    yield s
    s.close()


@pytest.fixture
def server(stub):
    srv = ApiServer(stub, "127.0.0.1", 0, outbox_size=64).start()
    yield srv
    srv.stop()


def rpc(ws, msg, timeout: float = 5.0) -> dict:
    """Send a request (dict or raw text/bytes) and return the next reply (skipping pushes)."""
    ws.send(msg if isinstance(msg, str | bytes) else json.dumps(msg))
    deadline = time.monotonic() + timeout
    while True:
        reply = json.loads(ws.recv(timeout=max(0.01, deadline - time.monotonic())))
        if "push" not in reply:
            return reply


def wait_for(pred, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


# ------------------------------------------------------------------ validation / error replies
@pytest.mark.parametrize(
    ("request_text", "code", "reply_id"),
    [
        ("{not json", schema.BAD_JSON, None),
        ('{"id": 1, "op": "ping", "x": NaN}', schema.BAD_JSON, None),
        ("[1, 2]", schema.BAD_REQUEST, None),
        ('{"op": "ping"}', schema.BAD_REQUEST, None),
        ('{"id": 7, "op": 3}', schema.BAD_REQUEST, 7),
        ('{"id": 8, "op": "reboot"}', schema.UNKNOWN_OP, 8),
        ('{"id": 9, "op": "status", "verbose": true}', schema.INVALID_PARAMS, 9),
        ('{"id": 10, "op": "ffc.input", "rates": {"s1": [2.0, 0]}}', schema.INVALID_PARAMS, 10),
        ('{"id": 11, "op": "ffc.input", "rates": {"s1": ["a", 0]}}', schema.INVALID_PARAMS, 11),
        ('{"id": 12, "op": "ffc.input", "rates": "fast"}', schema.INVALID_PARAMS, 12),
        ('{"id": 13, "op": "subscribe", "kinds": ["video"]}', schema.INVALID_PARAMS, 13),
        (
            '{"id": 14, "op": "subscribe", "kinds": ["joint_states"], "max_rate": -1}',
            schema.INVALID_PARAMS,
            14,
        ),
        ('{"id": 15, "op": "trajectory.send", "points": []}', schema.INVALID_PARAMS, 15),
        (
            (
                '{"id": 16, "op": "trajectory.send", "points": [{"time_from_start": 1, '
                '"segments": {"s1": {"kappa": -1}}}]}'
            ),
            schema.INVALID_PARAMS,
            16,
        ),
        (
            (
                '{"id": 17, "op": "trajectory.send", "points": [{"time_from_start": 2, "segments": '
                '{"s1": {"kappa": 1}}}, {"time_from_start": 1, "segments": {"s1": {"kappa": 1}}}]}'
            ),
            schema.INVALID_PARAMS,
            17,
        ),
        ('{"id": 18, "op": "controllers.switch"}', schema.INVALID_PARAMS, 18),
        # review 2026-11-26: duplicate keys were accepted, the last one winning
        ('{"id": 20, "op": "status", "op": "ping"}', schema.BAD_JSON, None),
        ('{"id": 21, "op": "ping", "id": 22}', schema.BAD_JSON, None),
        (
            (
                '{"id": 23, "op": "trajectory.send", "points": [{"t": 1, "segments": '
                '{"s1": {"kappa": 1, "kappa": 2}}}]}'
            ),
            schema.BAD_JSON,
            None,
        ),
        # a time no trajectory can have: "the rate along the path cannot be computed"
        (
            (
                '{"id": 25, "op": "trajectory.send", "points": [{"t": 1e15, "segments": '
                '{"s1": {"kappa": 1}}}]}'
            ),
            schema.INVALID_PARAMS,
            25,
        ),
        # a curvature vector with one component left out was accepted as 0
        (
            (
                '{"id": 24, "op": "trajectory.send", "points": [{"t": 1, "segments": '
                '{"s1": {"ky": 1}}}]}'
            ),
            schema.INVALID_PARAMS,
            24,
        ),
        ('{"id": 19, "op": "unsubscribe", "sub": 999}', schema.NOT_FOUND, 19),
        ('{"id": "x", "op": "controllers.switch", "start": ["nope"]}', schema.REJECTED, "x"),
    ],
)
def test_bad_request_gets_error_reply_and_connection_keeps_serving(
    server, request_text, code, reply_id
):
    with ws_connect(server.url) as ws:
        reply = rpc(ws, request_text)
        assert reply["ok"] is False
        assert reply["error"]["code"] == code, reply
        assert reply["id"] == reply_id
        assert reply["error"]["message"]
        assert rpc(ws, {"id": 99, "op": "ping"}) == {
            "id": 99,
            "ok": True,
            "result": {"pong": True, "t": pytest.approx(time.time(), abs=5)},
        }


def test_oversize_request_gets_too_large_and_connection_survives(server):
    with ws_connect(server.url, max_size=None) as ws:
        big = json.dumps({"id": 1, "op": "ping", "pad": "x" * (70 * 1024)})
        reply = rpc(ws, big)
        assert reply["error"]["code"] == schema.TOO_LARGE
        assert rpc(ws, {"id": 2, "op": "ping"})["ok"] is True


def test_frame_above_hard_limit_closes_only_that_connection(server):
    with ws_connect(server.url) as other:
        with ws_connect(server.url, max_size=None) as ws:
            ws.send("x" * (2 * 1024 * 1024))
            with pytest.raises(ConnectionClosed) as info:
                ws.recv(timeout=5)
            assert info.value.rcvd is not None and info.value.rcvd.code == 1009
        assert rpc(other, {"id": 1, "op": "ping"})["ok"] is True


def test_binary_frame_is_refused_with_error_reply(server):
    with ws_connect(server.url) as ws:
        reply = rpc(ws, b'{"id": 1, "op": "ping"}')
        assert reply["error"]["code"] == schema.BAD_REQUEST
        assert "binary" in reply["error"]["message"]


def test_daemon_exception_becomes_internal_error_not_a_crash(server, stub):
    # status is answered from the daemon's latest snapshot (every 50 ms): let one be taken
    stub.fail_status = True
    time.sleep(0.3)
    with ws_connect(server.url) as ws:
        reply = rpc(ws, {"id": 1, "op": "status"})
        assert reply["error"]["code"] == schema.INTERNAL
        assert "ZeroDivisionError" in reply["error"]["message"]
        stub.fail_status = False
        time.sleep(0.3)
        status = rpc(ws, {"id": 2, "op": "status"})["result"]
        assert status["state"] == "connected"
        assert status["nan"] is None  # non-finite numbers are sent as null (strict JSON)


def test_unencodable_daemon_data_gives_an_error_and_streams_go_on(server, stub):
    with connect(server.url) as c:
        sub = c.subscribe(["joint_states"])
        stub.fail_status = True
        stub.publish({"kind": "joint_states", "t": 0.0, "bad": object()})
        with pytest.raises(ApiError) as info:
            c.loop_stats()
        assert info.value.code == schema.INTERNAL and "not encodable" in info.value.message
        stub.fail_status = False
        time.sleep(0.1)
        got = [sub.get(timeout=2) for _ in range(5)]
        assert all(m is not None and "bad" not in m for m in got)
        assert c.loop_stats() == {"rate_hz": 100.0}


def test_valid_ops_reach_the_facade_with_canonical_params(server, stub):
    with connect(server.url) as c:
        assert c.topology()["controlled"] == ["s1"]
        assert c.loop_stats() == {"rate_hz": 100.0}
        assert c.controllers() == [{"name": "jtc", "state": "active"}]
        c.switch(start=["ffc"], stop=["jtc"])
        assert stub.switch_calls == [(["ffc"], ["jtc"])]
        c.ffc_input({"s1": (0.5, -0.25)})
        assert stub.ffc_calls[-1] == {"s1": (0.5, -0.25)}
        # who sent it goes with it (the cFFC's input_from): the connection as the server sees
        # it, and whom it acts for when it says; never its token's label
        me = c.session()
        assert stub.ffc_sources[-1] == {"peer": me["peer"], "client": me["agent"]}
        with on_behalf_of("stick js0"):
            c.ffc_input({"s1": (0.0, 0.0)})
        assert stub.ffc_sources[-1] == {
            "peer": me["peer"],
            "client": me["agent"],
            "for": "stick js0",
        }
        with pytest.raises(ApiError) as info:
            c.switch(start=["nope"])
        assert info.value.code == schema.REJECTED and "nope" in info.value.message


def test_a_scripts_numpy_values_go_through_and_a_value_json_cannot_carry_is_named(server, stub):
    """Review 2026-11-28: a script's numpy values (``np.float32``: not a float) raised a raw
    TypeError from json inside the client, NaN was "Out of range float values are not JSON
    compliant" without saying which, and a deflection that was not a pair raised IndexError or
    ValueError from the client's own conversion."""
    np = pytest.importorskip("numpy")
    with connect(server.url) as c:
        c.ffc_input({"s1": np.array([0.5, -0.25], dtype=np.float32)})
        assert stub.ffc_calls[-1] == {"s1": (0.5, -0.25)}
        c.ffc_input({"s1": (np.float32(0.25), np.float64(0.0))})
        assert stub.ffc_calls[-1] == {"s1": (0.25, 0.0)}
        point = {"time_from_start": np.float32(1.0), "segments": {"s1": {"kappa": np.float32(2)}}}
        goal = c.send_trajectory([{**point, "segments": {"s1": {"kappa": 2.0, "phi": 0.0}}}],
                                 wait=False)  # fmt: skip
        assert goal in stub.goals
        cases = [
            ([{**point, "segments": {"s1": {"kappa": np.float64("nan"), "phi": 0.0}}}],
             "points[0].segments.s1.kappa: nan is not a finite number"),
            ([{**point, "segments": {"s1": {"kappa": math.inf, "phi": 0.0}}}],
             "points[0].segments.s1.kappa: inf is not a finite number"),
            ([point, {**point, "segments": {"s1": {"kappa": 1.0, "phi": {0.5}}}}],
             "points[1].segments.s1.phi: a set is not a JSON value"),
        ]  # fmt: skip
        for points, where in cases:
            with pytest.raises(ApiError) as info:
                c.send_trajectory(points, wait=False)
            assert info.value.code == schema.INVALID_PARAMS, info.value
            assert info.value.message == f"cannot encode request: {where}"
        # a long trajectory (sent in chunks) with a NaN near its end: refused before any chunk
        # goes, so no half-made upload is left on the server
        sent: list[str] = []
        real_call = c.call
        c.call = lambda op, **kw: sent.append(op) or real_call(op, **kw)
        wave = [{"time_from_start": 0.01 * (k + 1), "segments": {"s1": {"kappa": 1.0, "phi": 0.0}}}
                for k in range(3000)]  # fmt: skip
        wave[2990]["segments"]["s1"]["phi"] = math.nan
        with pytest.raises(ApiError) as info:
            c.send_trajectory(wave, wait=False)
        assert info.value.message == (
            "cannot encode request: points[2990].segments.s1.phi: nan is not a finite number"
        )
        assert sent == []
        c.call = real_call
        for bad in ((0.5,), "ab", 0.5, np.float32(0.5), np.zeros(3)):
            with pytest.raises(ApiError) as info:
                c.ffc_input({"s1": bad})
            assert info.value.code == schema.INVALID_PARAMS and "rates.s1" in info.value.message
        assert not c._pending  # noqa: SLF001 - nothing left waiting for a reply never coming
        assert c.status()  # and the connection goes on


# ------------------------------------------------------------------ streams
def test_subscribe_delivers_messages_and_max_rate_thins_them(server):
    with connect(server.url) as c:
        fast = c.subscribe(["joint_states"])
        slow = c.subscribe(["joint_states"], max_rate=20)
        time.sleep(1.0)
        fast_stats, slow_stats = fast.close(), slow.close()
        # The stub publishes at ~200 Hz; thinned to 20 Hz over ~1 s gives ~20 messages.
        assert fast_stats["sent"] > 80
        assert 10 <= slow_stats["sent"] <= 30
        assert slow_stats["thinned"] > 50
        msg = fast.get(timeout=0) or {}
        assert msg.get("kind") == "joint_states"


def test_trajectory_progress_and_result_are_pushed_to_the_sender(server, stub):
    seen: list[dict] = []
    with connect(server.url) as c:
        points = [{"time_from_start": 0.4, "segments": {"s1": {"kappa": 1.0, "phi": 0.0}}}]
        result = c.send_trajectory(points, progress=seen.append, timeout=5)
        assert result["state"] == "succeeded" and result["done"] is True
        me = c.session()  # who sent it goes with the goal (its status's "from")
        assert stub.goal_sources[-1] == {"peer": me["peer"], "client": me["agent"]}
        assert len(seen) >= 3  # several progress updates before the end
        progress = [s["progress"] for s in seen]
        assert progress == sorted(progress)


def test_client_disconnect_mid_stream_releases_subscription_and_stops_ffc(server, stub):
    ws = ws_connect(server.url)
    assert rpc(ws, {"id": 1, "op": "subscribe", "kinds": ["joint_states", "events"]})["ok"]
    peer = rpc(ws, {"id": 2, "op": "session"})["result"]["peer"]
    for i in range(5):
        assert rpc(ws, {"id": 10 + i, "op": "ffc.input", "rates": {"s1": [0.8, 0.0]}})["ok"]
    ws.recv(timeout=2)  # stream is flowing
    assert len(stub.subscribers) == 1
    # Vanish without a closing handshake, as a killed process would.
    ws.socket.shutdown(socket.SHUT_RDWR)
    ws.socket.close()
    assert wait_for(lambda: server.stats()["clients"] == 0)
    assert wait_for(lambda: not stub.subscribers)
    assert len(stub.unsubscribed) == 1
    # Its cFFC stream is ended with a zero command instead of waiting for the deadman.
    assert wait_for(lambda: stub.ffc_calls[-1] == {"s1": (0.0, 0.0)})
    assert stub.ffc_sources[-1]["peer"] == peer  # in the vanished client's name
    assert "for" not in stub.ffc_sources[-1]
    with connect(server.url) as c:  # and the server still serves
        assert c.ping() < 1.0


def _lazy_client(port: int, request: dict) -> socket.socket:
    """A WebSocket client on a raw socket that sends one request and then never reads."""
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect(("127.0.0.1", port))
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
            "Sec-WebSocket-Version: 13\r\n\r\n"
        ).encode()
    )
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101")
    payload = json.dumps(request).encode()
    assert len(payload) < 126
    mask = os.urandom(4)
    masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
    sock.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)
    return sock


def test_slow_subscriber_gets_drops_and_does_not_block_others(stub):
    stub.period = 1 / 1000  # ~1 kHz of ~16 KB messages: fills socket buffers in a second or two
    stub.pad = "x" * 16000
    srv = ApiServer(stub, "127.0.0.1", 0, outbox_size=16).start()
    try:
        lazy = _lazy_client(srv.port, {"id": 1, "op": "subscribe", "kinds": ["joint_states"]})
        assert wait_for(lambda: srv.stats()["dropped"] > 500, timeout=20)
        with connect(srv.url) as c:
            rtts = [c.ping() for _ in range(20)]
        assert max(rtts) < 0.5
        lazy.close()
    finally:
        srv.stop()


def test_request_flood_is_paced_not_refused(stub):
    srv = ApiServer(stub, "127.0.0.1", 0, max_request_rate=500).start()  # burst 100
    try:
        with ws_connect(srv.url) as ws:
            t0 = time.monotonic()
            for i in range(300):
                ws.send(json.dumps({"id": i, "op": "ping"}))
            replies = [json.loads(ws.recv(timeout=10)) for _ in range(300)]
            elapsed = time.monotonic() - t0
            assert [r["id"] for r in replies] == list(range(300))
            assert all(r["ok"] for r in replies)
            assert elapsed >= 0.9 * (300 - 100) / 500  # paced at ~500 requests/s
            assert srv.stats()["throttled"] > 0
    finally:
        srv.stop()


def test_client_raises_connection_error_when_server_goes_away(stub):
    srv = ApiServer(stub, "127.0.0.1", 0).start()
    c = connect(srv.url)
    sub = c.subscribe(["joint_states"])
    srv.stop()
    with pytest.raises(ConnectionError):
        for _ in sub:
            pass
    with pytest.raises(ApiConnectionError):
        c.status()
    c.close()


def test_connect_to_nothing_is_a_connection_error():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ConnectionError) as info:
        connect(f"ws://127.0.0.1:{port}", timeout=2)
    assert "cannot reach the daemon" in str(info.value)


# ------------------------------------------------------------------ security
def test_loopback_detection():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("") and not is_loopback("robot.local")


def test_non_loopback_bind_without_token_is_refused(stub):
    for host in ("0.0.0.0", "", "192.168.1.20"):
        with pytest.raises(ApiServerError, match="without a token"):
            ApiServer(stub, host, 0)
    # issue 13: tokens need 16+ characters (8 were allowed before)
    with pytest.raises(ApiServerError, match="at least 16"):
        check_bind("0.0.0.0", "short-token-123", insecure=True)


def test_token_is_checked_on_connect(stub):
    srv = ApiServer(stub, "0.0.0.0", 0, token="correct-horse-battery", insecure=True).start()
    url = f"ws://127.0.0.1:{srv.port}"
    try:
        with pytest.raises(ApiAuthError, match="wrong token"):
            connect(url, token="wrong-token-123")
        with pytest.raises(ApiAuthError, match="token is required"):
            connect(url, token="")
        with connect(url, token="correct-horse-battery") as c:
            assert c.status()["state"] == "connected"
        assert srv.stats()["auth_failures"] == 2
    finally:
        srv.stop()


def test_port_in_use_is_a_clear_start_error(stub, server):
    with pytest.raises(ApiServerError, match="cannot listen"):
        ApiServer(stub, "127.0.0.1", server.port).start()


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ({"kx": 0.5}, "give both 'kx' and 'ky'"),
        ({"ky": 1.0}, "give both 'kx' and 'ky'"),
        ({"kx": 0.5, "ky": 0.1, "phi": 1.0}, "give both 'kx' and 'ky' (1/m), or 'kappa' and 'phi'"),
        ({"kappa": 1.0, "foo": 2}, "unknown field(s) foo"),
        ({"kapa": 1.0}, "unknown field(s) kapa"),
    ],
)
def test_a_waypoints_segment_names_what_is_wrong_and_never_guesses_a_component(target, message):
    """Review 2026-11-26: {"kx": 0.5} drove the other axis to 0 without a word; an unknown
    field got only the generic hint."""
    pts = [{"time_from_start": 1.0, "segments": {"s1": target}}]
    with pytest.raises(schema.RequestError) as ei:
        schema.validate_points(pts)
    assert message in ei.value.message and "points[0].segments.s1" in ei.value.message
