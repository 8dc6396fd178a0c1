"""Chunked uploads (``trajectory.upload``) and subscription rates: audit findings (2026-11).

- an error in a later chunk named the waypoint's index within that chunk, not within the
  trajectory (``points[257]`` for waypoint 5000);
- a new upload on a connection silently replaced an unfinished one, so two threads sending long
  trajectories through one (thread-safe) client collided (``not_found: no upload 11``);
- ``subscribe`` took ``max_rate: 1e-300``, a subscription that never delivers.

Driven against the in-memory facade of ``test_api_protocol.py``.
"""

from __future__ import annotations

import json
import threading

import pytest
from test_api_protocol import FacadeStub, rpc, wait_for
from websockets.sync.client import connect as ws_connect

from host.api import schema
from host.api.client import ApiError, ApiTimeoutError, connect
from host.api.server import ApiServer
from host.client_common import CliError
from host.client_motion import load_trajectory_file

pytestmark = pytest.mark.timeout(60)


class RecordingStub(FacadeStub):
    """The facade stub, keeping the waypoints of every goal it accepted."""

    def __init__(self) -> None:
        super().__init__(publish_hz=20.0)
        self.sent: dict[str, list[dict]] = {}

    def send_trajectory(
        self, points: list[dict], controller: str | None = None, source: dict | None = None
    ) -> str:
        gid = super().send_trajectory(points, controller, source)
        self.sent[gid] = points
        return gid


@pytest.fixture
def stub():
    s = RecordingStub()
    yield s
    s.close()


@pytest.fixture
def server(stub):
    srv = ApiServer(stub, "127.0.0.1", 0).start()
    yield srv
    srv.stop()


def _points(n: int, t0: float = 0.0, kappa: float = 1.0) -> list[dict]:
    return [
        {"time_from_start": t0 + (i + 1) * 0.01, "segments": {"s1": {"kappa": kappa, "phi": 0.0}}}
        for i in range(n)
    ]


def _upload(ws, points: list[dict], upload: int | None = None, rid: int = 1) -> dict:
    extra = {} if upload is None else {"upload": upload}
    return rpc(ws, {"id": rid, "op": "trajectory.upload", "points": points, **extra})


# ------------------------------------------------------------------ error positions
def test_an_error_in_a_later_chunk_names_its_index_in_the_whole_trajectory(server, tmp_path):
    points = _points(10_000)
    points[5000]["segments"]["s1"]["kappa"] = "x"
    with connect(server.url) as c, pytest.raises(ApiError) as info:
        c.send_trajectory(points, wait=False)
    assert info.value.code == schema.INVALID_PARAMS
    assert "points[5000].segments.s1.kappa: expected a number, got string" in info.value.message
    # `ucr trajectory` validates the file itself: the same waypoint, counted from 1 (prose, not
    # a JSON path: the 5001st waypoint of the file)
    f = tmp_path / "bad.json"
    f.write_text(json.dumps(points))
    with pytest.raises(CliError, match=r"waypoint 5001\.segments\.s1\.kappa"):
        load_trajectory_file(str(f))


def test_times_across_chunks_are_checked_with_the_index_in_the_whole_trajectory(server):
    with ws_connect(server.url) as ws:
        first = _upload(ws, _points(3))  # times 0.01 .. 0.03
        uid = first["result"]["upload"]
        # the next chunk's first waypoint does not come after the upload's last one
        again = _upload(ws, _points(2, t0=0.01), uid, rid=2)
        assert again["error"]["code"] == schema.INVALID_PARAMS
        assert again["error"]["message"].startswith("points[3].time_from_start: times must")
        # ... nor in the last chunk, sent with trajectory.send (and a later waypoint in it)
        uid = _upload(ws, _points(3), rid=3)["result"]["upload"]
        last = _points(3, t0=0.03)
        last[2]["time_from_start"] = 0.01
        sent = rpc(ws, {"id": 4, "op": "trajectory.send", "upload": uid, "points": last})
        assert sent["error"]["message"].startswith("points[5].time_from_start: times must")


