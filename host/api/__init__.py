"""Local network API of the daemon: JSON over WebSocket beside the control loop, and a client.

``host.api.server`` runs next to a :class:`host.daemon.Daemon`; ``host.api.client`` talks to it.
The wire format (ops, replies, pushes, error codes) lives in ``host.api.schema`` and is
documented in ``docs/api.md``.
"""

from __future__ import annotations

import os

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765  # same default as host.config.ApiConfig
ENV_URL = "UCR_URL"
ENV_TOKEN = "UCR_TOKEN"
ENV_TOKEN_FILE = "UCR_TOKEN_FILE"  # a file (mode 0600) holding the token, for every client
ENV_CA = "UCR_CA"


def default_url() -> str:
    """The URL clients use when none is given: ``$UCR_URL`` or the loopback default."""
    return os.environ.get(ENV_URL) or f"ws://{DEFAULT_HOST}:{DEFAULT_PORT}"
