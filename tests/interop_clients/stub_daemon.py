"""A daemon facade in memory for the interop clients' tests that need no emulated chain: the
API's contract (what :class:`host.api.server.ApiServer` calls) for softrobot2, joint states at
``publish_hz`` on the daemon's clock (``time.monotonic``), no goals. Served by a real
ApiServer, so ``ucr record`` / ``ucr foxglove`` run against it as their own processes. The
facade's mechanics (publishing loop, subscriptions) are the API tests' ``FacadeStub``."""

from __future__ import annotations

import time
from pathlib import Path

from tests.host.test_api_protocol import FacadeStub

REPO = Path(__file__).resolve().parents[2]
ROBOT_FILE = REPO / "robots" / "softrobot2.ucrdf"
NAMES = ["segment_1", "segment_2"]


class StubDaemon(FacadeStub):
    def __init__(self, publish_hz: float = 50.0) -> None:
        super().__init__(publish_hz=publish_hz)

    def joint_state(self, n: int) -> dict:
        return {"kind": "joint_states", "t": time.monotonic(), "seq": n,
                "names": NAMES, "kappa": [0.5, 0.5], "phi": [0.0, 0.0]}  # fmt: skip

    # --- facade (softrobot2's)
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