def test_a_refused_chunk_ends_its_upload_and_frees_its_points(server):
    with ws_connect(server.url) as ws:
        uid = _upload(ws, _points(3))["result"]["upload"]
        assert server.stats()["upload_points"] == 3
        bad = _points(2, t0=0.03)
        bad[1]["segments"]["s1"]["kappa"] = -1.0
        refused = _upload(ws, bad, uid, rid=2)
        assert refused["error"]["message"].startswith("points[4].segments.s1.kappa: must be >=")
        assert server.stats()["upload_points"] == 0
        gone = _upload(ws, _points(2, t0=0.03), uid, rid=3)
        assert gone["error"]["code"] == schema.NOT_FOUND


# ------------------------------------------------------------------ several uploads
def test_a_new_upload_never_replaces_another_on_the_same_connection(server, stub):
    with ws_connect(server.url) as ws:
        a = _upload(ws, _points(3))["result"]["upload"]
        b = _upload(ws, _points(2, t0=10.0), rid=2)["result"]["upload"]
        assert a != b and server.stats()["upload_points"] == 5
        assert _upload(ws, _points(2, t0=0.03), a, rid=3)["result"] == {"upload": a, "points": 5}
        goal_b = rpc(ws, {"id": 4, "op": "trajectory.send", "upload": b, "points": _points(1, 11)})
        goal_a = rpc(ws, {"id": 5, "op": "trajectory.send", "upload": a, "points": _points(1, 1)})
        assert len(stub.sent[goal_a["result"]["goal"]]) == 6
        assert len(stub.sent[goal_b["result"]["goal"]]) == 3
        assert server.stats()["upload_points"] == 0


def test_uploads_per_connection_are_bounded_with_an_explicit_error(server):
    with ws_connect(server.url) as ws, ws_connect(server.url) as other:
        ids = [
            _upload(ws, _points(1), rid=k)["result"]["upload"] for k in range(schema.MAX_UPLOADS)
        ]
        refused = _upload(ws, _points(1), rid=99)
        assert refused["error"]["code"] == schema.REJECTED
        assert f"at most {schema.MAX_UPLOADS} uploads" in refused["error"]["message"]
        for k, uid in enumerate(ids):  # every one still there
            assert _upload(ws, _points(1, t0=1.0), uid, rid=10 + k)["result"]["points"] == 2
        assert _upload(other, _points(1))["ok"]  # another connection's count is its own
        # an upload is its connection's only
        stolen = _upload(other, _points(1, t0=1.0), ids[0], rid=2)
        assert stolen["error"]["code"] == schema.NOT_FOUND
    assert wait_for(lambda: server.stats()["upload_points"] == 0)


def test_the_bound_on_pending_upload_points_holds_for_several_uploads(stub):
    srv = ApiServer(stub, "127.0.0.1", 0, upload_points_total=5).start()
    try:
        with ws_connect(srv.url) as ws:
            _upload(ws, _points(3))
            b = _upload(ws, _points(2), rid=2)["result"]["upload"]
            over = _upload(ws, _points(1, t0=1.0), b, rid=3)
            assert over["error"]["code"] == schema.UNAVAILABLE
            assert srv.stats()["upload_points"] == 3  # the refused chunk ended upload b
            assert _upload(ws, _points(3), rid=4)["error"]["code"] == schema.UNAVAILABLE
    finally:
        srv.stop()


