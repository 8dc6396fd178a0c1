"""The end-to-end rig: an emulated chain (the real firmware on the MicroPython VM), the real
daemon driving it and its API server on a free loopback port — what the end-to-end tests
(tests/host, tests/view, tests/interop_clients) and the benchmarks (bench_api, bench_view,
bench_record, bench_zenoh) start. One place, so they all boot, wait and tear down alike.

    from tools.rig import EmulatedRig
    with EmulatedRig("softrobot3.ucrdf", rate_hz=50.0) as rig:
        connect(rig.url).status()

The daemon is started again and again while the emulated segments boot (they answer DISCOVER
only once their VM runs); a rig that cannot start closes what it opened.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
ROBOTS = REPO / "robots"
DEFAULT_ROBOT = ROBOTS / "softrobot3.ucrdf"
BOOT_TIMEOUT_S = 20.0  # how long the segments may take to answer DISCOVER (a loaded machine)


def start_daemon_on(chain: Any, robot: Any, boot_timeout_s: float, **daemon_args: Any) -> Any:
    """A started :class:`host.daemon.Daemon` on ``chain``, retried while its segments boot
    (DaemonError after ``boot_timeout_s``)."""
    from host.daemon import Daemon, DaemonError  # noqa: PLC0415 - `ucr --help` stays fast

    deadline = time.monotonic() + boot_timeout_s
    while True:
        try:
            return Daemon(robot, port=chain.host_port, **daemon_args).start()
        except DaemonError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class EmulatedRig:
    """``chain`` (:class:`tools.emulator.EmulatedChain`, one segment per bendable of
        ``robot``), ``daemon`` and ``api`` (``"thread"``: :class:`host.api.server.ApiServer` in this
        process; ``"process"``: :class:`host.api.process.ApiProcess`; None: no API).

        ``robot`` is a U(C)RDF path or a file name in robots/; ``rate_hz`` the loop rate (None: the
        configuration's); ``realtime_priority`` the daemon's SCHED_FIFO priority (0: normal,
    host/realtime.py). :meth:`restart_daemon` starts a fresh daemon (and API) on the same chain.
    """

    def __init__(
        self,
        robot: str | Path = DEFAULT_ROBOT,
        *,
        rate_hz: float | None = None,
        realtime_priority: int = 0,
        api: str | None = "thread",
        boot_timeout_s: float = BOOT_TIMEOUT_S,
    ) -> None:
        from tools.emulator import EmulatedChain  # noqa: PLC0415
        from tools.segment_config import configs  # noqa: PLC0415
        from ucrdf.parser import load  # noqa: PLC0415

        if api not in ("thread", "process", None):
            raise ValueError(f"api must be 'thread', 'process' or None, not {api!r}")
        path = Path(robot)
        self.robot_file = path if path.is_absolute() or path.exists() else ROBOTS / path
        self.robot = load(self.robot_file)
        self.rate_hz = rate_hz
        self.realtime_priority = realtime_priority
        self.api_kind = api
        self.boot_timeout_s = boot_timeout_s
        self.daemon: Any = None
        self.api: Any = None
        self.chain = EmulatedChain(len(self.robot.bendables), config_for=configs(self.robot))
        try:
            self.start_daemon()
        except BaseException:
            self.close()
            raise

    @property
    def srv(self) -> Any:
        """The API server (the name the tests use)."""
        return self.api

    @property
    def url(self) -> str:
        """The API's ``ws://`` URL."""
        return self.api.url

    def start_daemon(self) -> None:
        """Start the daemon (retried while the segments boot), then its API."""
        args: dict[str, Any] = {"realtime_priority": self.realtime_priority}
        if self.rate_hz is not None:
            args["rate_hz"] = self.rate_hz
        self.daemon = start_daemon_on(self.chain, self.robot, self.boot_timeout_s, **args)
        if self.api_kind == "thread":
            from host.api.server import ApiServer  # noqa: PLC0415

            self.api = ApiServer(self.daemon, "127.0.0.1", 0).start()
        elif self.api_kind == "process":
            from host.api.process import ApiProcess  # noqa: PLC0415

            self.api = ApiProcess(self.daemon, "127.0.0.1", 0).start()

    def stop_daemon(self) -> None:
        """Stop the API, then the daemon (segments told to HOLD); the chain keeps running."""
        if self.api is not None:
            self.api.stop()
        if self.daemon is not None:
            self.daemon.stop()
        self.api = self.daemon = None

    def restart_daemon(self) -> None:
        """A fresh daemon (and API) on the same chain: it discovers the chain again."""
        self.stop_daemon()
        self.start_daemon()

    def close(self) -> None:
        """Stop the API and the daemon, then the emulated segments."""
        try:
            self.stop_daemon()
        finally:
            self.chain.close()

    def __enter__(self) -> EmulatedRig:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
