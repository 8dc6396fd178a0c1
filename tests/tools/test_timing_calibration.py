"""The timing model's host-speed estimate (tools/emulator/timing.py): the calibration kernel runs
on the real VM, a slow run does not decide the CPU factor, and bench_timing refuses a file that
is not MicroPython's pystone."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tools.emulator import timing

REPO = Path(__file__).resolve().parents[2]


def test_the_kernel_runs_on_the_vm_and_reports_loops_per_second() -> None:
    rate = timing.kernel_rate(runs=1)
    assert 10_000 < rate < 1_000_000_000


def test_a_run_in_a_slow_window_does_not_set_the_factor(monkeypatch) -> None:
    """On a shared machine a whole VM run can go at half speed: the best of the runs counts."""
    outs = iter(["@@ 1200000\n", "@@ 2500000\n", "@@ 1300000\n"])
    monkeypatch.setattr(timing.mpvm, "run_code", lambda code, timeout=60: next(outs))
    assert timing.kernel_rate(runs=3) == 2500000
    monkeypatch.setattr(timing.mpvm, "run_code", lambda code, timeout=60: "no result")
    with pytest.raises(RuntimeError, match="printed no result"):
        timing.kernel_rate(runs=1)


def test_bench_timing_refuses_a_file_that_is_not_pystone(tmp_path: Path) -> None:
    bad = tmp_path / "x.py"
    bad.write_text("print('hello')\n")
    for arg, why in ((bad, "is not MicroPython's pystone"), (tmp_path / "nope.py", "cannot read")):
        proc = subprocess.run(
            [sys.executable, "benchmarks/bench_timing.py", "--pystone", str(arg)],
            cwd=REPO, capture_output=True, text=True, timeout=60,
        )  # fmt: skip
        assert proc.returncode == 2 and why in proc.stderr, proc.stderr
        assert "Traceback" not in proc.stderr
