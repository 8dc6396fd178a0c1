"""Review of ``ucr calibrate`` and ``ucr doctor`` (ten defects): each test says what happened
before its fix. No emulator: recording stand-ins for the session and the link, a pty for a
segment's REPL port."""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import tempfile
import threading
from pathlib import Path

import pytest

import host.calibrate_cli as cli
import host.calibrate_robot as calibrate_robot
from host import doctor
from host.calibrate import CalibrationError
from host.doctor_base import P_FAULT, P_FAULT_COUNT
from host.doctor_checks import check_segment, check_timing
from host.link import LinkError
from host.link_frames import ProtocolVersionError
from tests.commissioning.test_calibrate_checks import FakeLink, FakeSession, _run
from tools.cli import main as ucr
from tools.mpvm import REPO
from ucrdf.parser import load

ROBOT = REPO / "robots" / "softrobot2.ucrdf"


def _robot(tmp_path: Path) -> Path:
    robot = tmp_path / "robot.ucrdf"
    shutil.copy(ROBOT, robot)
    return robot


def _one_line(err: str) -> bool:
    return err.count("\n") == 1 and err.startswith("ucr calibrate: ") and "Traceback" not in err


def _usage(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str]:
    try:
        rc = ucr(list(argv))
    except SystemExit as exc:  # argparse's own usage errors
        rc = exc.code
    return rc, capsys.readouterr().err


