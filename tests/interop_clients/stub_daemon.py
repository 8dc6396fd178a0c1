"""A daemon facade in memory for the interop clients' tests that need no emulated chain: the
API's contract (what :class:`host.api.server.ApiServer` calls) for softrobot2, joint states at
``publish_hz`` on the daemon's clock (``time.monotonic``), no goals. Served by a real
ApiServer, so ``ucr record`` / ``ucr foxglove`` run against it as their own processes."""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ROBOT_FILE = REPO / "robots" / "softrobot2.ucrdf"
NAMES = ["segment_1", "segment_2"]


class StubDaemon:
    def __init__(self, publish_hz: float = 50.0) -> None:
        self.lock = threading.Lock()
        self.subscribers: list[tuple[set[str], queue.Queue]] = []
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
            self.publish({"kind": "joint_states", "t": time.monotonic(), "seq": n,
                          "names": NAMES, "kappa": [0.5, 0.5], "phi": [0.0, 0.0]})  # fmt: skip

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
        js = {n: {"kappa": 0.5, "phi": 0.0, "valid": True} for n in NAMES}
        return {"state": "connected", "robot": "softrobot2", "port": "loop://", "rate_hz": 50.0,
                "segments": NAMES, "hwi": "active", "active_controllers": ["jtc"],
                "running_goals": [], "joint_states": js}  # fmt: skip

    def topology(self) -> dict:
        return {"robot": "softrobot2", "expected": NAMES, "controlled": NAMES,
                "file": str(ROBOT_FILE)}  # fmt: skip

    def loop_stats(self) -> dict:
        return {"rate_hz": 50.0}

    def controllers(self) -> list[dict]:
        return [{"name": "jtc", "state": "active"}]

    def subscribe(self, kinds: list[str]) -> queue.Queue:
        q: queue.Queue = queue.Queue(maxsize=500)
        with self.lock:
            self.subscribers.append((set(kinds), q))
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self.lock:
            self.subscribers = [(k, x) for k, x in self.subscribers if x is not q]
