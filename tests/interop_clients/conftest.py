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


class Rig:
    """The real daemon (50 Hz: less load on a shared machine, more slack for the emulated
    segments) and its API server on an emulated chain of softrobot3."""

    def __init__(self) -> None:
        from tools.rig import EmulatedRig

        self._rig = EmulatedRig(ROBOT_FILE, rate_hz=50.0, boot_timeout_s=30)

    @property
    def daemon(self):
        return self._rig.daemon

    @property
    def srv(self):
        return self._rig.srv

    @property
    def url(self) -> str:
        return self.srv.url

    def _whole(self) -> bool:
        st = self.daemon.status()
        js = st["joint_states"]
        return st["state"] == "connected" and len(js) == 3 and all(s["valid"] for s in js.values())

    def ensure_whole(self) -> str:
        """The API URL of a daemon controlling all three segments. On a heavily loaded machine
        an emulated segment can miss enough cycles that the daemon (rightly) cuts the chain
        there; then start a fresh daemon, which discovers the chain again."""
        if not wait_for(self._whole, 15, 0.1):
            self._rig.restart_daemon()
            assert wait_for(self._whole, 60, 0.1), self.daemon.status()
        return self.url

    def close(self) -> None:
        self._rig.close()


@pytest.fixture(scope="package")
def rig():
    r = Rig()
    try:
        yield r
    finally:
        r.close()


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


def whole_chain(client, timeout: float = 30.0) -> None:
    """Wait until the daemon controls all three segments with valid states (after a rebuild)."""

    def ok() -> bool:
        st = client.status()
        js = st["joint_states"]
        return st["state"] == "connected" and len(js) == 3 and all(s["valid"] for s in js.values())

    assert wait_for(ok, timeout, 0.1), client.status()


def _starved(result: dict) -> bool:
    """An abort that a starved emulator causes on a loaded machine (the daemon being safe): a
    segment process not scheduled for 150 ms reads as a neighbour gone (DOWNSTREAM_DOWN, a
    topology change) or as a lost link, path error or hold."""
    why = result.get("reason", "")
    cause = (result.get("abort") or {}).get("cause")
    return cause in ("topology_change", "link_loss", "path_tolerance", "segment_fault") or any(
        w in why
        for w in ("topology changed", "link loss", "path tolerance", "holding", "DOWNSTREAM_DOWN")
    )


def straighten(client, timeout: float = 30.0) -> None:
    """Bring every segment back to straight (a trajectory from wherever it is)."""
    for _ in range(3):  # a loaded machine may drop a segment for a moment: the goal aborts
        whole_chain(client)
        if client.status()["manual_control"]:
            client.hand_back()
        pts = [{"time_from_start": 1.5, "segments": {n: {"kx": 0.0, "ky": 0.0}
                for n in ("segment_1", "segment_2", "segment_3")}}]  # fmt: skip
        res = client.send_trajectory(pts, timeout=timeout)
        if res["state"] == "succeeded" or not _starved(res):
            break
    assert res["state"] == "succeeded", res


GOAL = {"segment_1": (2.0, 0.5), "segment_3": (1.5, -1.2)}  # kappa 1/m, phi rad
EXPECTED_TOPICS = {
    "/robot_description": "std_msgs/msg/String",
    "/ucr/robot_description_ucrdf": "std_msgs/msg/String",
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/joint_states": "sensor_msgs/msg/JointState",
    "/ucr/arcs": "visualization_msgs/msg/MarkerArray",
    "/ucr/segments": "diagnostic_msgs/msg/DiagnosticArray",
    "/ucr/loop_stats": "diagnostic_msgs/msg/DiagnosticArray",
    "/ucr/trajectory/goals": "std_msgs/msg/String",
    "/ucr/trajectory/results": "std_msgs/msg/String",
    "/ucr/trajectory/commanded": "trajectory_msgs/msg/JointTrajectory",
}


@pytest.fixture(scope="package")
def recording(rig, tmp_path_factory):
    """A recording of one trajectory (segment_1 and segment_3 bend, then hold)."""
    from host.api.client import connect

    url = rig.ensure_whole()
    path = tmp_path_factory.mktemp("rec") / "run.mcap"
    with connect(url) as c:
        straighten(c)
        proc = ucr("record", "-o", str(path), "--url", url, "--robot", str(ROBOT_FILE))
        try:
            assert wait_for(lambda: path.exists() and path.stat().st_size > 0, 30)
            time.sleep(1.0)
            pts = [{"time_from_start": 1.5, "segments": {n: {"kappa": k, "phi": p}
                    for n, (k, p) in GOAL.items()}}]  # fmt: skip
            sent = []  # every goal sent: each is recorded (commanded, accepted)
            for _ in range(3):  # see straighten(): a segment dropped under load aborts a goal
                whole_chain(c)
                result = c.send_trajectory(pts, timeout=30)
                sent.append(result["id"])
                if not _starved(result):
                    break
            assert result["state"] == "succeeded", result
            result = {**result, "sent": sent}
            time.sleep(1.5)  # the goal poll (2 Hz) and a status poll (1 Hz) see the result
        finally:
            code, out, err = stop(proc)
    assert code == 130 and "ucr: interrupted (Ctrl-C)" in err, err  # Ctrl-C: the file closed
    return path, result, err


NODE_DIR = Path(__file__).resolve().parent / "node"


@pytest.fixture(scope="session")
def node_clients():
    """Directory holding the npm packages of tests/interop_clients/node (installed once with
    `npm ci` into a cache outside the repository, keyed by the lock file) and the test scripts."""
    import hashlib
    import shutil

    node, npm = shutil.which("node"), shutil.which("npm")
    if not node or not npm:
        pytest.skip("node and npm are needed for the independent JavaScript clients")
    lock = (NODE_DIR / "package-lock.json").read_bytes()
    key = hashlib.sha256(lock).hexdigest()[:16]
    base = Path(os.environ.get("UCR_NODE_CACHE") or Path.home() / ".cache" / "ucr-tests")
    target = base / f"interop-node-{key}"
    if not (target / "node_modules" / ".ucr-complete").exists():
        target.mkdir(parents=True, exist_ok=True)
        for name in ("package.json", "package-lock.json"):
            shutil.copy(NODE_DIR / name, target / name)
        try:
            res = subprocess.run(
                [npm, "ci", "--no-audit", "--no-fund", "--ignore-scripts"], cwd=target,
                capture_output=True, text=True, timeout=600,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            pytest.skip("npm ci timed out (npm registry unreachable?)")
        if res.returncode != 0:
            tail = (res.stderr or res.stdout).strip().splitlines()[-3:]
            pytest.skip(f"npm ci failed (npm registry unreachable?): {' / '.join(tail)}")
        (target / "node_modules" / ".ucr-complete").write_text(key)
    for script in NODE_DIR.glob("*.mjs"):
        shutil.copy(script, target / script.name)
    return target


def run_node(node_dir: Path, script: str, *args: str, timeout: float = 120.0) -> dict:
    """Run one of the node scripts; returns its JSON output."""
    import json

    res = subprocess.run(["node", script, *args], cwd=node_dir, capture_output=True, text=True,
                         timeout=timeout)  # fmt: skip
    assert res.stdout.strip(), f"no output from {script}: {res.stderr}"
    out = json.loads(res.stdout.strip().splitlines()[-1])
    out["_returncode"] = res.returncode
    out["_stderr"] = res.stderr
    return out
