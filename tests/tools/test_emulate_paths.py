"""``ucr emulate`` with a --workdir or --control-socket that cannot work: one line, exit 2, before
any segment starts (was: a traceback, some after the segments started); another emulator's live
control socket is never taken over, a file that is not a socket never deleted."""

from __future__ import annotations

import socket
import subprocess

import pytest

from tests.cli_run import run_ucr
from tools.emulator import EmulatorError
from tools.emulator.control import ControlSocket


def _emulate(*argv: str) -> subprocess.CompletedProcess[str]:
    # (timeout: the old code started the chain and ran until stopped)
    return run_ucr("emulate", *argv, "--no-stdin", timeout=30)


def _refused(proc: subprocess.CompletedProcess[str], why: str) -> None:
    assert proc.returncode == 2 and "Traceback" not in proc.stderr, proc.stderr
    assert proc.stderr.strip().splitlines() == [f"ucr: error: {why}"]
    assert "host port" not in proc.stdout  # nothing started


def test_a_workdir_that_cannot_be_created_is_one_line(tmp_path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("mine")
    _refused(_emulate("1", "--workdir", "/proc/x"),
             "--workdir /proc/x: cannot create it (No such file or directory)")  # fmt: skip
    _refused(_emulate("1", "--workdir", str(afile)),
             f"--workdir {afile}: exists and is not a directory")  # fmt: skip
    _refused(_emulate("1", "--workdir", str(afile / "sub")),
             f"--workdir {afile / 'sub'}: cannot create it (Not a directory)")  # fmt: skip
    assert afile.read_text() == "mine"


def test_a_control_socket_in_a_missing_directory_is_refused_before_starting() -> None:
    _refused(_emulate("2", "--control-socket", "/nonexist/ctl.sock"),
             "--control-socket /nonexist/ctl.sock: no such directory /nonexist")  # fmt: skip


def test_a_regular_file_is_not_taken_as_a_control_socket(tmp_path) -> None:
    afile = tmp_path / "notes.txt"
    afile.write_text("mine")
    _refused(_emulate("1", "--control-socket", str(afile)),
             f"--control-socket {afile} exists and is not a socket (not replaced): "
             "choose another path")  # fmt: skip
    assert afile.read_text() == "mine"


def test_a_live_control_socket_is_never_taken_over(tmp_path) -> None:
    """Defect: the socket file of a running emulator was unlinked and bound again."""
    path = tmp_path / "ctl.sock"
    with socket.socket(socket.AF_UNIX) as live:
        live.bind(str(path))
        live.listen()
        _refused(_emulate("1", "--control-socket", str(path)),
                 f"--control-socket {path} is the control socket of a running emulator "
                 "(or another program): choose another path")  # fmt: skip
        with socket.socket(socket.AF_UNIX) as client:
            client.connect(str(path))  # still the first listener's
            live.accept()[0].close()


def test_a_stale_control_socket_is_replaced(tmp_path) -> None:
    from tools.emulator.control import socket_path_problem  # (new: the old code had none)

    path = tmp_path / "ctl.sock"
    with socket.socket(socket.AF_UNIX) as dead:  # an emulator killed before removing its file
        dead.bind(str(path))
    assert path.is_socket() and socket_path_problem(path) is None
    control = ControlSocket(None, path)  # type: ignore[arg-type]  # (no command is sent)
    try:
        with socket.socket(socket.AF_UNIX) as client:
            client.connect(str(path))
    finally:
        control.close()
    assert not path.exists()


def test_a_control_socket_path_too_long_is_refused(tmp_path) -> None:
    from tools.emulator.control import socket_path_problem

    path = tmp_path / ("s" * 120)
    assert "too long for a unix socket" in (socket_path_problem(path) or "")
    with pytest.raises(EmulatorError, match="too long for a unix socket"):
        ControlSocket(None, path)  # type: ignore[arg-type]
