"""A serial port that will not open says why and what to do (host/serialport.py, issue 10).

Real ports: pseudo-terminals stand in for /dev/ttyUSB0, with the group and mode udev gives an
adapter (root:dialout 0660); the busy port is held the way the daemon holds it (pyserial's
exclusive lock) by another process.
"""

from __future__ import annotations

import grp
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from host.link import ChainLink, LinkError
from host.serialport import describe_open_error, holders

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture
def pty_port():
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield path
    os.close(slave)
    os.close(master)


def test_missing_port_points_at_the_stable_names() -> None:
    with pytest.raises(LinkError) as info:
        ChainLink("/dev/ttyUCRnothere0")
    msg = str(info.value)
    assert "/dev/ttyUCRnothere0" in msg and "does not exist" in msg
    assert "/dev/serial/by-id/" in msg


def test_a_regular_file_as_port_is_named_not_a_serial_port(tmp_path) -> None:
    # new-user audit: pyserial's "Could not configure port: (25, 'Inappropriate ioctl for
    # device')" was all a user given a wrong --port learned
    f = tmp_path / "notatty"
    f.write_bytes(b"")
    with pytest.raises(LinkError) as info:
        ChainLink(str(f))
    msg = str(info.value)
    assert "not a serial port" in msg and "--port" in msg and "ioctl" not in msg, msg


def test_missing_pi_uart_says_how_to_enable_it() -> None:
    msg = describe_open_error("/dev/serial0", FileNotFoundError(2, "No such file or directory"))
    assert "raspi-config" in msg and "enable_uart=1" in msg


def test_busy_port_names_the_process_that_holds_it(pty_port) -> None:
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            textwrap.dedent(
                f"""
                import serial, sys, time
                s = serial.Serial({pty_port!r}, exclusive=True)
                print("held", flush=True)
                sys.stdin.read()
                """
            ),
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        assert holder.pid in [pid for pid, _ in holders(pty_port)]
        with pytest.raises(LinkError) as info:
            ChainLink(pty_port)
        msg = str(info.value)
        assert "busy" in msg and f"PID {holder.pid} (" in msg, msg
        assert "Errno" not in msg
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)


def test_the_ptys_other_end_is_not_named_as_a_competing_holder() -> None:
    """Review 2026-11-26: with `ucr emulate` and one daemon, a second daemon was told the port
    is "held by PID <emulate> (ucr), PID <daemon> (ucr)": the emulator keeps its pty's slave
    open, but it is the device end (it has the master), not a competitor."""
    script = textwrap.dedent(
        """
        import os, sys
        master, slave = os.openpty()  # the emulated device: both ends, as tools/emulator does
        print(os.ttyname(slave), flush=True)
        sys.stdin.read()
        """
    )
    device = subprocess.Popen(
        [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    user = None
    try:
        path = device.stdout.readline().strip()
        user = subprocess.Popen(
            [sys.executable, "-c", f"import sys; f = open({path!r}, 'rb', 0); sys.stdin.read()"],
            stdin=subprocess.PIPE,
        )
        end = time.monotonic() + 10
        while user.pid not in [p for p, _ in holders(path)] and time.monotonic() < end:
            time.sleep(0.05)
        assert [p for p, _ in holders(path)] == [user.pid]
    finally:
        for proc in (user, device):
            if proc is not None:
                proc.stdin.close()
                proc.wait(timeout=30)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to open the port as another user")
def test_permission_error_names_the_dialout_group_and_the_fix(pty_port) -> None:
    dialout = grp.getgrnam("dialout").gr_gid
    os.chown(pty_port, 0, dialout)
    os.chmod(pty_port, 0o660)
    code = textwrap.dedent(
        f"""
        import os, sys
        sys.path.insert(0, {str(REPO)!r})
        from host.link import ChainLink, LinkError
        import serial.serialposix, termios, fcntl, pwd, grp
        os.setgroups([]); os.setgid(65534); os.setuid(65534)  # imported first: /root is private
        try:
            ChainLink({pty_port!r})
        except LinkError as exc:
            print(exc)
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd="/"
    )
    msg = proc.stdout.strip()
    assert proc.returncode == 0, proc.stderr
    assert "permission denied" in msg and "'nobody'" in msg, msg
    assert "group 'dialout'" in msg and "usermod -aG dialout nobody" in msg, msg


def test_a_port_busy_inside_the_process_that_emulates_it_names_that_process() -> None:
    """Review 2026-11-27: with `ucr demo` (emulator and daemon in one process) `ucr doctor` on
    its chain port said "another process holds it, not one this user can see"; the holder is
    visible: it is the emulating process itself."""
    from host.serialport import _busy

    script = textwrap.dedent(
        """
        import fcntl, os, sys, termios
        master, slave = os.openpty()  # the emulated device and, in the same process, its user
        user = os.open(os.ttyname(slave), os.O_RDWR | os.O_NOCTTY)
        fcntl.ioctl(user, termios.TIOCEXCL)  # held exclusively, as pyserial's exclusive=True
        print(os.ttyname(slave), flush=True)
        sys.stdin.read()
        """
    )
    demo = subprocess.Popen(
        [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        path = demo.stdout.readline().strip()
        msg = _busy(path)
        assert f"held inside PID {demo.pid} (" in msg and "not one this user can see" not in msg
        assert holders(path) == []  # still not a competitor
    finally:
        demo.stdin.close()
        demo.wait(timeout=30)
