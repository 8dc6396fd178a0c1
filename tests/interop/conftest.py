"""Fixtures for the interop tests: an emulated 3-segment chain (the real firmware on the
MicroPython VM) driven by the real daemon behind its API, and `ucr` commands run as their own
processes, as a person runs them."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
ROBOT_FILE = REPO / "robots" / "softrobot3.ucrdf"

pytest.importorskip("mcap", reason="the 'record' extra (mcap) is not installed")
pytest.importorskip("mcap_ros2", reason="the 'record' extra (mcap-ros2-support) is not installed")


@pytest.fixture(scope="package")
def rig():
    """(daemon, api server) on an emulated chain of softrobot3; torn down afterwards."""
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load

    robot = load(ROBOT_FILE)
    chain = EmulatedChain(3, config_for=configs(robot))
    daemon = srv = None
    try:
        deadline = time.monotonic() + 20
        while True:  # the VMs need a moment to boot before they answer DISCOVER
            try:
                daemon = Daemon(robot, port=chain.host_port).start()
                break
            except DaemonError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        srv = ApiServer(daemon, "127.0.0.1", 0).start()
        yield daemon, srv
    finally:
        if srv is not None:
            srv.stop()
        if daemon is not None:
            daemon.stop()
        chain.close()


def ucr(*args: str, **kw) -> subprocess.Popen:
    """Start `ucr ARGS` in its own process (stdout/stderr piped, text)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "tools.cli", *args], cwd=REPO, env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw,
    )  # fmt: skip


def wait_for(cond, timeout: float, step: float = 0.05) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(step)
    return bool(cond())


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT, timeout: float = 30.0):
    """Send ``sig`` and wait; returns (returncode, stdout, stderr)."""
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=timeout)
    return proc.returncode, out, err


def straighten(client, timeout: float = 30.0) -> None:
    """Bring every segment back to straight (a trajectory from wherever it is)."""
    if client.status()["manual_control"]:
        client.hand_back()
    pts = [{"time_from_start": 1.5, "segments": {n: {"kx": 0.0, "ky": 0.0}
            for n in ("segment_1", "segment_2", "segment_3")}}]  # fmt: skip
    res = client.send_trajectory(pts, timeout=timeout)
    assert res["state"] == "succeeded", res
