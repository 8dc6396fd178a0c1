"""The view asks the daemon instead of guessing (issue 15 residuals): its token's scope from the
``session`` op (the control-op probe only for an older daemon), and whether FILE is the daemon's
robot from ``robot.description`` (the whole robot compared, each difference named), without a
browser or a chain."""

from __future__ import annotations

import re
import time

import pytest
from view_helpers import CONTROL_TOKEN, NAMES, READ_TOKEN, ROBOT, fake_topology, two_token_server

from host.api.client import ApiError
from ucrdf.parser import load
from ucrdf.writer import dumps

pytestmark = pytest.mark.timeout(120)


class _Sub:
    def __enter__(self) -> _Sub:
        return self

    def __exit__(self, *exc) -> None:
        pass

    def get(self, timeout: float) -> None:  # nothing is pushed
        time.sleep(min(timeout, 0.05))


class _Daemon:
    """An API client on a pretend daemon running softrobot3 that records the ops it is sent.

    ``session``: its answer to ``session`` (None: an older daemon, ``unknown_op``); ``probe``:
    the error code the scope probe gets; ``described``: whether it knows ``robot.description``.
    """

    def __init__(self, session: dict | None, probe: str = "not_found", described: bool = True):
        import hashlib

        self.session, self.probe, self.described = session, probe, described
        self.ops: list[str] = []
        robot = load(ROBOT)
        text = dumps(robot)
        self.description = {"robot": "softrobot3", "file": "/srv/ucr/softrobot3.ucrdf",
                            "sha256": hashlib.sha256(text.encode()).hexdigest(),
                            "bytes": len(text.encode()), "text": text}  # fmt: skip
        self.topo = fake_topology("/srv/ucr/softrobot3.ucrdf")

    def topology(self) -> dict:
        self.ops.append("topology")
        return dict(self.topo)

    def status(self) -> dict:
        return {"state": "connected", "segments": list(NAMES), "active_controllers": ["jtc"]}

    def controllers(self) -> list:
        return []

    def call(self, op: str, **params):
        self.ops.append(op)
        if op == "session" and self.session is not None:
            return dict(self.session)
        if op == "robot.description" and self.described:
            return dict(self.description)
        if op == "trajectory.upload_cancel":
            raise ApiError(self.probe, "the probe's answer")
        raise ApiError("unknown_op", f"unknown op {op!r}")

    def subscribe(self, kinds, max_rate=None) -> _Sub:
        return _Sub()

    def close(self) -> None:
        pass


def _source(monkeypatch, daemon: _Daemon, robot_file=None):
    import view.source as vs

    monkeypatch.setattr(vs, "connect", lambda *a, **k: daemon)
    return vs.LiveSource("ws://127.0.0.1:9", None, None if robot_file is None else str(robot_file))


# -- (a) the token's scope ----------------------------------------------------------------------
def test_the_view_takes_its_scope_from_the_daemons_session_answer_not_a_probe(monkeypatch):
    """The daemon says "read" through ``session``: the view believes it, and sends no control
    op to find out (a probe here would have said control)."""
    daemon = _Daemon({"scope": "read", "authenticated": True})
    src = _source(monkeypatch, daemon, ROBOT)
    try:
        assert src.scope == "read" and src.scope_from == "session"
        assert "session" in daemon.ops and "trajectory.upload_cancel" not in daemon.ops
    finally:
        src.stop()
    daemon = _Daemon({"scope": "control", "authenticated": True}, probe="forbidden")
    src = _source(monkeypatch, daemon, ROBOT)
    try:
        assert src.scope == "control" and "trajectory.upload_cancel" not in daemon.ops
    finally:
        src.stop()


def test_an_older_daemon_without_session_is_probed_as_before(monkeypatch):
    daemon = _Daemon(None, probe="forbidden")
    src = _source(monkeypatch, daemon, ROBOT)
    try:
        assert src.scope == "read" and src.scope_from == "probe"
        assert daemon.ops.index("session") < daemon.ops.index("trajectory.upload_cancel")
    finally:
        src.stop()


def test_the_view_asks_the_real_api_server_its_scope_without_a_forbidden_request():
    from host.api.client import connect
    from view.source import LiveSource

    with two_token_server() as srv:
        with connect(srv.url, token=READ_TOKEN) as c:
            assert LiveSource._ask_scope(c) == ("read", "session")
        with connect(srv.url, token=CONTROL_TOKEN) as c:
            assert LiveSource._ask_scope(c) == ("control", "session")
        assert srv.stats()["forbidden"] == 0  # the old probe cost a read token one each


# -- (b) FILE against the daemon's robot description ---------------------------------------------
def _variant(tmp_path, name: str, old: str, new: str):
    text = ROBOT.read_text()
    assert old in text
    path = tmp_path / name
    path.write_text(text.replace(old, new, 1))
    return path


