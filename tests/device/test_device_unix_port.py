"""The firmware as the emulator launches it: ``micropython -X heapsize=160k -i main.py`` in a
segment directory, UARTs on ptys named by UCR_UP_PORT / UCR_DOWN_PORT, REPL on the process's
controlling pty. Proves the unix HAL (raw ptys, poll), the loop, fault injection by UCR_FAULTS,
and that Ctrl-C on the REPL leaves the process at the REPL prompt (what mpremote needs)."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import shutil
import subprocess
import termios
import time
import tty
from pathlib import Path

import pytest

from protocol import messages as M
from protocol.frame import FrameReader
from tools import mpvm

REPO = mpvm.REPO


def _read(fd: int, seconds: float) -> bytes:
    out = b""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.02)
        if r:
            try:
                out += os.read(fd, 4096)
            except OSError:
                break
    return out


@pytest.fixture
def segment(tmp_path: Path):
    """One firmware process on ptys; yields (up master fd, down master fd, repl master fd, proc)."""
    binary = mpvm.micropython_binary()
    seg = tmp_path / "seg"
    shutil.copytree(REPO / "device", seg, ignore=shutil.ignore_patterns("__pycache__"))
    (seg / "protocol").mkdir()
    for f in (REPO / "protocol").glob("*.py"):
        shutil.copy2(f, seg / "protocol" / f.name)
    fds = []
    pairs = [pty.openpty() for _ in range(3)]
    for m, s in pairs:
        fds += [m, s]
    (um, us), (dm, ds), (rm, rs) = pairs
    for fd in (um, dm):
        tty.setraw(fd)
    env = dict(
        os.environ,
        UCR_UP_PORT=os.ttyname(us),
        UCR_DOWN_PORT=os.ttyname(ds),
        UCR_UID="C0FFEE000001",
        UCR_FAULTS="2:overload",
        MICROPYPATH=f".frozen:{seg}",
    )

    def child() -> None:
        os.setsid()
        fcntl.ioctl(0, termios.TIOCSCTTY, 0)

    proc = subprocess.Popen(
        [binary, "-X", "heapsize=160k", "-i", "main.py"],
        cwd=seg,
        env=env,
        stdin=rs,
        stdout=rs,
        stderr=rs,
        preexec_fn=child,
    )
    try:
        yield um, dm, rm, proc
    finally:
        proc.kill()
        proc.wait(timeout=5)
        for fd in fds:
            os.close(fd)


def test_unix_port_segment_answers_on_ptys_and_ctrl_c_reaches_the_repl(segment):
    um, dm, rm, proc = segment
    banner = b""
    end = time.monotonic() + 10
    while b"up, 200 Hz" not in banner and time.monotonic() < end:
        banner += _read(rm, 0.1)
    assert b"segment c0ffee000001 up" in banner
    os.write(um, M.encode_discover(1) + M.encode_heartbeat(2, 5))
    msgs = [M.decode_message(f) for f in FrameReader().feed(_read(um, 0.3))]
    desc = [m for m in msgs if m["type"] == "DESCRIPTOR"]
    assert desc and desc[0]["uid"] == "c0ffee000001" and desc[0]["servo_driver"] == "emulated"
    state = [m for m in msgs if m["type"] == "STATE"]
    assert state and {"HOLD", "UNCONFIGURED", "SERVO_FAULT"} <= state[0]["status"]
    assert any(m["type"] == "EVENT" and m["name"] == "SERVO_FAULT" for m in msgs)
    down = FrameReader().feed(_read(dm, 0.1))
    assert [(f.mtype, f.hop) for f in down] == [(0x01, 1), (0x03, 1)]
    os.write(rm, b"\x03")
    out = _read(rm, 1.0)
    assert b"KeyboardInterrupt" in out and out.rstrip().endswith(b">>>")
    assert proc.poll() is None  # still alive, at the REPL
