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
        # were checked only after contacting the daemon (exit 1), or silently ignored (--nice)
        (["record", "-o", "r.mcap", "--subdivisions", "1000000000"],
         "argument --subdivisions: must be <= 1000, got 1000000000"),
        (["foxglove", "--subdivisions", "1001"], "argument --subdivisions: must be <= 1000"),
        (["record", "-o", "r.mcap", "--nice", "-5"],
         ("argument --nice: must be >= 0, got -5: only lowering this process's priority is "
         "offered")),
        (["replay", "x.mcap", "--nice", "-1"], "argument --nice: must be >= 0, got -1"),
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


def test_a_dangling_symlink_as_output_is_refused_by_name(tmp_path):
    """Defect: `ucr: None` (the refusal found nothing, then open(..., "xb") failed)."""
    link = tmp_path / "dang.mcap"
    link.symlink_to(tmp_path / "x" / "target.mcap")
    for extra in ((), ("--overwrite",)):  # never followed: it would create the target
        res = run_ucr("record", "-o", str(link), "--duration", "1", "--url", "ws://127.0.0.1:9",
                      *extra)  # fmt: skip
        assert res.returncode == 1 and res.stderr.strip().splitlines() == [
            (
                f"ucr: {link} is a symlink to {tmp_path / 'x' / 'target.mcap'}, which does not "
                "exist: refused, not followed"
            )
        ], res.stderr


class _Daemon:
    """The API calls robot_for makes, for a daemon running ``robot``."""

    def __init__(self, robot) -> None:
        self.text = robot.read_text()

    def topology(self):
        return {"file": "/elsewhere/robot.ucrdf"}

    def robot_description(self):
        return {"text": self.text}


def test_a_robot_file_that_is_not_utf8_is_named(tmp_path):
    """Defect: `ucr: 'utf-8' codec can't decode byte 0xff ...`, no file named."""
    from interop.live import FeedError, robot_for

    text = (REPO / "robots/softrobot3.ucrdf").read_text()
    latin = tmp_path / "latin.ucrdf"  # valid XML (its declaration says ISO-8859-1), not UTF-8
    body = text.split("?>", 1)[1] if text.startswith("<?xml") else text
    latin.write_bytes(b'<?xml version="1.0" encoding="ISO-8859-1"?>\n<!-- \xe9 -->' + body.encode())
    with pytest.raises(FeedError, match=rf"^{latin}: not UTF-8 text \(byte 0xe9 at offset 49\)"):
        robot_for(_Daemon(REPO / "robots/softrobot3.ucrdf"), str(latin))
    garbage = tmp_path / "garbage.ucrdf"
    garbage.write_bytes(b"\xff\xfe<robot/>")
    with pytest.raises(FeedError, match=rf"^{garbage}:1: "):
        robot_for(_Daemon(REPO / "robots/softrobot3.ucrdf"), str(garbage))


def test_a_robot_file_that_is_not_the_daemons_robot_is_refused():
    """Defect: `--robot softrobot2.ucrdf` against a 3-segment daemon recorded an inconsistent
    file without a word."""
    from interop.live import FeedError, robot_for

    daemon = _Daemon(REPO / "robots/softrobot3.ucrdf")
    two = REPO / "robots/softrobot2.ucrdf"
    with pytest.raises(
        FeedError,
        match=r"softrobot2.ucrdf is not the daemon's robot \(bendables "
        r"segment_1, segment_2 here, segment_1, segment_2, segment_3 there\)",
    ):
        robot_for(daemon, str(two))
    robot, _ = robot_for(daemon, str(REPO / "robots/softrobot3.ucrdf"))  # the same robot: fine
    assert list(robot.bendables) == ["segment_1", "segment_2", "segment_3"]


def test_fanout_tells_its_owner_which_sink_failed_and_feeds_the_others():
    """`ucr record` stops when its file fails; other owners keep the rest going."""
    from interop.sinks import Fanout

    class Sink:
        def __init__(self, fail: bool) -> None:
            self.fail, self.got, self.closed = fail, 0, False

        def write(self, *a):
            if self.fail:
                raise OSError(28, "No space left on device")
            self.got += 1

        def tick(self):
            pass

        def close(self):
            self.closed = True

    bad, good = Sink(True), Sink(False)
    dropped = []
    out = Fanout([bad, good], on_drop=lambda s, e: dropped.append((s, e.strerror)))
    out.write("/t", "std_msgs/msg/String", "", b"", 0)
    out.write("/t", "std_msgs/msg/String", "", b"", 1)
    assert dropped == [(bad, "No space left on device")] and bad.closed and good.got == 2