# -- 1. a robot file that cannot be written -------------------------------------------------------
@pytest.mark.parametrize("denied", ["directory", "file"])
def test_a_robot_file_that_cannot_be_written_is_refused_before_anything_moves(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    denied: str,
) -> None:
    """Before: check() only read the file, so the script ran and the segment stored the
    calibration; the file's PermissionError came only at persist (here, as root, the read-only
    file was even replaced). The permission is simulated: the tests run as root."""
    robot = _robot(tmp_path)
    before = robot.read_text()
    refused = robot.parent if denied == "directory" else robot
    real_access = os.access

    def access(path: object, mode: int, *a: object, **k: object) -> bool:
        if Path(str(path)) == refused and mode & os.W_OK:
            return False
        return real_access(path, mode, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(os, "access", access)
    session = FakeSession(name="segment_1")
    rc, _, link = _run(monkeypatch, tmp_path, "identify\npersist\n", session, robot)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert str(robot) in err and "not writable" in err and "(nothing moved)" in err
    assert session.calls == []  # neither moved nor stored on the segment
    assert robot.read_text() == before and link.closed


def test_a_robot_file_the_system_refuses_at_persist_is_one_line_exit_1(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: the PermissionError of tempfile.mkstemp at persist was caught by nothing in
    run_script: a traceback, after the segment had stored the calibration."""
    robot = _robot(tmp_path)

    def refuse(*a: object, **k: object) -> tuple[int, str]:
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    session = FakeSession(name="segment_1")
    rc, _, _ = _run(monkeypatch, tmp_path, "identify\npersist\n", session, robot)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert "Permission denied" in err and f"stored on the segment but not in {robot}" in err


# -- 2. --script writes the robot file at the persist step ----------------------------------------
class FailsAfterPersist(FakeSession):
    def move(self, kappa: float, phi: float) -> dict:
        if ("persist",) in self.calls:
            raise CalibrationError("the segment did not settle")
        return super().move(kappa, phi)


def test_the_script_writes_the_robot_file_at_the_persist_step(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: the file was written only when the whole script ended, so a step failing after
    `persist` left the segment calibrated and the file not (the terminal UI writes at persist)."""
    robot = _robot(tmp_path)
    session = FailsAfterPersist(name="segment_1")
    session.zeros = [0.1, -0.2, 0.05]
    rc, path, _ = _run(monkeypatch, tmp_path, "identify\npersist\nbend 1 0\n", session, robot)
    out, err = capsys.readouterr()
    assert rc == 1 and f"{path}:3: bend" in err, err
    assert 'zero_offset="-0.2000"' in robot.read_text()
    assert f"persist: written to {robot}" in out


# -- 3. calibrate listens before its first frame, as doctor does ----------------------------------
def _pty(answer: bytes | None) -> tuple[int, int, bytearray]:
    """(master, slave, bytes received): a fake REPL answering a carriage return with ``answer``
    (None: silent, as a running firmware's REPL is)."""
    master, slave = os.openpty()
    got = bytearray()

    def repl() -> None:
        while True:
            try:
                data = os.read(master, 256)
            except OSError:
                return
            got.extend(data)
            if answer is not None and b"\r" in data:
                os.write(master, answer)

    threading.Thread(target=repl, daemon=True).start()
    return master, slave, got


@pytest.mark.parametrize(
    "answer, words",
    [(b"\r\n>>> ", "is a segment's REPL port"), (None, "the port is silent")],
)
def test_calibrate_sends_no_frame_to_a_segments_repl_port(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], answer: bytes | None, words: str
) -> None:
    """Before: calibrate sent DISCOVER at once (its bytes hold Ctrl-C and Ctrl-D, which stop or
    reset a segment's firmware on its REPL port), then said `unknown segment ... no segment
    answers`."""
    master, slave, got = _pty(answer)
    script = tmp_path / "cal.txt"
    script.write_text("identify\n")
    args = argparse.Namespace(
        script=str(script), robot=None, segment="segment_1", port=os.ttyname(slave), baud=921600
    )
    try:
        rc = cli.cmd_calibrate(args)
    finally:
        os.close(slave)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert words in err and "alibrate sends no" in err  # `nothing more here` / `no frame`
    assert "unknown segment" not in err
    assert bytes(got) == b"\r"  # a carriage return, nothing that stops or resets a board
    os.close(master)


# -- 4. the port failing during doctor's timing check ---------------------------------------------
def test_the_port_failing_during_the_timing_check_is_a_finding() -> None:
    """Before: link.heartbeat's LinkError in check_timing was not caught: a traceback that lost
    the findings, where every other check makes it a finding."""

    class Unplugged:
        def heartbeat(self, timeout: float, expected: int) -> list:
            raise LinkError("/dev/ttyUSB0: device disconnected")

    found = check_timing(Unplugged(), 1, 1.0)
    assert found.level == "error" and found.check == "timing"
    assert "device disconnected" in found.message and "adapter" in found.fix


# -- 5. the terminal UI's return code and a failed persist ----------------------------------------
def test_a_hold_the_failed_port_cannot_send_ends_the_ui_with_code_1_not_a_crash() -> None:
    """Before: session.stop() raising LinkError in the q action was an unhandled exception
    (textual: return code 1 and a traceback; here its pilot re-raised it)."""
    pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")
    from host.calibrate_tui import CalibrateApp

    class Broken:
        position, n, zeros, dirs, stopped = 0, 3, [0.0, 0.0, 0.0], [1, 1, 1], False

        def stop(self) -> None:
            raise LinkError("/dev/ttyUSB0: device disconnected")

        def __getattr__(self, name: str) -> object:
            return lambda *a, **k: None

    app = CalibrateApp(Broken())  # type: ignore[arg-type]

    async def drive() -> None:
        async with app.run_test() as pilot:
            await pilot.pause(0.2)
            await pilot.press("space")
            await pilot.pause(0.2)
            await pilot.press("q")
            await pilot.pause(0.3)

    asyncio.run(drive())
    assert app.return_code == 1
    assert app.error is not None and "HOLD not sent" in app.error
    assert any("device disconnected" in line for line in app.lines)


def test_a_failed_persist_in_the_ui_is_kept_for_the_exit() -> None:
    """Before: a persist whose robot file write failed was said only in the UI's log, gone when
    it closed (the app kept no record of it)."""
    pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")
    from host.calibrate_robot import RobotFileError
    from host.calibrate_tui import CalibrateApp

    session = FakeSession(name="segment_1")
    session.position, session.n, session.uid, session.stopped = 0, 3, "abc", False
    session.resume = lambda: None  # type: ignore[attr-defined]

    def refuse(result: object) -> None:
        raise RobotFileError("robot.ucrdf: cannot write the robot file: No space left on device")

    app = CalibrateApp(session, on_persist=refuse)  # type: ignore[arg-type]

    async def drive() -> None:
        async with app.run_test() as pilot:
            await pilot.press("p")
            await pilot.pause(0.5)
            while app.busy:
                await pilot.pause(0.1)
            await pilot.press("q")
            await pilot.pause(0.3)

    asyncio.run(drive())
    assert app.persist_error is not None and "No space left" in app.persist_error
    assert app.return_code == 0  # the UI itself ended well: the CLI turns the error into exit 1


@pytest.mark.parametrize(
    "code, persist_error, error, rc, words",
    [
        (1, None, None, 1, "the terminal UI stopped on an error (code 1)"),
        (1, None, "HOLD not sent (gone); its watchdog holds it", 1, "HOLD not sent (gone)"),
        (0, "robot.ucrdf: cannot write the robot file: No space", None, 1, "persist failed: "),
    ],
)
def test_run_tui_exits_1_after_a_crash_or_a_failed_persist(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    code: int,
    persist_error: str | None,
    error: str | None,
    rc: int,
    words: str,
) -> None:
    """Before: run_tui returned 0 unless the app's return code was 130 (textual's 1 after an
    unhandled exception was a success), and said nothing of a failed persist."""
    pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")
    import host.calibrate_tui as tui

    class Ran:  # an app that ended like that
        def __init__(self, *a: object, **k: object) -> None:
            self.return_code = code
            self.persist_error = persist_error
            self.error = error

        def run(self) -> None:
            pass

    link = FakeLink()
    monkeypatch.setattr(cli, "open_session", lambda args, say=print: (link, FakeSession()))
    monkeypatch.setattr(tui, "CalibrateApp", Ran)
    args = argparse.Namespace(robot=None, segment="segment_1", port="x", baud=9600, script=None)
    assert cli.cmd_calibrate(args) == rc
    err = capsys.readouterr().err
    assert _one_line(err) and words in err, err
    assert link.closed


# -- 6. files that are not UTF-8 ------------------------------------------------------------------
def test_a_script_that_is_not_utf8_is_one_line_exit_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: UnicodeDecodeError (a traceback) from Path.read_text in calibrate_script.load."""
    script = tmp_path / "cal.txt"
    script.write_bytes(b"\xffidentify\n")
    args = argparse.Namespace(
        script=str(script), robot=None, segment="segment_1", port="x", baud=921600
    )
    rc = cli.cmd_calibrate(args)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert f"{script}: cannot read the script: not UTF-8 text (byte 0xff at offset 0)" in err


def test_a_robot_file_that_is_not_utf8_is_one_line_exit_1(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: UnicodeDecodeError (a traceback) from Path.read_text in calibrate_robot.check."""
    robot = tmp_path / "robot.ucrdf"
    robot.write_bytes(b"<robot>\xe9</robot>")
    session = FakeSession(name="segment_1")
    rc, _, _ = _run(monkeypatch, tmp_path, "identify\npersist\n", session, robot)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert "not UTF-8 text (byte 0xe9 at offset 7)" in err and session.calls == []
    with pytest.raises(calibrate_robot.RobotFileError, match="not UTF-8"):
        calibrate_robot.write(robot, "segment_1", [0.0] * 3, [1] * 3)


# -- 7. an empty --robot (an unset variable) ------------------------------------------------------
@pytest.mark.parametrize(
    "argv",
    [
        ["doctor", "--port", "/nonexistent/ttyUSB9", "--seconds", "0", "--robot", ""],
        ["calibrate", "--port", "/nonexistent/ttyUSB9", "--segment", "1", "--robot", ""],
        ["calibrate", "--port", "/nonexistent/ttyUSB9", "--segment", "1", "--script", ""],
    ],
)
def test_an_empty_path_is_a_usage_error_naming_it(
    capsys: pytest.CaptureFixture[str], argv: list[str]
) -> None:
    """Before: `--robot ""` was taken for no --robot (doctor then checked the chain without the
    robot and exited 1 here; calibrate would have calibrated without writing the file)."""
    rc, err = _usage(capsys, *argv)
    assert rc == 2, err
    assert f"argument {argv[-2]}: empty path ''" in err and "Traceback" not in err


# -- 8. --baud bounds -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "command, baud, words",
    [
        ("calibrate", "0", "must be >= 1"),
        ("calibrate", "-1", "must be >= 1"),
        ("calibrate", str(2**31), "must be <= 10000000 bit/s"),
        ("doctor", str(2**31), "must be <= 10000000 bit/s"),
    ],
)
def test_an_impossible_baud_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], command: str, baud: str, words: str
) -> None:
    """Before: calibrate took any int (0 is termios B0, the line hung up; -1 exited 1) and
    neither bounded it above (2**31: OverflowError in pyserial, a traceback)."""
    argv = [command, "--port", "/nonexistent/ttyUSB9", "--baud", baud]
    if command == "calibrate":
        argv += ["--segment", "1"]
    rc, err = _usage(capsys, *argv)
    assert rc == 2, err
    assert f"argument --baud: {words}" in err and "Traceback" not in err


