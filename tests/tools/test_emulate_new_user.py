"""New-user audit of ``ucr emulate``: an option that would be silently ignored is a usage error,
and Ctrl-C stops it with exit 130 and one line, no traceback (SIGTERM still exits 0)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from tests.cli_run import run_ucr
from tools.mpvm import REPO


def _emulate(*argv: str) -> subprocess.CompletedProcess[str]:
    # (timeout: the old code started the chain and ran until stopped)
    return run_ucr("emulate", *argv, timeout=30)


def test_cpu_factor_without_the_timing_model_is_a_usage_error() -> None:
    proc = _emulate("1", "--no-stdin", "--cpu-factor", "50")
    assert proc.returncode == 2, proc.stdout
    assert "--cpu-factor needs --timing-model" in proc.stderr
    assert "host port" not in proc.stdout  # nothing started


def test_keep_without_a_workdir_is_a_usage_error() -> None:
    proc = _emulate("1", "--no-stdin", "--keep")
    assert proc.returncode == 2, proc.stdout
    assert "--keep needs --workdir" in proc.stderr
    assert "host port" not in proc.stdout


@pytest.mark.needs_micropython  # the emulator runs in a child process
def test_ctrl_c_stops_the_emulator_with_exit_130_and_one_line() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "emulate", "2", "--no-stdin"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group: SIGINT to it is a terminal's Ctrl-C
    )
    try:
        line = ""
        while not line.startswith("running"):
            line = proc.stdout.readline()
            assert line, proc.stderr.read()
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert out.strip().splitlines()[-1] == "emulator stopped (Ctrl-C)"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
