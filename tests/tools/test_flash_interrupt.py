"""Review 3 defect A: an interruption of ``ucr flash`` (SIGINT, SIGTERM, the board switched off)
at any point leaves the board out of the raw REPL, running its previous firmware, without
temporary files, and the one-line message says only what really happened."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from flash_helpers import discover_name, one_segment_named

from tools.flash import TMP_SUFFIX, FlashError, flash

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"

pytestmark = [pytest.mark.timeout(120), pytest.mark.alone]  # give-up timeouts: conftest.py


@pytest.fixture(scope="module")
def chain():
    with one_segment_named("before") as ch_link:
        yield ch_link


def _flash_and_signal(port: str, sig: int, after: str, delay: float) -> tuple[int, str]:
    """Run ``ucr flash`` in the foreground process group sense (its own process, default signal
    dispositions) and send ``sig`` once its output shows ``after``."""
    proc = subprocess.Popen(
        [sys.executable, "-u", "-m", "tools.cli", "flash", "--port", port, "--robot", str(ROBOT)]
        + ["--segment", "segment_1", "--servo-driver", "emulated"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # noqa: PLW1509
    )
    assert proc.stdout is not None
    for line in proc.stdout:
        if after in line:
            time.sleep(delay)  # mid-transfer: the board is inside a raw-REPL command
            os.kill(proc.pid, sig)
            break
    _, err = proc.communicate(timeout=60)
    return proc.returncode, err


@pytest.mark.parametrize(
    ("sig", "after", "delay"),
    [
        (signal.SIGINT, "[10/", 0.0),
        (signal.SIGINT, "[10/", 0.03),
        (signal.SIGINT, "[ 3/", 0.08),
        # (not later than file 20: on a quick run the last files and the rename were done
        # before a signal sent 0.15 s after file 25, and the flash rightly succeeded)
        (signal.SIGINT, "[20/", 0.15),
        (signal.SIGTERM, "[20/", 0.05),
    ],
)
def test_a_signal_midway_leaves_the_previous_firmware_running(chain, sig, after, delay) -> None:
    ch, link = chain
    seg = ch.segment_dir(0)
    name = discover_name(link, chain=ch)
    restarts = ch.stats()["segments"][0]["restarts"]
    code, err = _flash_and_signal(ch.repl_port(0), sig, after, delay)
    assert code == 130, err  # interrupted, as every ucr command (it was 2, a usage error's code)
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("ucr: error: interrupted; nothing was changed"), err
    assert "temporary files removed" in err and "previous firmware" in err, err
    assert not [p for p in seg.rglob("*" + TMP_SUFFIX)], err
    ch.wait_restarts(0, restarts + 1, timeout=20)  # out of the raw REPL: main.py runs again
    assert discover_name(link, chain=ch) == name


def test_ctrl_c_during_the_final_renames_is_held_back_until_they_end(chain) -> None:
    ch, link = chain
    code, err = _flash_and_signal(ch.repl_port(0), signal.SIGINT, "verified", 0.0)
    assert code == 0, err
    assert not [p for p in ch.segment_dir(0).rglob("*" + TMP_SUFFIX)]
    assert discover_name(link, chain=ch) == "segment_1"  # the new firmware, complete, runs


def test_a_board_switched_off_midway_is_not_claimed_reset(chain) -> None:
    ch, link = chain
    name = discover_name(link, chain=ch)
    lines: list[str] = []

    def log(line: str) -> None:
        lines.append(line)
        if line.startswith("[ 5/"):
            ch.power_off(0)

    t0 = time.monotonic()
    try:
        with pytest.raises(FlashError) as info:
            flash(ch.repl_port(0), {"name": "after"}, log=log, connect_timeout=5.0)
    finally:
        ch.power_on(0)
    message = str(info.value)
    assert time.monotonic() - t0 < 25, message
    assert "reset to its previous firmware" not in message, message
    assert "did not answer" in message and "ucr flash" in message, message
    # before: mpremote's "could not enter raw repl" after 10 s of silence (15 s in all here)
    assert "failed: the board sent nothing for 5 s" in message, message
    assert discover_name(link, chain=ch) == name


def test_a_successful_flash_removes_stale_uploads_of_a_failed_one(chain) -> None:
    ch, link = chain
    seg = ch.segment_dir(0)
    (seg / ("old_module.mpy" + TMP_SUFFIX)).write_bytes(b"x")
    (seg / "protocol" / ("gone.py" + TMP_SUFFIX)).write_bytes(b"y")
    lines: list[str] = []
    restarts = ch.stats()["segments"][0]["restarts"]
    flash(ch.repl_port(0), {"name": "before"}, log=lines.append)
    assert not [p for p in seg.rglob("*" + TMP_SUFFIX)]
    assert any("old_module.mpy.new" in line for line in lines), lines
    ch.wait_restarts(0, restarts + 1, timeout=20)
    assert discover_name(link, chain=ch) == "before"
