"""Raw HTTP handshakes for the guard tests (API, view, Foxglove door): what a hand-made client,
a browser page or an attacker sends, byte for byte, and the start of the server's answer."""

from __future__ import annotations

import socket
import threading


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


class IdleFlood:
    """``n`` idle TCP connections to ``port`` that never send a byte, each reopened as soon as
    the server closes it (the API and Foxglove door tests)."""

    def __init__(self, port: int, n: int) -> None:
        self.port = port
        self.socks = [self._open() for _ in range(n)]
        self.reopened = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._keep, daemon=True)
        self._thread.start()

    def _open(self) -> socket.socket | None:
        try:
            s = socket.create_connection(("127.0.0.1", self.port), timeout=2)
        except OSError:
            return None
        s.setblocking(False)
        return s

    def _keep(self) -> None:
        while not self._stop.wait(0.02):
            for i, s in enumerate(self.socks):
                try:
                    if s is not None and s.recv(1) != b"":
                        continue  # (the server never sends to an idle socket)
                except BlockingIOError:
                    continue
                except OSError:
                    pass
                if s is not None:
                    s.close()
                self.socks[i] = self._open()
                self.reopened += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        for s in self.socks:
            if s is not None:
                s.close()
