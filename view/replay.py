"""A recording as the view's source: ``ucr replay run.mcap --view`` plays an MCAP file (written by
``ucr record``) into the 3D view, at the rate :func:`interop.replay.play` keeps.

:class:`ReplaySource` is an :class:`interop.sinks.Sink` (it receives the encoded ROS 2 messages)
and a view source (``lock``, ``snap``, ``robot``: what :class:`view.app.ViewApp` polls). The robot
comes from the recording's own ``/ucr/robot_description_ucrdf`` (or ``robot_file``), the
configuration from ``/joint_states`` (``<bendable>/kappa``, ``<bendable>/phi``); a bendable whose
recorded position is NaN (no valid state then) shows as fault.
"""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path
from typing import Any

from interop import ros2
from ucrdf.errors import UcrdfError
from ucrdf.parser import load, parse_string
from view.source import Snapshot


class ReplaySource:
    """The recorded robot, updated by the replayed messages (no controls on the page)."""

    mode = "replay"

    def __init__(self, recording: str | Path, robot_file: str | Path | None = None) -> None:
        self.recording = str(recording)
        self.lock = threading.Lock()
        self.snap = Snapshot(robot_file=self.recording, connected=True)
        self.robot: Any = None
        self.messages = 0
        if robot_file is not None:
            self._set_robot(load(robot_file), str(robot_file))

    # -- view source -------------------------------------------------------------------------
    def stop(self) -> None:
        """Nothing runs of its own: :func:`interop.replay.play` drives it."""

    # -- sink --------------------------------------------------------------------------------
    def write(self, topic: str, typename: str, schema: str, data: bytes, t_ns: int) -> None:
        if topic == "/ucr/robot_description_ucrdf" and self.robot is None:
            text = ros2.codec(typename).decode(data).data
            try:
                robot = parse_string(text, f"{self.recording}:/ucr/robot_description_ucrdf")
            except UcrdfError as exc:
                with self.lock:
                    self.snap.errors = [str(d) for d in exc.diagnostics]
                    self.snap.seq += 1
                return
            self._set_robot(robot, self.recording)
        elif topic == "/joint_states":
            self._joints(ros2.codec(typename).decode(data))

    def tick(self) -> None:
        """Nothing to flush."""

    def close(self) -> None:
        """Nothing to release (the view is stopped by its owner)."""

    # -- internals ---------------------------------------------------------------------------
    def _set_robot(self, robot: Any, name: str) -> None:
        with self.lock:
            self.robot = robot
            s = self.snap
            s.robot_file = name
            s.robot_version += 1
            s.expected = list(robot.bendables)
            s.present = list(robot.bendables)
            s.status = {n: "ok" for n in robot.bendables}
            s.topology_seq += 1
            s.seq += 1

    def _joints(self, msg: Any) -> None:
        vals: dict[str, dict[str, float]] = {}
        for name, pos in zip(msg.name, msg.position, strict=False):
            seg, _, var = name.rpartition("/")
            if seg and var in ("kappa", "phi"):
                vals.setdefault(seg, {})[var] = float(pos)
        with self.lock:
            s = self.snap
            for seg, v in vals.items():
                ok = len(v) == 2 and all(math.isfinite(x) for x in v.values())
                if ok:
                    s.state[seg] = {"kappa": v["kappa"], "phi": v["phi"]}
                s.valid[seg] = ok
                s.status[seg] = "ok" if ok else "fault"
            s.t_received = time.monotonic()
            s.seq += 1
            s.sample_seq += 1  # a recorded sample: the latency figure counts it
            self.messages += 1
