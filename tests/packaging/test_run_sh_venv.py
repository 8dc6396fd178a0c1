"""`./run.sh setup` and a virtual environment left half-made (review 2026-11-26): when
`python3 -m venv` fails (Debian without python3-venv) it leaves a `bin/python` without pip, and
every later setup failed with "No module named pip", even after python3-venv was installed. And a
venv installed for another directory (a moved or copied checkout, or one .venv shared by two):
pip's editable install and the scripts' #! lines name that directory, so it ran the other code (or
nothing: "cannot execute: required file not found")."""

from __future__ import annotations

import hashlib
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


def test_a_venv_installed_for_another_directory_is_installed_again(tmp_path: Path) -> None:
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=120)
    site = next((venv / "lib").glob("python3.*/site-packages"))
    # stamped as installed (runtime only, spec "."), as ./run.sh setup leaves it
    stamp = venv / ".ucr-installed"
    want = (REPO / "pyproject.toml").read_bytes() + b".\n" + (venv / "pyvenv.cfg").read_bytes()
    stamp.write_text(hashlib.sha256(want).hexdigest()[:16] + "\n")
    no_index = tmp_path / "no-wheels"
    no_index.mkdir()
    env = {
        **os.environ,
        "UCR_VENV": str(venv),
        "UCR_EXTRAS": "",
        "PIP_NO_INDEX": "1",  # an install attempt fails at once instead of installing
        "PIP_FIND_LINKS": str(no_index),
    }

    def setup() -> subprocess.CompletedProcess:
        return subprocess.run(
            ["./run.sh", "setup"], cwd=REPO, env=env, capture_output=True, text=True, timeout=120
        )

    # its code is this checkout's: nothing to do
    (site / "ucr-here.pth").write_text(f"{REPO}\n")
    proc = setup()
    assert proc.returncode == 0, proc.stderr
    assert "another directory" not in proc.stderr and "installing" not in proc.stderr
    assert stamp.exists()
    # its code is another directory's (where the checkout was before): installed again
    other = tmp_path / "old-checkout"
    (other / "host").mkdir(parents=True)
    (other / "host" / "__init__.py").write_text("")
    (site / "ucr-here.pth").write_text(f"{other}\n")
    proc = setup()
    assert "was installed for another directory" in proc.stderr, proc.stderr
    assert "installing ." in proc.stderr, proc.stderr  # (fails here: no index, on purpose)
    assert not stamp.exists()  # the next setup tries again