# -- 9. a DISCOVER that fails says why ------------------------------------------------------------
@pytest.mark.parametrize(
    "failure, words",
    [
        (ProtocolVersionError(1, "9"), "speaks protocol version 9"),
        (LinkError("incomplete discovery: answers from position 1, 3"), "incomplete discovery"),
    ],
)
def test_a_failed_discovery_is_reported_as_itself_not_as_an_unknown_segment(
    monkeypatch: pytest.MonkeyPatch,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    failure: LinkError,
    words: str,
) -> None:
    """Before: `except LinkError: descs = []` turned both into `unknown segment 'segment_1': no
    segment answers`, pointing at the segment name instead of a reflash or the cable."""
    import host.link

    class Answering(FakeLink):
        def __init__(self, *a: object) -> None:
            super().__init__()

        def discover(self, timeout: float = 0.5) -> list[dict]:
            raise failure

    monkeypatch.setattr(host.link, "ChainLink", Answering)
    monkeypatch.setattr(cli, "listen", lambda *a, **k: None, raising=False)
    script = tmp_path / "cal.txt"
    script.write_text("identify\n")
    args = argparse.Namespace(
        script=str(script), robot=None, segment="segment_1", port="x", baud=921600
    )
    rc = cli.cmd_calibrate(args)
    err = capsys.readouterr().err
    assert rc == 1 and _one_line(err), err
    assert words in err and "unknown segment" not in err
    if isinstance(failure, ProtocolVersionError):
        assert doctor.PROTOCOL_FIX in err  # doctor's fix, word for word


