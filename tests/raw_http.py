"""Raw HTTP handshakes for the guard tests (API, view, Foxglove door): what a hand-made client,
a browser page or an attacker sends, byte for byte, and the start of the server's answer."""

from __future__ import annotations

import socket


def read_head(s: socket.socket, end: bytes = b"\r\n") -> bytes:
    """Read from ``s`` until ``end`` has arrived (the status line by default; ``b"\\r\\n\\r\\n"``
    for all headers) or the server closed; what was read."""
    data = b""
    while end not in data:
        chunk = s.recv(4096)
        if not chunk:
            break
        data += chunk
    return data