def test_a_file_differing_beyond_the_bendables_numbers_is_named_and_refused(monkeypatch, tmp_path):
    """Same names, same lengths and limits, but a visual on the base and another mass: the
    topology's segments could not tell (controls were allowed); the description does, and the
    message names what differs and both sha256."""
    path = _variant(
        tmp_path, "visual.ucrdf", '<link name="base"/>',
        '<link name="base"><visual><geometry><box size="0.2 0.2 0.02"/></geometry></visual></link>',
    )  # fmt: skip
    path.write_text(path.read_text().replace('<mass value="0.3"/>', '<mass value="0.5"/>', 1))
    daemon = _Daemon({"scope": "control"})
    src = _source(monkeypatch, daemon, path)
    try:
        why = src.snap.mismatch
        assert why.startswith(f"{path} is not the daemon's robot: "), why
        assert "link 'base': geometry differs" in why, why
        assert "bendable 'segment_1': inertial differs" in why, why
        assert f"the daemon's sha256 {daemon.description['sha256'][:12]}" in why, why
        assert "Controls refused (view only)" in why
        assert "robot.description" in daemon.ops
    finally:
        src.stop()


def test_the_same_robot_written_differently_is_no_mismatch(monkeypatch, tmp_path):
    """Comments, spacing and number spelling do not count: the files are compared as robots."""
    text = ROBOT.read_text()
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S).replace('length="0.316"', 'length="3.16e-1"')
    path = tmp_path / "reformatted.ucrdf"
    path.write_text(text.replace("  ", "\t"))
    src = _source(monkeypatch, _Daemon({"scope": "control"}), path)
    try:
        assert src.snap.mismatch == ""
    finally:
        src.stop()


def test_the_differences_are_said_in_plain_words(monkeypatch, tmp_path):
    path = _variant(tmp_path, "other.ucrdf", 'robot name="softrobot3"', 'robot name="other3"')
    path.write_text(path.read_text().replace('length="0.316"', 'length="0.39"', 1))
    src = _source(monkeypatch, _Daemon({"scope": "control"}), path)
    try:
        why = src.snap.mismatch
        assert "robot name: the daemon's 'softrobot3', the file's 'other3'" in why, why
        # the per-bendable numbers keep their words; the bendable's model is not said twice
        assert "segment_1 length: the daemon's 0.316, the file's 0.39" in why, why
        assert "bendable 'segment_1': model" not in why, why
        said = "the daemon's robot description (/srv/ucr/softrobot3.ucrdf) differs from the file"
        assert said in why, why
    finally:
        src.stop()


def test_an_older_daemon_without_a_description_is_compared_by_its_segments(monkeypatch, tmp_path):
    """No ``robot.description`` (unknown_op): the topology's segments, as before, and the view
    does not ask again on this connection."""
    path = _variant(tmp_path, "long.ucrdf", 'length="0.316"', 'length="0.39"')
    daemon = _Daemon({"scope": "control"}, described=False)
    src = _source(monkeypatch, daemon, path)
    try:
        assert "segment_1 length: the daemon's 0.316, the file's 0.39" in src.snap.mismatch
        assert "sha256" not in src.snap.mismatch
        src._apply_topology(daemon.topology())
        assert daemon.ops.count("robot.description") == 1
    finally:
        src.stop()


def test_the_description_is_asked_again_only_when_the_daemons_robot_changes(monkeypatch):
    daemon = _Daemon({"scope": "control"})
    src = _source(monkeypatch, daemon, ROBOT)
    try:
        assert src.snap.mismatch == ""
        src._apply_topology({**daemon.topo, "controlled": NAMES[:2]})  # a hot-plug push
        assert daemon.ops.count("robot.description") == 1
        daemon.description = {**daemon.description, "robot": "other", "sha256": "ab" * 32,
                              "text": daemon.description["text"].replace(
                                  'name="softrobot3"', 'name="other"', 1)}  # fmt: skip
        src._apply_topology({**daemon.topo, "robot": "other"})  # adopted: another robot
        assert daemon.ops.count("robot.description") == 2
        assert "robot name: the daemon's 'other', the file's 'softrobot3'" in src.snap.mismatch
    finally:
        src.stop()


def test_the_view_against_the_real_api_server_names_the_difference(tmp_path):
    """End to end through the API server and a daemon's facade (never started: no chain)."""
    from host.api.server import ApiServer
    from tests.host.test_api_session_description import DescribedStub
    from view.source import LiveSource

    stub = DescribedStub()
    srv = ApiServer(stub, "127.0.0.1", 0, token=None).start()
    path = _variant(tmp_path, "axis.ucrdf", '<link name="base"/>',
                    '<link name="base"><visual><geometry><sphere radius="0.05"/></geometry>'
                    "</visual></link>")  # fmt: skip
    try:
        src = LiveSource(srv.url, None, str(path))
        try:
            assert "link 'base': geometry differs" in src.snap.mismatch, src.snap.mismatch
            assert src.scope_from == "session"
        finally:
            src.stop()
        same = LiveSource(srv.url, None, str(ROBOT))
        try:
            assert same.snap.mismatch == ""
        finally:
            same.stop()
    finally:
        srv.stop()
        stub.close()
