"""`ucr daemon` as deployed, a process beside the emulated chain: it serves its API from a process
of its own (issue 12, finding 7), restarted if it dies and ended with the daemon; and it takes
10,000-waypoint trajectories through the Python client and `ucr trajectory` (issue 12, finding 6).
Figures (200 clients at 10 Hz, latency) are in benchmarks/bench_api.py."""

from __future__ import annotations

import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from daemon_helpers import REPO, ROBOT_FILE, emulated_configs, wait_for

from host.api.client import ApiError, connect
from host.link import ChainLink
from host.motion import EVENT_MAX_WAYPOINTS
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


def test_sigterm_to_the_api_process_during_a_slow_daemon_stop_is_not_taken_for_a_crash(caplog):
    """Review 2026-11-26: systemd and a terminal signal every process of the daemon's group;
    the API process exited at once, and a daemon that took a moment before stopping its API
    (`ucr demo`: the printer, the statistics, the view first) logged "API process exited (code
    0); restarting" as an ERROR during an ordered stop. The API process now gives the daemon
    time to stop it."""
    import logging

    from host.api.process import ApiProcess

    class Daemon:  # the facade calls the bridge makes while idle
        def status(self) -> dict:
            return {"state": "connected"}

    api = ApiProcess(Daemon(), "127.0.0.1", 0).start()
    try:
        with caplog.at_level(logging.INFO, logger="ucr.api"):
            os.kill(api.pid, signal.SIGTERM)
            time.sleep(1.5)  # the daemon's own stop work before it stops the API
            api.stop()
        assert api.restarts == 0
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    finally:
        api.stop()


