"""Fixtures for the host daemon tests; helpers live in ``daemon_helpers``."""

from __future__ import annotations

import pytest
from daemon_helpers import ROBOT_FILE

from ucrdf.parser import load


@pytest.fixture(scope="session")
def robot3():
    return load(ROBOT_FILE)
