"""``ucr calibrate --script``: the script and the robot file are checked against the segment
before anything moves or is stored (no emulator: a recording stand-in for the session)."""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import pytest

import host.calibrate_cli as cli
from host.calibrate_script import ScriptError, parse
from tools.mpvm import REPO

KAPPA_MAX = 8.73


class FakeLink:
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


class FakeSession:
    """Records every step that would move the segment or store a calibration."""

    def __init__(self, name: str = "segment_1", measured: float | None = None) -> None:
        self.desc = {"name": name, "kappa_max": KAPPA_MAX, "uid": "abc"}
        self.zeros = [0.0, 0.0, 0.0]
        self.dirs = [1, 1, 1]
        self.calls: list[tuple] = []
        self.said: list[str] = []
        self.measured = measured

    def say(self, text: str) -> None:
        self.said.append(text)

    def move(self, kappa: float, phi: float) -> dict:
        self.calls.append(("move", kappa, phi))
        got = self.measured if self.measured is not None else kappa
        return {"kappa": got, "phi": phi}

    def identify(self, *a) -> None:
        self.calls.append(("identify", *a))

    def check_directions(self, *a) -> list[int]:
        self.calls.append(("check_directions", *a))
        return []

    def tension(self, *a) -> None:
        self.calls.append(("tension", *a))

    def keep(self, *a) -> None:
        self.calls.append(("keep", *a))

    def persist(self):
        from host.calibrate import Result

        self.calls.append(("persist",))
        return Result(list(self.zeros), list(self.dirs))

    def stop(self) -> None:
        pass


def _run(monkeypatch, tmp_path: Path, script: str, session: FakeSession, robot: Path | None = None):
    link = FakeLink()
    monkeypatch.setattr(cli, "open_session", lambda args, say=print: (link, session))
    path = tmp_path / "cal.txt"
    path.write_text(script)
    args = argparse.Namespace(
        script=str(path),
        robot=str(robot) if robot else None,
        segment="segment_1",
        port="x",
        baud=921600,
    )
    return cli.cmd_calibrate(args), path, link


@pytest.mark.parametrize(
    "script, line, words",
    [
        ("straight\nbend 20 90\n", 2, "beyond the segment's kappa_max 8.73"),
        ("identify\ncheck-directions 50\n", 2, "beyond the segment's kappa_max 8.73"),
        ("identify 0.4\nidentify 9\n", 2, "beyond the segment's kappa_max"),
    ],
)
def test_a_curvature_beyond_kappa_max_is_refused_before_anything_moves(
    monkeypatch, tmp_path, capsys, script, line, words
) -> None:
    session = FakeSession()
    rc, path, link = _run(monkeypatch, tmp_path, script, session)
    err = capsys.readouterr().err
    assert rc == 1
    assert f"{path}:{line}:" in err and words in err
    assert session.calls == []  # nothing moved
    assert link.closed


@pytest.mark.parametrize(
    "text, words",
    [
        ("straight\nbend -2 90\n", "kappa -2 1/m is negative"),
        ("straight\ncheck-directions -0.4\n", "is negative"),
        ("identify\ntension 0.05 5\n", "tension STEP 5 rad must be in (0, 0.1]"),
        ("identify\ntension 0.05 0\n", "tension STEP 0 rad"),
        ("identify\ntension 0.9\n", "tension LOAD 0.9 must be in (0, 0.8)"),
    ],
)
def test_steps_beyond_the_documented_bounds_are_refused_by_the_whole_file_check(
    text, words
) -> None:
    with pytest.raises(ScriptError) as exc:
        parse(text, "cal.txt")
    assert str(exc.value).startswith("cal.txt:2:")
    assert words in str(exc.value)


def test_the_bend_report_shows_the_curvature_reached_not_the_request(
    monkeypatch, tmp_path, capsys
) -> None:
    session = FakeSession(measured=7.5)  # e.g. a servo range stopped it short
    rc, _, _ = _run(monkeypatch, tmp_path, "bend 8 90\n", session)
    assert rc == 0
    said = " ".join(session.said)
    assert "kappa 7.500 1/m" in said and "measured" in said
    assert "asked 8.000" in said


def test_a_robot_file_without_the_segment_is_refused_before_anything_moves_or_persists(
    monkeypatch, tmp_path, capsys
) -> None:
    robot = tmp_path / "robot.ucrdf"
    shutil.copy(REPO / "robots" / "softrobot2.ucrdf", robot)
    before = robot.read_text()
    session = FakeSession(name="seg3")  # the chain's segment is not in this file
    rc, _, link = _run(monkeypatch, tmp_path, "identify\npersist\n", session, robot)
    err = capsys.readouterr().err
    assert rc == 1
    assert "no <bendable name='seg3'>" in err
    assert session.calls == []  # neither moved nor stored on the segment
    assert robot.read_text() == before
    assert link.closed


def test_a_robot_file_whose_bendable_lacks_servos_is_refused_up_front(
    monkeypatch, tmp_path, capsys
) -> None:
    robot = tmp_path / "robot.ucrdf"
    text = (REPO / "robots" / "softrobot2.ucrdf").read_text()
    start = text.index('<servo index="0" id="1"')
    end = text.index("</actuation>", start)
    robot.write_text(text[:start] + text[end:])
    session = FakeSession(name="segment_1")
    rc, _, _ = _run(monkeypatch, tmp_path, "identify\npersist\n", session, robot)
    assert rc == 1
    assert "has no <servo index=" in capsys.readouterr().err
    assert session.calls == []


def test_a_good_robot_file_lets_the_script_run_and_takes_the_result(
    monkeypatch, tmp_path, capsys
) -> None:
    robot = tmp_path / "robot.ucrdf"
    shutil.copy(REPO / "robots" / "softrobot2.ucrdf", robot)
    session = FakeSession(name="segment_1")
    session.zeros = [0.1, -0.2, 0.05]
    rc, _, _ = _run(monkeypatch, tmp_path, "identify 0.4\nbend 1 0\npersist\n", session, robot)
    assert rc == 0, capsys.readouterr().err
    assert [c[0] for c in session.calls] == ["identify", "move", "persist"]
    assert 'zero_offset="-0.2000"' in robot.read_text()
