"""The interop commands fail with one line, never a traceback: optional dependencies missing,
daemon unreachable, unreadable recording."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.cli_run import run_ucr

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
        ("mcap_ros2", ["foxglove"]),  # the server is ucr's own (interop/guard.py): no SDK
        ("mcap_ros2", ["replay", "x.mcap"]),
    ],
)
def test_missing_optional_dependency_is_one_line(mod, argv):
    res = subprocess.run([sys.executable, "-c", MISSING.format(mod=mod, argv=argv)], cwd=REPO,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 1
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and repr(mod) in lines[0], lines
    assert "pip install -e '" in lines[0] and "[record]'" in lines[0], lines  # not PyPI's 'ucr'


def test_record_without_a_daemon_says_so(tmp_path):
    res = run_ucr("record", "-o", str(tmp_path / "r.mcap"), "--url", "ws://127.0.0.1:9")
    assert res.returncode == 1 and "Traceback" not in res.stderr
    assert "cannot reach the daemon" in res.stderr


def test_replay_of_a_file_that_is_not_mcap_is_one_line(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"this is not an mcap file at all")
    res = run_ucr("replay", str(bad), "--execute", "--robot", str(REPO / "robots/softrobot3.ucrdf"))
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert "bad.mcap: not an MCAP file" in res.stderr
    res = run_ucr("replay", str(bad), "--port", "0")
    assert res.returncode == 1 and "bad.mcap: not an MCAP file" in res.stderr
    res = run_ucr("replay", str(tmp_path / "missing.mcap"), "--port", "0")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr


def test_record_keeps_an_existing_file_unless_overwrite(tmp_path):
    """Defect: `ucr record -o EXISTING` replaced a recording without a word."""
    old = tmp_path / "old.mcap"
    old.write_bytes(b"an earlier recording")
    res = run_ucr("record", "-o", str(old), "--url", "ws://127.0.0.1:9")
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines() == [
        f"ucr: {old} exists: refused, it is kept (--overwrite replaces it)"
    ]
    assert old.read_bytes() == b"an earlier recording"
    res = run_ucr("record", "-o", str(tmp_path), "--url", "ws://127.0.0.1:9")
    assert res.returncode == 1 and "is a directory" in res.stderr, res.stderr
    res = run_ucr("record", "-o", str(old), "--overwrite", "--url", "ws://127.0.0.1:9")
    assert res.returncode == 1 and "cannot reach the daemon" in res.stderr  # got past the check


def test_the_recording_sink_refuses_a_file_that_appeared_meanwhile(tmp_path):
    from interop.record import McapSink

    f = tmp_path / "r.mcap"
    f.write_bytes(b"x")
    with pytest.raises(FileExistsError):
        McapSink(f, overwrite=False)
    assert f.read_bytes() == b"x"
    McapSink(f).close()  # the library default (tests, benchmarks) replaces


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["replay", "x.mcap", "--go"], "--go only with --execute"),
        (["replay", "x.mcap", "--measured"], "--measured only with --execute"),
        (["replay", "x.mcap", "--rate", "-1"],
         "argument --rate: must be a finite number >= 0, got -1"),
        (["replay", "x.mcap", "--rate", "nan"], "argument --rate: must be a finite number >= 0"),
        (["replay", "x.mcap", "--execute", "--measured", "--sample-period", "0"],
         "argument --sample-period: must be a finite number of s > 0"),
        (["replay", "x.mcap", "--execute", "--lead-in", "-2"],
         "argument --lead-in: must be a finite number of s > 0"),
        (["replay", "x.mcap", "--wait-client", "-1"],
         "argument --wait-client: must be a finite number of s >= 0"),
        (["replay", "x.mcap", "--port", "70000"], "argument --port: must be a port 0..65535"),
        (["record", "-o", "r.mcap", "--duration", "-1"],
         "argument --duration: must be a finite number of s > 0"),
        (["record", "-o", "r.mcap", "--duration", "0"],
         "argument --duration: must be a finite number of s > 0"),
        (["record", "-o", "r.mcap", "--flush-interval", "-1"], "argument --flush-interval: must"),
        (["record", "-o", "r.mcap", "--viz-rate", "0"],
         "argument --viz-rate: must be a finite number of Hz > 0"),
        (["record", "-o", "r.mcap", "--subdivisions", "0"], "argument --subdivisions: must be"),
        (["foxglove", "--duration", "0"], "argument --duration: must be a finite number of s > 0"),
        (["record", "-o", "r.mcap", "--duration", "1e400"],  # infinity is > 0: say "finite"
         "argument --duration: must be a finite number of s > 0, got 1e400"),
        (["foxglove", "--viz-rate", "-5"],
         "argument --viz-rate: must be a finite number of Hz > 0"),
        (["record", "-o", "r.mcap", "--insecure"], "--insecure only with a Foxglove server"),
        (["record", "-o", "r.mcap", "--tls-cert", "c.pem", "--tls-key", "k.pem"],
         "--tls-cert, --tls-key only with a Foxglove server"),
        (["record", "-o", "r.mcap", "--allow-origin", "https://x"], "--allow-origin only with"),
    ],
)  # fmt: skip
def test_impossible_option_values_are_usage_errors(tmp_path, argv, message):
    """Defect: these were accepted in silence (`--rate -1` printed "at -1x", `--go` without
    `--execute` did nothing)."""
    import os

    env = {**os.environ, "PYTHONPATH": str(REPO)}  # this tree's ucr, run where r.mcap may land
    res = subprocess.run([sys.executable, "-m", "tools.cli", *argv], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)  # fmt: skip
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr and message in res.stderr.strip().splitlines()[-1]
    assert not (tmp_path / "r.mcap").exists()


def test_rate_zero_still_means_as_fast_as_possible(tmp_path):
    """The documented `--rate 0` (and `--wait-client 0`) stay valid."""
    from tools.cli import build_parser

    args = build_parser().parse_args(["replay", "x.mcap", "--rate", "0", "--wait-client", "0"])
    assert args.rate == 0 and args.wait_client == 0
