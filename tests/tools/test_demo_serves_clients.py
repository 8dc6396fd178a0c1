"""Issue 19 item 1: ``ucr demo --forever`` serves client commands from the moment it prints the
API URL. A client ``ucr move`` while the demo script runs replaces the demo's goal: the demo
script stops (saying so), the daemon keeps running and answering, and the client's move runs."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.cli_run import run_ucr

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.timeout(180)


def test_demo_forever_keeps_serving_a_client_that_moves_during_the_script() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "demo", "--forever", "--quiet-log"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    lines: list[str] = []
    try:
        url = None
        end = time.monotonic() + 90
        while url is None and time.monotonic() < end:
            line = proc.stdout.readline()
            assert line, "demo ended before printing the API URL:\n" + "".join(lines)
            lines.append(line)
            m = re.match(r"API on (\S+)", line)
            if m:
                url = m.group(1)
        assert url, "".join(lines)
        # at once, while the demo's own trajectory runs
        # (a goal may abort with cause link_loss when the loaded machine starves the emulated
        # segments — docs/daemon.md "No motion without a command": then it is sent again)
        for _ in range(3):
            moved = run_ucr(
                "move",
                "--url",
                url,
                "--segment",
                "segment_2",
                "--kappa",
                "0.5",
                "--duration",
                "1.0",
            )
            if "link loss" not in moved.stderr:
                break
        # served: the goal was accepted and ran to an end the daemon reported (a loaded machine
        # may abort it by a tolerance: that is the daemon serving, not failing)
        assert "accepted" in moved.stdout, moved.stdout + moved.stderr
        assert moved.returncode == 0 or " aborted: " in moved.stderr, moved.stdout + moved.stderr
        # the demo yields; the daemon keeps serving
        end = time.monotonic() + 60
        while time.monotonic() < end:
            line = proc.stdout.readline()
            assert line, "demo exited:\n" + "".join(lines)
            lines.append(line)
            if line.startswith("== running until Ctrl-C"):
                break
        text = "".join(lines)
        assert "== running until Ctrl-C" in text and proc.poll() is None, text
        st = run_ucr("status", "--url", url)
        assert st.returncode == 0 and "segment_2" in st.stdout, st.stdout + st.stderr
        for _ in range(3):
            again = run_ucr(
                "move",
                "--url",
                url,
                "--segment",
                "segment_2",
                "--kappa",
                "0.0",
                "--duration",
                "1.0",
            )
            if "link loss" not in again.stderr:
                break
        assert "accepted" in again.stdout, again.stdout + again.stderr
        assert again.returncode == 0 or " aborted: " in again.stderr, again.stdout + again.stderr
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            out, _ = proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    text = "".join(lines) + out
    # the demo's exit code is its own script's: on a loaded host that script's goal may end
    # aborted by link loss three times (the daemon being safe); what this test asks is that the
    # daemon kept serving meanwhile (above) and that SIGTERM ends it cleanly
    starved = "== trajectory aborted: link loss" in text
    assert proc.returncode == 0 or (proc.returncode == 1 and starved), text
    # --quiet-log: only warnings, from the API process too (review 2026-11-26: it logged INFO)
    info = [ln for ln in ("".join(lines) + out).splitlines() if re.search(r"\bINFO\b", ln)]
    assert not info, info
