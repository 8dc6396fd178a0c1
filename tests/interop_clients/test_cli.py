"""The interop commands fail with one line, never a traceback: optional dependencies missing,
daemon unreachable, unreadable recording."""

from __future__ import annotations

import subprocess
import sys

import pytest

from .conftest import REPO

MISSING = """
import sys
sys.modules[{mod!r}] = None  # as if the optional package were not installed
from tools.cli import main
sys.exit(main({argv!r}))
"""


@pytest.mark.parametrize(
    ("mod", "argv"),
    [
        ("mcap", ["record", "-o", "x.mcap"]),
        ("foxglove", ["foxglove"]),
        ("mcap_ros2", ["replay", "x.mcap"]),
    ],
)
def test_missing_optional_dependency_is_one_line(mod, argv):
    res = subprocess.run([sys.executable, "-c", MISSING.format(mod=mod, argv=argv)], cwd=REPO,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "pip install 'ucr[record]'" in lines[0] and repr(mod) in lines[0]


def _ucr(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tools.cli", *argv], cwd=REPO,
                          capture_output=True, text=True, timeout=120)  # fmt: skip


def test_record_without_a_daemon_says_so(tmp_path):
    res = _ucr("record", "-o", str(tmp_path / "r.mcap"), "--url", "ws://127.0.0.1:9")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert "cannot reach the daemon" in res.stderr


def test_replay_of_a_file_that_is_not_mcap_is_one_line(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    res = _ucr("replay", str(bad), "--execute", "--robot", str(REPO / "robots/softrobot3.ucrdf"))
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert "bad.mcap: not an MCAP file" in res.stderr
    res = _ucr("replay", str(bad), "--port", "0")
    assert res.returncode == 1 and "bad.mcap: not an MCAP file" in res.stderr
    res = _ucr("replay", str(tmp_path / "missing.mcap"), "--port", "0")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
