"""Bounds that say what they mean for infinity (issue 12 audit, left-overs of its CLI finding):
an infinite value passes "> 0", so the messages that refuse it say "a finite number"."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest

from host import doctor
from host.doctor_checks import Finding
from host.limits import ConfigError, bendable_limits
from tools.cli import main
from tools.segment_config import SegmentConfigError, config_for
from ucrdf.parser import load

ROBOT = Path(__file__).resolve().parent.parent / "robots" / "softrobot3.ucrdf"


def test_an_infinite_kappa_max_of_a_robot_built_in_code_says_finite() -> None:
    robot = load(ROBOT)
    b = robot.bendables["segment_1"]
    b.model.limits.kappa_max = math.inf
    with pytest.raises(ConfigError, match=r"must be a finite number > 0, got inf"):
        bendable_limits(robot)


def test_an_infinite_spool_radius_says_finite() -> None:
    robot = load(ROBOT)
    act = robot.bendables["segment_1"].actuation
    robot.bendables["segment_1"].actuation = dataclasses.replace(act, spool_radius=math.inf)
    with pytest.raises(SegmentConfigError, match=r"spool radius must be a finite number of m > 0"):
        config_for(robot, "segment_1")


def test_an_infinite_cpu_factor_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["emulate", "1", "--cpu-factor", "inf"]) != 0
    assert "--cpu-factor must be a finite number >= 1, got inf" in capsys.readouterr().err


def test_doctor_json_counts_positions_from_one_like_its_text(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    found = [Finding("firmware", "ok", "firmware 0.1.0", position=0), Finding("port", "ok", "ok")]
    monkeypatch.setattr(doctor, "run", lambda *a, **k: found)
    args = type("A", (), {"port": "x", "baud": 921600, "robot": None, "seconds": 0, "json": 1})
    assert doctor.cmd_doctor(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert [f["position"] for f in out] == [1, None]
    assert doctor.format_text(found).splitlines()[0].startswith("[ok  ] position 1 ")


def test_the_calibration_audit_names_positions_from_one(caplog: pytest.LogCaptureFixture) -> None:
    """`ucr calibrate`'s audit lines said "segment 0" for the first segment."""
    import logging
    import threading

    from host.calibrate import Session

    class Link:
        def hold(self, position: int) -> None:
            pass

    s = Session.__new__(Session)  # (its constructor reads the calibration over the link)
    s.link, s.position, s.uid, s._stop = Link(), 0, "24a1600c3b5e", threading.Event()
    with caplog.at_level(logging.INFO, logger="ucr.audit"):
        s.stop()
    assert "HOLD segment at position 1 (" in caplog.text, caplog.text
