"""`ucr daemon` serves its API from a process of its own (issue 12, finding 7): client load never
competes with the control loop for the interpreter lock. The API process is restarted if it
dies, and ends with the daemon. Figures (200 clients at 10 Hz) are in benchmarks/bench_api.py."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from daemon_helpers import REPO, ROBOT_FILE, emulated_configs, wait_for

from host.api.client import connect
from host.link import ChainLink
from tools.emulator import EmulatedChain

pytestmark = pytest.mark.timeout(180)


@pytest.fixture(scope="module")
def chain(robot3):
    with EmulatedChain(3, config_for=emulated_configs(robot3)) as ch:
        with ChainLink(ch.host_port) as link:  # wait until the segments answer
            assert wait_for(lambda: len(link.discover(timeout=0.3)) == 3, 15.0, 0.1)
        yield ch


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listener_pid(port: int) -> int | None:
    """The pid holding the TCP socket that listens on ``port`` (from /proc)."""
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            f = line.split()
            if int(f[1].rsplit(":", 1)[1], 16) == port and f[3] == "0A":  # LISTEN
                inodes.add(f[9])
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:[") and link[8:-1] in inodes:
                    return int(pid)
        except OSError:
            continue
    return None


def _ppid(pid: int) -> int:
    return int(Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[1])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_ucr_daemon_serves_the_api_from_its_own_process(chain, tmp_path):
    port = _free_port()
    cfg = tmp_path / "daemon.yaml"
    cfg.write_text(f"api: {{bind: 127.0.0.1, port: {port}}}\n")
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "daemon",
            "--robot",
            str(ROBOT_FILE),
            "--port",
            chain.host_port,
            "--config",
            str(cfg),
        ],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    url = f"ws://127.0.0.1:{port}"
    try:

        def api_up() -> bool:
            try:
                with connect(url, timeout=2) as c:
                    return c.status()["state"] == "connected"
            except (ConnectionError, TimeoutError):
                return False

        assert wait_for(api_up, 30.0, 0.2)
        api_pid = _listener_pid(port)
        assert api_pid is not None and api_pid != proc.pid
        assert _ppid(api_pid) == proc.pid  # a child of the daemon, not the daemon

        # the API process dies: the daemon goes on and starts a new one
        os.kill(api_pid, signal.SIGKILL)
        assert wait_for(lambda: _listener_pid(port) not in (None, api_pid), 30.0, 0.2)
        assert proc.poll() is None
        assert wait_for(api_up, 30.0, 0.2)
        new_pid = _listener_pid(port)

        # the daemon ends: so does its API process
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
        assert wait_for(lambda: not _alive(new_pid), 10.0, 0.1)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        time.sleep(0.1)
