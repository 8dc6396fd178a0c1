"""``ucr check``: exit codes, the summary tree, ``path:line: message`` errors, no traceback."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.cli_run import run_ucr

from .conftest import REPO, ROBOTS, VALID, edit

pytestmark = pytest.mark.timeout(60)


def test_check_valid_file_prints_tree_and_exits_0():
    result = run_ucr("check", str(ROBOTS / "softrobot3.ucrdf"))
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert out.startswith("robot softrobot3: 4 links, 0 joints, 3 bendables")
    assert "bendable segment_3 (model pcc, length 0.316 m)" in out
    assert "kappa_max 3.314 1/m (60.0° bend)" in out
    assert "command: kappa [0, 3.314] init 0; phi [-3.142, 3.142] init 0" in out
    assert result.stderr == ""


def test_check_hybrid_shows_joint_types():
    result = run_ucr("check", str(ROBOTS / "hybrid_arm.ucrdf"))
    assert result.returncode == 0, result.stderr
    assert "joint elbow (revolute" in result.stdout and "joint wrist_mount (fixed)" in result.stdout


def test_check_invalid_file_prints_path_line_errors_and_exits_1(tmp_path):
    bad = tmp_path / "bad.ucrdf"
    text = edit('<parent link="arm"/>', '<parent link="nowhere"/>')
    text = edit('<backbone length="0.3"', '<backbone length="-1"', text)
    bad.write_text(text)
    result = run_ucr("check", str(bad))
    assert result.returncode == 1
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert "Traceback" not in result.stderr
    pattern = re.compile(rf"^{re.escape(str(bad))}:\d+: \S")
    assert all(pattern.match(line) for line in lines[:-1]), result.stderr
    assert lines[-1] == f"{bad}: {len(lines) - 1} errors"
    assert any("parent link 'nowhere' is not defined" in line for line in lines)


@pytest.mark.parametrize("kind", ["missing", "directory", "binary"])
def test_check_unreadable_input_is_one_clear_line(tmp_path, kind):
    target = tmp_path / "x.ucrdf"
    if kind == "directory":
        target.mkdir()
    elif kind == "binary":
        target.write_bytes(bytes(range(256)))
    result = run_ucr("check", str(target))
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    first = result.stderr.splitlines()[0]
    assert first.startswith(f"{target}:")


def test_quiet_check_prints_nothing(tmp_path):
    good = tmp_path / "good.ucrdf"
    good.write_text(VALID)
    result = run_ucr("check", "-q", str(good))
    assert (result.returncode, result.stdout, result.stderr) == (0, "", "")


def test_closed_pipe_is_not_a_traceback():
    """`ucr check FILE | head`: the reader is gone before ucr writes; ucr must exit quietly."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "tools.cli", "check", str(ROBOTS / "hybrid_arm.ucrdf")],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        proc.stdout.close()  # the reader exits before ucr has started up
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "Traceback" not in err
    assert proc.returncode == 0
