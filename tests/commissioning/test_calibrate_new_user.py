"""New-user audit of ``ucr calibrate``: every error of a script at once (each FILE:LINE, the
lines against the segment too), an unknown --segment refused as ``ucr move`` refuses one, and
Ctrl-C exits 130 with one line wherever it comes."""

from __future__ import annotations

import argparse
import asyncio
from pathlib import Path

import pytest

import host.calibrate_cli as cli
from host.calibrate_cli import find_segment
from host.calibrate_script import ScriptError, parse
from tests.commissioning.test_calibrate_checks import FakeLink, FakeSession, _run

DESCS = [
    {"position": 0, "name": "segment_1", "uid": "aa01"},
    {"position": 1, "name": "segment_2", "uid": "bb02"},
]

BROKEN = """identify
jump 3
jog 1 0.9
wait 99
bend 20 90
tension 0.9 5
jog 7 0.1
persist
"""


def test_the_whole_file_check_reports_every_error_with_its_line() -> None:
    with pytest.raises(ScriptError) as info:
        parse(BROKEN, "cal.txt")
    lines = str(info.value).splitlines()
    assert [ln.split(": ", 1)[0] for ln in lines] == [
        "cal.txt:2",
        "cal.txt:3",
        "cal.txt:4",
        "cal.txt:6",
        "cal.txt:6",
    ], lines
    assert "unknown command 'jump'" in lines[0] and "jog at most 0.5 rad" in lines[1]
    assert "LOAD 0.9" in lines[3] and "STEP 5 rad" in lines[4]
    # the well-formed lines are kept, for the checks against the segment
    assert [st.line for st in info.value.steps] == [1, 5, 7, 8]


def test_the_cli_reports_file_and_segment_errors_together_before_anything_moves(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    session = FakeSession()
    session.desc["tendon_angles"] = [0.0, 2.1, 4.2]  # three servos: 0..2
    rc, path, link = _run(monkeypatch, tmp_path, BROKEN, session)
    err = capsys.readouterr().err
    assert rc == 1 and session.calls == [] and link.closed
    for line, words in (
        (2, "unknown command"),
        (3, "jog at most 0.5"),
        (4, "wait 0..60 s"),
        (5, "beyond the segment's kappa_max 8.73"),
        (6, "LOAD 0.9"),
        (7, "servo 7: the segment has servos 0..2"),
    ):
        assert any(f"{path}:{line}:" in ln and words in ln for ln in err.splitlines()), err
    numbers = [
        int(ln.split(f"{path}:")[1].split(":")[0]) for ln in err.splitlines() if f"{path}:" in ln
    ]
    assert numbers == sorted(numbers)  # in file order
    assert f"7 problem(s) in {path} (nothing moved)" in err


def test_an_unknown_segment_is_refused_as_ucr_move_refuses_it() -> None:
    with pytest.raises(ValueError) as info:
        find_segment(DESCS, "segment_9")
    message = str(info.value)
    assert message.startswith("unknown segment 'segment_9': "), message
    assert "position 1: segment_1 (aa01)" in message and "position 2: segment_2 (bb02)" in message
    assert "a chain position counted from 1" in message
    with pytest.raises(ValueError, match=r"unknown segment '0' \(positions count from 1\)"):
        find_segment(DESCS, "0")


def test_a_non_ascii_digit_is_an_unknown_segment_not_a_crash() -> None:
    with pytest.raises(ValueError) as info:
        find_segment(DESCS, "²")  # str.isdigit says yes, int() refuses it
    assert str(info.value).startswith("unknown segment '²'")


def test_ctrl_c_while_the_chain_is_searched_exits_130_with_one_line(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def interrupted(args: argparse.Namespace, say: object = print) -> tuple:
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "open_session", interrupted)
    script = tmp_path / "cal.txt"
    script.write_text("straight\n")
    base = {"robot": None, "segment": "segment_1", "port": "x", "baud": 921600}
    for extra in ({"script": str(script)}, {"script": None}):  # script, and the terminal UI
        if extra["script"] is None:
            pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")
        try:
            rc = cli.cmd_calibrate(argparse.Namespace(**base, **extra))
        except KeyboardInterrupt:
            pytest.fail("Ctrl-C escaped `ucr calibrate` (the dispatcher says nothing)")
        err = capsys.readouterr().err
        assert rc == 130
        assert err.count("\n") == 1 and "stopped (Ctrl-C)" in err and "Traceback" not in err


def test_ctrl_c_in_the_terminal_ui_exits_130_and_holds(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("textual", reason="the 'tui' extra (textual) is not installed")
    import host.calibrate_tui as tui

    stops: list[int] = []

    class Stub:  # a session: the UI only shows it; stop() is what Ctrl-C must call
        position, n, zeros, dirs, stopped = 0, 3, [0.0, 0.0, 0.0], [1, 1, 1], False

        def stop(self) -> None:
            stops.append(1)

        def __getattr__(self, name: str) -> object:
            return lambda *a, **k: None

    session = Stub()
    app = tui.CalibrateApp(session)  # type: ignore[arg-type]

    async def drive() -> None:
        async with app.run_test() as pilot:
            await pilot.pause(0.2)
            await pilot.press("ctrl+c")
            await pilot.pause(0.3)

    asyncio.run(drive())
    assert stops and app.return_code == 130

    class Ran:  # run_tui with an app that ended like that one
        def __init__(self, *a: object, **k: object) -> None:
            self.return_code = app.return_code
            self.persist_error = app.persist_error
            self.error = app.error

        def run(self) -> None:
            pass

    link = FakeLink()
    monkeypatch.setattr(cli, "open_session", lambda args, say=print: (link, session))
    monkeypatch.setattr(tui, "CalibrateApp", Ran)
    args = argparse.Namespace(robot=None, segment="segment_1", port="x", baud=9600, script=None)
    assert cli.cmd_calibrate(args) == 130
    assert capsys.readouterr().err == "ucr calibrate: stopped (Ctrl-C): the segment holds\n"
    assert link.closed
