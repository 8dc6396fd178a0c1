"""`ucr flash` against an emulated segment's REPL pty: copy, verify, reset, rediscover."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from host.link import ChainLink
from tests.cli_run import run_ucr
from tools.emulator import EmulatedChain
from tools.flash import Flasher, FlashError, flash

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"


def discover_one(link: ChainLink, timeout: float = 15.0) -> dict:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        descs = link.discover(timeout=0.3)
        if descs:
            return descs[0]
        time.sleep(0.1)
    raise AssertionError("segment did not answer DISCOVER")


@pytest.fixture(scope="module")
def one_segment():
    with EmulatedChain(1) as chain:
        link = ChainLink(chain.host_port)
        discover_one(link)
        yield chain, link
        link.close()


def _robot_with_changed_kappa_max(tmp_path: Path, value: float) -> Path:
    text = ROBOT.read_text()
    start = text.index('<bendable name="segment_2">')
    head, tail = text[:start], text[start:]
    tail = re.sub(r'kappa_max="[0-9.]+"', f'kappa_max="{value}"', tail, count=1)
    path = tmp_path / "robot.ucrdf"
    path.write_text(head + tail)
    return path


def test_ucr_flash_installs_the_segments_configuration(one_segment, tmp_path) -> None:
    chain, link = one_segment
    assert discover_one(link)["name"] == "segment"  # firmware defaults before
    robot = _robot_with_changed_kappa_max(tmp_path, 3.5)
    restarts = chain.stats()["segments"][0]["restarts"]
    proc = run_ucr(
        "flash", "--port", chain.repl_port(0), "--robot", str(robot), "--segment", "segment_2"
    )
    assert proc.returncode == 0, proc.stderr
    total = re.search(r"\[\s*1/(\d+)\] \S+", proc.stdout).group(1)
    assert f"[{total}/{total}] main.py" in proc.stdout  # progress per file, main.py last
    assert "verified" in proc.stdout and "config.json" in proc.stdout
    chain.wait_restarts(0, restarts + 1)
    desc = discover_one(link)
    assert desc["name"] == "segment_2"
    assert desc["kappa_max"] == pytest.approx(3.5)
    assert desc["kappa_rate_max"] == pytest.approx(5.0)
    assert desc["tendon_radius"] == pytest.approx(0.06)


def test_flash_precompiled_mpy_boots_and_runs(one_segment) -> None:
    chain, link = one_segment
    restarts = chain.stats()["segments"][0]["restarts"]
    lines: list[str] = []
    config = {"name": "precompiled", "watchdog_ms": 250}
    flash(chain.repl_port(0), config, mpy=True, log=lines.append)
    chain.wait_restarts(0, restarts + 1)
    seg = chain.segment_dir(0)
    assert (seg / "protocol" / "frame.mpy").is_file()
    assert not (seg / "protocol" / "frame.py").exists()
    assert (seg / "main.py").is_file()
    desc = discover_one(link)
    assert desc["name"] == "precompiled" and desc["watchdog_ms"] == 250
    assert any("verified" in line for line in lines)


def test_missing_port_is_a_clear_error(tmp_path) -> None:
    proc = run_ucr(
        "flash", "--port", "/dev/ttyUSB_nope", "--robot", str(ROBOT), "--segment", "segment_1"
    )
    assert proc.returncode == 1  # a failure, not a usage error (2 until 2026-11-28)
    assert "does not exist" in proc.stderr and "Traceback" not in proc.stderr


def test_unknown_segment_is_a_clear_error() -> None:
    proc = run_ucr("flash", "--port", "/dev/null", "--robot", str(ROBOT), "--segment", "nope")
    assert proc.returncode == 1 and "no bendable 'nope'" in proc.stderr


def test_busy_port_is_a_clear_error(one_segment) -> None:
    chain, _ = one_segment
    with serial.Serial(chain.repl_port(0), exclusive=True):
        with pytest.raises(FlashError, match="busy"):
            flash(chain.repl_port(0), {}, log=lambda s: None)


def test_a_device_that_is_not_a_micropython_repl_is_a_clear_error() -> None:
    master, slave = os.openpty()  # a serial device that never answers
    try:
        with pytest.raises(FlashError, match="did not answer like a MicroPython REPL"):
            Flasher(os.ttyname(slave), connect_timeout=1.0, log=lambda s: None)
    finally:
        os.close(master)
        os.close(slave)


def test_mpremote_cli_with_resume_works_on_the_running_firmware(one_segment) -> None:
    chain, link = one_segment
    discover_one(link)
    proc = subprocess.run(
        [
            str(Path(sys.executable).parent / "mpremote"),
            "connect",
            chain.repl_port(0),
            "resume",
            "exec",
            "import sys; print(sys.implementation.name, sys.platform)",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "micropython linux"
    # mpremote left the board at the REPL, firmware stopped: the chain's segment is silent now,
    # as on a real board, until it is reset.
    assert link.discover(timeout=0.3) == []
    chain.restart(0)
    assert discover_one(link)["position"] == 0


def test_plain_mpremote_soft_resets_into_the_raw_repl_like_a_board(one_segment) -> None:
    """mpremote's default soft-resets the board in the raw REPL; a board then stays there without
    running main.py (ports/esp32/main.c), so `mpremote connect PORT fs …` works. The emulator
    used to start main.py again and mpremote waited forever for the raw REPL."""
    chain, link = one_segment
    discover_one(link)
    mpremote = str(Path(sys.executable).parent / "mpremote")
    port = chain.repl_port(0)
    # a session that leaves the REPL in its own terminal mode (ISIG off), then a reboot: the
    # rebooted segment must answer Ctrl-C again, as a board's UART does after every reset
    proc = subprocess.run(
        [mpremote, "connect", port, "resume", "exec", "print(1)"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    chain.restart(0)
    discover_one(link)
    for args in (["exec", "print(6 * 7)"], ["fs", "ls"]):
        proc = subprocess.run(
            [mpremote, "connect", port, *args], capture_output=True, text=True, timeout=30
        )
        assert proc.returncode == 0, proc.stderr
    assert "main.py" in proc.stdout
    # the firmware is not running (a board after a raw-REPL soft reset): the chain is silent
    assert link.discover(timeout=0.3) == []
    chain.restart(0)
    assert discover_one(link)["position"] == 0


def test_a_stored_calibration_is_kept_and_said_or_forgotten_on_request(one_segment) -> None:
    """Review 2026-11-26: a calibration stored by `ucr calibrate` (calibration.json, which wins
    over config.json at boot) survived every reflash without a word, so doctor's advice
    "reflash" never cleared the difference. Now flash says it keeps it, and
    --forget-calibration removes it."""
    import json

    from protocol import cal_core

    chain, link = one_segment
    seg = chain.segment_dir(0)
    stored = {"version": cal_core.CAL_VERSION,
              "servos": [{"zero_offset": 0.0, "direction": 1} for _ in range(3)]}  # fmt: skip
    (seg / "calibration.json").write_text(json.dumps(stored))
    config = {"name": "calibrated"}
    lines: list[str] = []
    flash(chain.repl_port(0), config, log=lines.append)
    assert any("kept the calibration stored on the board" in ln for ln in lines), lines
    assert (seg / "calibration.json").is_file()
    lines.clear()
    flash(chain.repl_port(0), config, log=lines.append, forget_calibration=True)
    assert any("removed the stored calibration" in ln for ln in lines), lines
    assert not (seg / "calibration.json").exists()
    assert discover_one(link)["name"] == "calibrated"


def test_the_documented_by_hand_deploy_keeps_the_flashed_layout(tmp_path: Path) -> None:
    """Review 2026-11-26: docs/firmware.md's by-hand copy (`fs cp -r protocol :protocol`) nested
    the package as protocol/protocol on a board that already had one (mpremote copies *into* an
    existing directory), so a second deploy left the old protocol running. The documented line,
    run twice against a flashed emulated segment, must give one protocol/ with the new files."""
    text = (REPO / "docs" / "firmware.md").read_text()
    (line,) = [ln.strip() for ln in text.splitlines() if ln.strip().startswith("mpremote connect")]
    (tmp_path / "config.json").write_text('{"name": "by_hand"}')
    for name in ("device", "protocol"):
        (tmp_path / name).symlink_to(REPO / name)
    mpremote = str(Path(sys.executable).parent / "mpremote")
    with EmulatedChain(1) as chain:
        link = ChainLink(chain.host_port)
        try:
            discover_one(link)
            cmd = line.replace("/dev/ttyUSB0", chain.repl_port(0)).replace("mpremote", mpremote, 1)
            for _ in range(2):
                proc = subprocess.run(
                    cmd, shell=True, cwd=tmp_path, capture_output=True, text=True, timeout=120
                )
                assert proc.returncode == 0, proc.stderr
            seg = chain.segment_dir(0)
            assert not (seg / "protocol" / "protocol").exists()
            assert (seg / "protocol" / "frame.py").read_bytes() == (
                REPO / "protocol" / "frame.py"
            ).read_bytes()
            chain.restart(0)
            try:
                assert discover_one(link)["name"] == "by_hand"
            except AssertionError:
                raise AssertionError(chain.repl_output(0)[-3000:]) from None
        finally:
            link.close()
