"""Fixtures for the host daemon tests; helpers live in ``daemon_helpers``.

``chain`` and ``daemon`` are module-scoped: the end-to-end modules that use them share one
emulated 3-segment chain and one daemon per module (a module that needs another kind defines
its own fixture of that name)."""

from __future__ import annotations

import pytest
from daemon_helpers import ROBOT_FILE, emulated_configs, start_daemon

from host.config import DaemonConfig
from host.daemon import Daemon
from tools.emulator import EmulatedChain
from ucrdf.parser import load


@pytest.fixture(scope="session")
def robot3():
    return load(ROBOT_FILE)


@pytest.fixture(scope="module")
def chain(robot3):
    with EmulatedChain(3, config_for=emulated_configs(robot3)) as ch:
        yield ch


@pytest.fixture(scope="module")
def daemon(chain, robot3):
    d = Daemon(robot3, DaemonConfig(port=chain.host_port))
    start_daemon(d)
    yield d
    d.stop()


@pytest.fixture
def stub():
    """The in-memory facade stub (test_api_protocol's ``FacadeStub``; a module may define its
    own fixture of that name)."""
    from test_api_protocol import FacadeStub

    s = FacadeStub()
    yield s
    s.close()


@pytest.fixture
def stub_server(stub):
    """A real API server over ``stub``."""
    from host.api.server import ApiServer

    srv = ApiServer(stub, "127.0.0.1", 0).start()
    yield srv
    srv.stop()


@pytest.fixture
def stub_url(stub_server):
    """The URL of a real API server over the in-memory facade stub (test_api_protocol)."""
    return stub_server.url
