"""``ucr`` as a user runs it, for the tests: a fresh ``python -m tools.cli`` in the repository,
output captured as text, stdin closed (a command that waits for input fails instead of hanging)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def run_ucr(
    *args: str, timeout: float = 120.0, env: dict[str, str] | None = None, stdout: Any = None
) -> subprocess.CompletedProcess[str]:
    """Run ``ucr ARGS...`` to its end (``env``: variables added to this process's; ``stdout``: a
    file its output goes to instead of being captured, e.g. /dev/full)."""
    return subprocess.run(
        [sys.executable, "-m", "tools.cli", *args],
        cwd=REPO,
        env=None if env is None else {**os.environ, **env},
        stdout=subprocess.PIPE if stdout is None else stdout,
        stderr=subprocess.PIPE,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )
