"""Two read-scope ops of the API (issue 15 residuals): ``session`` tells a client its own
connection's scope (no probe with a control op needed, no token revealed), and
``robot.description`` gives the daemon's robot as canonical U(C)RDF text with its sha256, so a
client can compare its own file with the robot the daemon drives."""

from __future__ import annotations

import hashlib
import json

import pytest

from host.api.client import ApiError, connect
from host.api.server import ApiServer
from tests.host.test_api_protocol import FacadeStub
from tests.view.view_helpers import CONTROL_TOKEN, READ_TOKEN, two_token_server
from ucrdf.parser import load, parse_string
from ucrdf.writer import dumps

pytestmark = pytest.mark.timeout(60)

ROBOT = "robots/softrobot3.ucrdf"


class DescribedStub(FacadeStub):
    """The facade stub with a daemon's ``topology`` and description of softrobot3."""

    def __init__(self) -> None:
        super().__init__(publish_hz=50.0)
        from host.daemon import Daemon

        # a daemon that is never started: its facade describes the robot without a chain
        self.daemon = Daemon(ROBOT, port="loop://")

    def topology(self) -> dict:
        return self.daemon.topology()

    def robot_description(self) -> dict:
        return self.daemon.robot_description()


@pytest.fixture
def described():
    with two_token_server(stub=DescribedStub()) as srv:
        yield srv


def test_session_tells_each_token_its_own_scope_and_never_a_token(described):
    with connect(described.url, token=READ_TOKEN, agent="ucr test") as c:
        me = c.session()
        assert me["scope"] == "read" and me["authenticated"] is True
        assert me["agent"] == "ucr test" and me["peer"].startswith("127.0.0.1:")
        text = json.dumps(me)
        assert READ_TOKEN not in text and CONTROL_TOKEN not in text
        assert "viewer.token" not in text  # not even the token's label
    with connect(described.url, token=CONTROL_TOKEN) as c:
        assert c.session()["scope"] == "control"
    # asked in the read scope: nothing was forbidden to learn it
    assert described.stats()["forbidden"] == 0


def test_session_without_tokens_is_control_and_not_authenticated():
    stub = FacadeStub(publish_hz=50.0)
    srv = ApiServer(stub, "127.0.0.1", 0, token=None).start()
    try:
        with connect(srv.url) as c:
            assert c.session() == {
                "scope": "control",
                "authenticated": False,
                "peer": c.session()["peer"],
                "agent": "ucr python client",
            }
            with pytest.raises(ApiError) as err:
                c.call("session", extra=1)
            assert err.value.code == "invalid_params"
    finally:
        srv.stop()
        stub.close()


def test_robot_description_is_the_daemons_robot_in_the_read_scope(described):
    robot = load(ROBOT)
    with connect(described.url, token=READ_TOKEN) as c:
        desc = c.robot_description()
        topo = c.topology()
    assert desc["robot"] == "softrobot3" and desc["file"] == ROBOT
    assert parse_string(desc["text"]) == robot  # the same robot, as the daemon holds it
    data = desc["text"].encode()
    assert desc["bytes"] == len(data)
    assert desc["sha256"] == hashlib.sha256(data).hexdigest()
    assert desc["sha256"] == hashlib.sha256(dumps(robot).encode()).hexdigest()
    # topology carries the sha256 and size (to notice a change), never the text
    assert topo["description"] == {"sha256": desc["sha256"], "bytes": desc["bytes"]}


def test_robot_description_text_is_left_out_above_its_bound(monkeypatch):
    import host.api.schema as schema
    from host.daemon import Daemon

    monkeypatch.setattr(schema, "DESCRIPTION_TEXT_MAX", 100)
    daemon = Daemon(ROBOT, port="loop://")
    desc = daemon.robot_description()
    assert desc["text"] is None and desc["bytes"] > 100
    assert daemon.topology()["description"] == {"sha256": desc["sha256"], "bytes": desc["bytes"]}
    assert desc["sha256"] == hashlib.sha256(dumps(load(ROBOT)).encode()).hexdigest()


def test_a_daemon_that_does_not_describe_its_robot_says_unavailable():
    stub = FacadeStub(publish_hz=50.0)  # it has no robot_description
    srv = ApiServer(stub, "127.0.0.1", 0, token=None).start()
    try:
        with connect(srv.url) as c, pytest.raises(ApiError) as err:
            c.robot_description()
        assert err.value.code == "unavailable"
    finally:
        srv.stop()
        stub.close()
