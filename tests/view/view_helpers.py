"""Helpers shared by the view tests (imported as ``view_helpers``: pytest puts this directory on
sys.path): the robot file, a pretend daemon's topology of it, waiting (Chromium: the suite's
``browser`` fixture, tests/conftest.py)."""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ROBOT = ROOT / "robots" / "softrobot3.ucrdf"
NAMES = ["segment_1", "segment_2", "segment_3"]


def wait_for(cond, timeout: float, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return bool(cond())


def page_controls(view, timeout: float = 30.0):
    """The controls of the page client that connected last with the page token (one page open)."""
    assert wait_for(lambda: any(p.gizmo is not None or p.sliders for p in view.pages.values()),
                    timeout), view.pages  # fmt: skip
    return view.pages[max(view.pages)]


class RawPage:
    """A page client speaking viser's protocol without a browser (what any local process can do):
    it sends what the page sends and decodes what the view sends it."""

    CAMERA = {"type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0],
              "position": [1.5, -1.5, 1.2], "fov": 1.3, "near": 0.01, "far": 1000.0,
              "image_height": 600, "image_width": 800, "look_at": [0.0, 0.0, 0.35],
              "up_direction": [0.0, 0.0, 1.0]}  # fmt: skip

    def __init__(self, port: int, path: str = "/", host: str = "127.0.0.1"):
        """``path``: the WebSocket's path (the page token's, ``/t/<secret>``, for controls)."""
        import viser
        from websockets.sync.client import connect

        # max_queue=None: the connection's thread keeps reading (and answering the view's pings)
        # while a test does other things for a minute; with websockets' default queue of 16 it
        # stopped reading once 16 messages waited and the keepalive ping timed out (code 1011)
        self.ws = connect(f"ws://{host}:{port}{path}", subprotocols=[f"viser-v{viser.__version__}"],
                          max_size=None, max_queue=None, open_timeout=30)  # fmt: skip
        self.seen: list[dict] = []
        self.send(self.CAMERA)  # viser counts a client as connected after its first camera pose

    def send(self, msg: dict) -> None:
        import msgspec

        self.ws.send(msgspec.msgpack.encode(msg))

    def read_until(self, cond, timeout: float) -> bool:
        """Decode what the view sends until ``cond(message)`` holds for one (all kept in seen)."""
        import msgspec
        import zstandard

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            try:
                raw = self.ws.recv(timeout=max(0.01, end - time.monotonic()))
            except TimeoutError:
                break
            if isinstance(raw, str):
                continue
            n, c = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
            body = zstandard.ZstdDecompressor().decompress(raw[16 : 16 + c], max_output_size=n)
            for m in msgspec.msgpack.decode(body)["messages"]:
                self.seen.append(m)
                if cond(m):
                    return True
        return False

    def labels(self, kind: str) -> list[str]:
        return [m.get("props", {}).get("label", "") for m in self.seen if m.get("type") == kind]

    def close(self) -> None:
        self.ws.close()


def fake_topology(file: str) -> dict:
    """A ``topology`` reply of a daemon running robots/softrobot3.ucrdf from ``file``."""
    from ucrdf.parser import load  # noqa: PLC0415

    robot = load(ROBOT)
    segs = [
        {"position": i + 1, "bendable": n, "name": n, "model": "pcc",
         "length": robot.bendables[n].model.backbone.length,
         "kappa_max": robot.bendables[n].model.limits.kappa_max,
         "kappa_rate_max": robot.bendables[n].model.limits.kappa_rate_max}
        for i, n in enumerate(NAMES)
    ]  # fmt: skip
    return {"robot": "softrobot3", "file": file, "expected": list(NAMES),
            "controlled": list(NAMES), "segments": segs}  # fmt: skip


#: a read-scope and a control-scope token of :func:`two_token_server`
READ_TOKEN, CONTROL_TOKEN = "read-only-token-0123456789", "control-token-0123456789ab"


@contextmanager
def two_token_server(publish_hz: float = 50.0, stub=None):
    """The real API server over ``stub`` (the facade stub by default), with a read and a control
    token (:data:`READ_TOKEN`, :data:`CONTROL_TOKEN`, labelled ``viewer.token`` and
    ``op.token``); yields the server and closes the stub after it."""
    from host.api.auth import CONTROL, READ, Token
    from host.api.server import ApiServer
    from tests.host.test_api_protocol import FacadeStub

    stub = FacadeStub(publish_hz=publish_hz) if stub is None else stub
    tokens = (Token(READ_TOKEN, READ, "viewer.token"), Token(CONTROL_TOKEN, CONTROL, "op.token"))
    srv = ApiServer(stub, "127.0.0.1", 0, tokens=tokens).start()
    try:
        yield srv
    finally:
        srv.stop()
        stub.close()
