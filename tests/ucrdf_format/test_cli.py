"""``ucr check``: exit codes, the summary tree, ``path:line: message`` errors, no traceback."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

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
    assert "command: kappa [0, 3.314] 1/m, init 0 1/m; phi [-3.142, 3.142] rad, init 0 rad" in out
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


def test_check_prints_interface_units_of_rigid_joints_too():
    out = run_ucr("check", str(ROBOTS / "hybrid_arm.ucrdf")).stdout
    assert "command: position [-1.571, 1.571] rad" in out and "state: position init 0 rad" in out


def test_an_empty_path_says_so():
    result = run_ucr("check", "")
    assert result.returncode == 1
    assert result.stderr == "'': cannot read file: the path is empty\n'': 1 error\n"


def test_a_file_beyond_the_size_limit_is_one_diagnostic(tmp_path, monkeypatch):
    from ucrdf import parser  # noqa: PLC0415
    from ucrdf.errors import UcrdfError  # noqa: PLC0415

    big = tmp_path / "big.ucrdf"
    big.write_text(VALID + "<!--" + "x" * (1 << 20) + "-->\n")
    monkeypatch.setattr(parser, "MAX_FILE_BYTES", 1 << 20)
    with pytest.raises(UcrdfError) as info:
        parser.load(big)
    assert str(info.value) == f"{big}: file is larger than 1 MiB: not a robot description"


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_an_endless_input_is_refused_not_read_to_the_end():
    result = run_ucr("check", "/dev/zero", timeout=60)
    assert result.returncode == 1
    assert result.stderr.splitlines()[0] == (
        "/dev/zero: file is larger than 64 MiB: not a robot description"
    )


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_a_stdout_that_cannot_take_the_summary_is_one_line():
    with open("/dev/full", "w") as full:
        result = run_ucr("check", str(ROBOTS / "softrobot3.ucrdf"), timeout=60, stdout=full)
    assert result.returncode == 1
    assert result.stderr == "ucr check: error: cannot write the summary: No space left on device\n"
