"""`ucr emulate` as people run it: prints ports, obeys control commands, stops on SIGTERM."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from host.link import ChainLink

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.needs_micropython  # the emulator runs in a child process
def test_emulate_robot_with_control_socket_and_sigterm(tmp_path) -> None:
    sock_path = tmp_path / "ctl.sock"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tools.cli",
            "emulate",
            "--robot",
            str(ROBOT),
            "--no-stdin",
            "--control-socket",
            str(sock_path),
            "--baud",
            "921600",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        lines = []
        while not lines or not lines[-1].startswith("running"):
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
            lines.append(line.strip())
        host = lines[0].removeprefix("host port: ")
        assert [ln.split(":")[0] for ln in lines[1:4]] == ["segment 1", "segment 2", "segment 3"]
        # the segment directory names the number the line starts with (seg1 for segment 1)
        assert [re.search(r" dir \S*/(seg\d+) ", ln)[1] for ln in lines[1:4]] == [
            "seg1",
            "seg2",
            "seg3",
        ]
        with ChainLink(host) as link:
            end = time.monotonic() + 15
            descs: list = []
            while len(descs) != 3 and time.monotonic() < end:
                descs = link.discover(timeout=0.5)
            assert [d["name"] for d in descs] == ["segment_1", "segment_2", "segment_3"]
            with socket.socket(socket.AF_UNIX) as s:
                s.connect(str(sock_path))
                f = s.makefile("rw")
                f.write("unplug 2\n")  # 1-based: the cable into the second segment
                f.flush()
                assert f.readline().strip() == "link 2 unplugged"
                f.readline()
                f.write("status\n")
                f.flush()
                status = "".join(iter(lambda: f.readline(), "\n"))
                assert "link 1: plugged, 921600 bd" in status and "link 2: UNPLUGGED" in status
            assert [d["position"] for d in link.discover(timeout=0.5)] == [0]
            pids = [int(p) for p in re.findall(r"pid (\d+)", status)]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
        assert proc.returncode == 0, err
        assert "emulator stopped" in out
        assert len(pids) == 3 and not any(_alive(p) for p in pids)
        assert not sock_path.exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_emulate_refuses_a_segment_count_that_does_not_match_the_robot() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "tools.cli", "emulate", "2", "--robot", str(ROBOT)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 2 and "3 bendables" in proc.stderr