def test_sigterm_to_the_whole_process_group_stops_without_an_api_restart(chain, tmp_path):
    """Review 2026-11-26: systemd (and a terminal) signal every process of the daemon's group;
    the API process exited at once, and the daemon logged "API process exited (code 0);
    restarting" as an ERROR during an ordered stop."""
    port = _free_port()
    cfg = tmp_path / "daemon.yaml"
    cfg.write_text(f"api: {{bind: 127.0.0.1, port: {port}}}\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "daemon", "--robot", str(ROBOT_FILE)]
        + ["--port", chain.host_port, "--config", str(cfg)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True,
    )  # fmt: skip
    try:
        assert wait_for(lambda: _connected(f"ws://127.0.0.1:{port}"), 30.0, 0.2)
        os.killpg(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, out
    assert "segments told to HOLD" in out
    assert "API process exited" not in out and "ERROR" not in out, out
    # an ordered stop is no warning of the API's (it logged "the daemon side closed" as one)
    assert not [ln for ln in out.splitlines() if " WARNING ucr.api" in ln], out


# ------------------------------------------------------------------ issue 12 finding 6
@pytest.fixture(scope="module")
def daemon_url(chain, tmp_path_factory):
    """`ucr daemon` (API in its own process) on the module's chain; its URL."""
    port = _free_port()
    cfg = tmp_path_factory.mktemp("cfg") / "daemon.yaml"
    cfg.write_text(f"api: {{bind: 127.0.0.1, port: {port}}}\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "daemon", "--robot", str(ROBOT_FILE)]
        + ["--port", chain.host_port, "--config", str(cfg)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    url = f"ws://127.0.0.1:{port}"
    try:
        assert wait_for(lambda: _connected(url), 30.0, 0.2)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _connected(url: str) -> bool:
    try:
        with connect(url, timeout=2) as c:
            st = c.status()
            return st["state"] == "connected" and len(st["segments"]) == 3
    except (ConnectionError, TimeoutError):
        return False


def _long_wave(n: int) -> list[dict]:
    """``n`` waypoints, 2 ms apart, a gentle wave on every segment (well inside the limits)."""
    names = ("segment_1", "segment_2", "segment_3")
    return [
        {
            "time_from_start": round(0.5 + 0.002 * i, 6),
            "segments": {
                s: {"kappa": round(0.3 + 0.2 * math.sin(i / 500 + k), 6), "phi": 0.5}
                for k, s in enumerate(names)
            },
        }
        for i in range(n)
    ]


def test_ten_thousand_waypoints_through_the_python_client(daemon_url):
    points = _long_wave(10_000)
    assert len(json.dumps(points)) > 10 * 64 * 1024  # far above one request's limit
    with connect(daemon_url, timeout=10) as c, c.subscribe("events") as events:
        for attempt in range(3):  # a loaded machine may starve the emulated chain into a rebuild
            assert wait_for(lambda: _connected(daemon_url), 30.0, 0.2)
            try:
                goal = c.send_trajectory(points, wait=False)
                break
            except ApiError as exc:
                if attempt == 2 or exc.code not in ("unavailable", "rejected"):
                    raise
        try:
            status = c.trajectory_status(goal)
            assert status["points"] == 10_000
            assert status["state"] in ("executing", "succeeded", "aborted"), status
            # every waypoint as commanded reaches an events subscriber (a recorder), in parts
            parts, deadline = [], time.monotonic() + 20.0
            while time.monotonic() < deadline and (not parts or len(parts) < parts[0]["parts"]):
                ev = events.get(timeout=1.0)
                if ev and ev.get("goal") == goal and ev.get("waypoints") is not None:
                    parts.append(ev)
            k = -(-10_000 // EVENT_MAX_WAYPOINTS)
            assert [p["event"] for p in parts] == ["goal_accepted"] + ["goal_waypoints"] * (k - 1)
            assert [p["part"] for p in parts] == list(range(1, k + 1))
            wps = [w for p in parts for w in p["waypoints"]]
            assert len(wps) == parts[0]["waypoint_count"] == 10_000
            assert wps[-1][0] == pytest.approx(points[-1]["time_from_start"])
        finally:
            c.cancel(goal)


def test_ten_thousand_waypoints_through_ucr_trajectory(daemon_url, tmp_path, capsys):
    from tools.cli import main as ucr

    f = tmp_path / "long.json"
    f.write_text(json.dumps({"waypoints": _long_wave(10_000)}))
    for _ in range(3):  # a loaded machine may starve the emulated chain into a rebuild
        assert wait_for(lambda: _connected(daemon_url), 30.0, 0.2)
        rc = ucr(["trajectory", str(f), "--url", daemon_url, "--no-wait", "--timeout", "10"])
        out, err = capsys.readouterr()
        if rc == 0 or not any(w in err for w in ("unavailable", "rejected", "not controlled")):
            break
    assert rc == 0, err
    goal = out.strip().splitlines()[-1].split()[-1]
    with connect(daemon_url, timeout=10) as c:
        try:
            assert c.trajectory_status(goal)["points"] == 10_000
        finally:
            c.cancel(goal)


def test_the_api_process_says_when_it_cannot_lower_its_priority() -> None:
    """Review 2026-11-26: the unit's seccomp filter took setpriority away, and os.nice's EPERM
    was swallowed: the API ran at the control loop's priority without a word. Now it warns."""
    script = """
import json, os, socket, sys, threading
def refuse(_n):
    raise PermissionError(1, "Operation not permitted")
os.nice = refuse
from host.api import process
from host.api.bridge import send_frame
a, b = socket.socketpair()
config = {"host": "127.0.0.1", "port": -1, "token": None, "options": {}, "log_level": "info"}
send_frame(b, threading.Lock(), b"C", json.dumps(config).encode())
sys.exit(process.main([str(a.detach())]))
"""
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert "could not lower the API process's priority" in proc.stderr, proc.stderr


def test_a_ctrl_c_on_the_terminal_reaches_the_daemon_not_its_api_process():
    """Suite run 2026-11-26 (a loaded machine): Ctrl-C while `ucr daemon` started reached the
    API process too, which died in its imports; the daemon exited 1 with "API process did
    not start". The API process is in a process group of its own: a terminal's SIGINT goes to
    the foreground group (the daemon's) only, and the daemon stops the API in order."""
    from host.api.process import ApiProcess

    class Daemon:
        def status(self) -> dict:
            return {"state": "connected"}

    api = ApiProcess(Daemon(), "127.0.0.1", 0).start()
    try:
        assert os.getpgid(api.pid) == api.pid != os.getpgid(0)
    finally:
        api.stop()


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


@pytest.mark.parametrize("chosen", [None, "pymalloc"])
def test_the_api_process_runs_on_the_c_allocator_unless_the_user_chose_one(monkeypatch, chosen):
    """bench_api 2026-11-27: after 1,000 connection attempts, 1,000 subscription requests and a
    flood of invalid trajectories the API process stayed 5.7 MiB above its baseline (CPython's
    arenas, pinned by a few survivors each, which malloc_trim cannot return); on the C allocator
    2.2 MiB (docs/api.md "Memory"). A PYTHONMALLOC the user set is kept."""
    from host.api.process import ApiProcess

    class Daemon:
        def status(self) -> dict:
            return {"state": "connected"}

    if chosen is None:
        monkeypatch.delenv("PYTHONMALLOC", raising=False)
    else:
        monkeypatch.setenv("PYTHONMALLOC", chosen)
    api = ApiProcess(Daemon(), "127.0.0.1", 0).start()
    try:
        assert _environ(api.pid).get("PYTHONMALLOC") == (chosen or "malloc")
    finally:
        api.stop()
