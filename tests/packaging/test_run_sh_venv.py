"""`./run.sh setup` and a virtual environment left half-made (review 2026-11-26): when
`python3 -m venv` fails (Debian without python3-venv) it leaves a `bin/python` without pip, and
every later setup failed with "No module named pip", even after python3-venv was installed."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_a_venv_without_pip_is_made_again_and_a_failing_venv_says_what_to_install(
    tmp_path: Path,
) -> None:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    # a python whose venv module fails, as Debian's does without python3-venv
    fake = tmp_path / "python3"
    fake.write_text(
        f'#!/bin/sh\nif [ "$1" = "-m" ] && [ "$2" = "venv" ]; then exit 1; fi\n'
        f'exec {sys.executable} "$@"\n'
    )
    fake.chmod(0o755)
    env = {**os.environ, "UCR_VENV": str(venv), "PYTHON": str(fake), "UCR_EXTRAS": ""}
    proc = subprocess.run(
        ["./run.sh", "setup"], cwd=REPO, env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 1, proc.stderr
    assert "has no pip" in proc.stderr and "creating it again" in proc.stderr, proc.stderr
    assert "sudo apt install python3-venv" in proc.stderr, proc.stderr
    assert not venv.exists()  # no half-made venv left for the next run to trip over
