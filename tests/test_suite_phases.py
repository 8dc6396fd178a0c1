"""`./run.sh test` runs the suite in two phases (conftest.py): ``--ucr-phase=shared`` in two
workers, then ``--ucr-phase=alone`` in one process. Every test must run in exactly one of them, and
what judges timing, drives a browser or runs the documentation's commands must be in the second."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# one of each kind: plain tests, a file marked alone, a test marked alone in a shared file, a
# browser file (its tests without the browser fixture too), the documentation's commands
SELECTION = [
    "tests/protocol/test_framing.py",
    "tests/host/test_link_health_fixes.py",
    "tests/commissioning/test_doctor.py",
    "tests/view/test_view_page_token.py",
    "docs/emulator.md",
]
ALONE_FILES = ("tests/host/test_link_health_fixes.py", "tests/view/test_view_page_token.py")


def _collected(*args: str) -> set[str]:
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
        + [*args, *SELECTION],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    return {ln for ln in res.stdout.splitlines() if "::" in ln}


def test_every_test_runs_in_exactly_one_phase_and_timing_browser_and_docs_run_alone() -> None:
    everything = _collected()
    shared = _collected("--ucr-phase=shared")
    alone = _collected("--ucr-phase=alone")
    assert shared | alone == everything and not shared & alone
    for nodeid in everything:
        path = nodeid.split("::")[0]
        must_be_alone = path.endswith(".md") or path in ALONE_FILES or "cpu_load" in nodeid
        assert (nodeid in alone) == must_be_alone, nodeid
    assert any(n.startswith("tests/commissioning/test_doctor.py") for n in shared)
