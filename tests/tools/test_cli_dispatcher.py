"""The ``ucr`` dispatcher: every area's commands are registered; a closed pipe is no traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tools.cli import build_parser

REPO = Path(__file__).resolve().parents[2]


def test_every_documented_command_is_registered():
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    assert set(sub.choices) >= {
        "check", "fk", "ik", "export-urdf", "emulate", "flash", "daemon", "demo",
        "status", "watch", "move", "trajectory", "controllers", "teleop",
    }  # fmt: skip


_BROKEN_PIPE_COMMAND = """
import sys
import tools.cli as cli

def body(args):
    print("a line for a reader that is gone")
    raise BrokenPipeError(32, "Broken pipe")  # what print() raises once the reader has left

parser = cli.build_parser()
sub = next(a for a in parser._actions if a.dest == "command")
sub.choices["status"].set_defaults(func=body)
cli.build_parser = lambda: parser
sys.exit(cli.main(["status"]))
"""


def test_a_reader_leaving_the_pipe_ends_the_command_quietly_without_a_traceback():
    """`ucr watch | head`: when the reader leaves, the command stops with 141 (128 + SIGPIPE),
    like a Unix tool, and no traceback (also at the interpreter's final flush)."""
    proc = subprocess.run(
        [sys.executable, "-c", _BROKEN_PIPE_COMMAND], cwd=REPO, capture_output=True, timeout=60
    )
    assert b"Traceback" not in proc.stderr and b"Exception ignored" not in proc.stderr, proc.stderr
    assert proc.returncode == 141


def test_an_unknown_option_shows_the_commands_own_usage(capsys):
    """`ucr status --bogus` printed the dispatcher's `usage: ucr [-h] COMMAND ...`, which says
    nothing about what status takes (review 2026-11-27)."""
    from tools.cli import main

    with pytest.raises(SystemExit) as info:
        main(["status", "--bogus"])
    err = capsys.readouterr().err
    assert info.value.code == 2
    assert (
        err.startswith("usage: ucr status ")
        and "ucr status: error: unrecognized arguments: --bogus" in err
    )
