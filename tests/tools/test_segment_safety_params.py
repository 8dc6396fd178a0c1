"""The segments' safety settings from the U(C)RDF: ``hw_watchdog_ms`` (the board's hardware
watchdog) and ``fault_action`` (hold or release the servos in FAULT) were config.json keys the
firmware honoured but nothing could set: a user had to hand-edit each flashed segment. Now they are
``SoftRobotInterface`` hardware params that ``ucr check`` checks with ``path:line`` as the firmware
would, and that ``ucr flash`` writes into config.json."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from tests.cli_run import run_ucr
from tools.segment_config import SegmentConfigError, config_for
from ucrdf.checks import firmware_refusal
from ucrdf.parser import load

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"
ANCHOR = '<param name="watchdog_ms">200</param>'


def _robot(tmp_path: Path, extra: str) -> Path:
    text = ROBOT.read_text()
    assert ANCHOR in text
    path = tmp_path / "r.ucrdf"
    path.write_text(text.replace(ANCHOR, ANCHOR + extra))
    return path


def _check(path: Path) -> subprocess.CompletedProcess[str]:
    return run_ucr("check", str(path), timeout=60)


def test_the_safety_params_reach_config_json_and_the_firmware_runs_them(tmp_path) -> None:
    path = _robot(
        tmp_path,
        '<param name="hw_watchdog_ms">100</param><param name="fault_action">release</param>',
    )
    assert _check(path).returncode == 0
    cfg = config_for(load(path), "segment_2")
    assert cfg["hw_watchdog_ms"] == 100 and cfg["fault_action"] == "release"
    assert firmware_refusal(cfg) is None


def test_without_them_config_json_is_as_flashed_before(tmp_path) -> None:
    cfg = config_for(load(ROBOT), "segment_2")
    assert "hw_watchdog_ms" not in cfg and "fault_action" not in cfg


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        ('<param name="hw_watchdog_ms">10</param>', "must be 0 (off) or 50..60000 ms"),
        ('<param name="hw_watchdog_ms">60.5</param>', "not a whole number of ms"),
        (
            '<param name="tick_ms">20</param><param name="hw_watchdog_ms">60</param>',
            "hw_watchdog_ms 60 is shorter than four ticks (tick_ms 20)",
        ),
        ('<param name="fault_action">relax</param>', "fault_action must be one of hold, release"),
    ],
    ids=["too-short", "fraction", "under-four-ticks", "unknown-action"],
)
def test_what_the_firmware_would_refuse_is_a_check_error_at_its_line(
    tmp_path, extra, message
) -> None:
    path = _robot(tmp_path, extra)
    result = _check(path)
    assert result.returncode == 1, result.stdout
    line = (
        ROBOT.read_text()
        .splitlines()
        .index(next(x for x in ROBOT.read_text().splitlines() if ANCHOR in x))
        + 1
    )
    assert f"{path}:{line}:" in result.stderr and message in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
    with pytest.raises(SegmentConfigError):  # ucr flash refuses it too
        config_for(load(path, check=False), "segment_2")


def test_a_hardware_watchdog_too_short_for_a_calibration_store_is_a_check_warning(
    tmp_path,
) -> None:
    """docs/firmware.md: storing a calibration takes an estimated 150-390 ms on an ESP32 plus the
    flash erase, so a hw_watchdog_ms under 1000 may reset the segment mid-store. `ucr check`
    accepted 100 without a word; now it warns at the param's line (exit code still 0)."""
    lines = ROBOT.read_text().splitlines()
    line = lines.index(next(x for x in lines if ANCHOR in x)) + 1
    short = _check(_robot(tmp_path, '<param name="hw_watchdog_ms">100</param>'))
    assert short.returncode == 0, short.stderr
    assert f"r.ucrdf:{line}: warning: hardware param hw_watchdog_ms 100 is below 1000 ms" in (
        short.stderr
    )
    for extra in ('<param name="hw_watchdog_ms">2000</param>', ""):
        fine = _check(_robot(tmp_path, extra))
        assert fine.returncode == 0 and "hw_watchdog_ms" not in fine.stderr, fine.stderr