# -- 10. the FAULT finding's fix, and the documentation's stale-flash line ------------------------
def test_the_fault_fix_can_be_followed_with_the_daemon_stopped() -> None:
    """Before: `remove the cause, then ucr clear-fault`, which needs the running daemon, while
    doctor needs it stopped: the fix now says to start the daemon first, or power-cycle."""

    class Faulted:
        def param_get(self, pos: int, pid: int, uid: object, timeout: float) -> object:
            return {P_FAULT: 3, P_FAULT_COUNT: 1}.get(pid, 0)

    (fault,) = [f for f in check_segment(Faulted(), 0, {"uid": "aa"}) if f.check == "fault"]
    assert fault.level == "error"
    assert "start the daemon" in fault.fix and "ucr clear-fault" in fault.fix
    assert "power-cycle" in fault.fix


def test_the_documented_stale_flash_finding_is_what_doctor_prints() -> None:
    """Before: docs/commissioning.md showed `position 2 robot: position 1 (segment_2)`, which
    doctor cannot print (both labels count from 1: `position 2 (segment_2)`)."""
    from host.doctor_config import check_robot
    from host.topology import chain_bendables

    path = REPO / "robots" / "softrobot3.ucrdf"
    robot = load(path)
    descs = []
    for pos, name in enumerate(chain_bendables(robot)):
        b = robot.bendables[name]
        length = 0.474 if name == "segment_2" else b.length
        descs.append({"position": pos, "name": name, "model": b.model.type, "length": length})
    (line,) = [  # its first line (the fix follows on the next)
        doctor.format_finding(f).splitlines()[0]
        for f in check_robot(str(path), descs)
        if "length" in f.message
    ]
    doc = (REPO / "docs" / "commissioning.md").read_text(encoding="utf-8")
    assert f"`{line}`" in doc, line