def test_threads_sending_long_trajectories_through_one_client_all_succeed(server, stub):
    threads_n = 6  # more than schema.MAX_UPLOADS
    # Make the threads overlap: each, once its first chunk is answered, waits (at most 1 s) for
    # the others to have started theirs. A client whose threads take turns gets past it late.
    gather = threading.Barrier(threads_n)
    results: dict[int, object] = {}
    with connect(server.url, timeout=20.0) as c:
        call = c.call

        def overlapping_call(op, timeout=None, **params):
            reply = call(op, timeout, **params)
            if op == "trajectory.upload" and "upload" not in params:
                try:
                    gather.wait(timeout=1.0)
                except threading.BrokenBarrierError:
                    pass
            return reply

        c.call = overlapping_call

        def send(k: int) -> None:
            try:
                results[k] = c.send_trajectory(_points(2000, t0=100.0 * k), wait=False)
            except Exception as exc:  # noqa: BLE001 - reported by the assertion below
                results[k] = exc

        threads = [threading.Thread(target=send, args=(k,)) for k in range(threads_n)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(50)
    assert all(isinstance(results.get(k), str) for k in range(threads_n)), results
    for k in range(threads_n):
        sent = stub.sent[results[k]]
        assert sent == [
            {"time_from_start": p["time_from_start"], "segments": p["segments"]}
            for p in _points(2000, t0=100.0 * k)
        ]
    assert server.stats()["upload_points"] == 0


# ------------------------------------------------------------------ cancel
def test_an_unfinished_upload_can_be_canceled_by_its_connection_only(server):
    """Before ``trajectory.upload_cancel`` an abandoned upload held its points (and one of the
    connection's MAX_UPLOADS slots) for 60 s."""
    with ws_connect(server.url) as ws, ws_connect(server.url) as other:
        uid = _upload(ws, _points(3))["result"]["upload"]
        stolen = rpc(other, {"id": 1, "op": "trajectory.upload_cancel", "upload": uid})
        assert stolen["error"]["code"] == schema.NOT_FOUND
        assert server.stats()["upload_points"] == 3
        done = rpc(ws, {"id": 2, "op": "trajectory.upload_cancel", "upload": uid})
        assert done["result"] == {"upload": uid, "canceled": True, "points": 3}
        assert server.stats()["upload_points"] == 0
        assert _upload(ws, _points(1, t0=1.0), uid, rid=3)["error"]["code"] == schema.NOT_FOUND
        again = rpc(ws, {"id": 4, "op": "trajectory.upload_cancel", "upload": uid})
        assert again["error"]["code"] == schema.NOT_FOUND
        for bad in ({}, {"upload": None}, {"upload": 0}, {"upload": "1"}, {"upload": 1, "x": 1}):
            reply = rpc(ws, {"id": 5, "op": "trajectory.upload_cancel", **bad})
            assert reply["error"]["code"] == schema.INVALID_PARAMS, bad


def test_the_client_cancels_its_upload_when_a_chunk_times_out(server):
    with connect(server.url) as c:
        call = c.call
        chunks = []

        def timing_out(op, timeout=None, **params):
            if op == "trajectory.upload" and "upload" in params:
                chunks.append(params["upload"])
                raise ApiTimeoutError("no reply to trajectory.upload")  # the 2nd chunk's reply lost
            return call(op, timeout, **params)

        c.call = timing_out
        with pytest.raises(ApiTimeoutError):
            c.send_trajectory(_points(2000), wait=False)
        assert chunks and server.stats()["upload_points"] == 0  # the first chunk's points freed
        assert c.cancel_upload(chunks[0]) is False  # already gone


# ------------------------------------------------------------------ subscription rates
@pytest.mark.parametrize("rate", [1e-300, 5e-324, 0.05, 0, -1, 1000.5])
def test_subscribe_refuses_a_max_rate_outside_its_range(server, rate):
    with ws_connect(server.url) as ws:
        msg = {"id": 1, "op": "subscribe", "kinds": ["joint_states"], "max_rate": rate}
        reply = rpc(ws, msg)
        assert reply["error"]["code"] == schema.INVALID_PARAMS
        assert reply["error"]["message"].startswith("max_rate: must be")
        ok = rpc(ws, {**msg, "id": 2, "max_rate": 0.1})
        assert ok["result"]["max_rate"] == 0.1
