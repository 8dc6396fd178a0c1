"""Every ``ucr`` client command docs/daemon.md lists in its packaging table exists."""

from __future__ import annotations

import re
import subprocess
import sys

from tools.mpvm import REPO


def test_the_client_commands_docs_daemon_lists_are_ucr_subcommands() -> None:
    text = (REPO / "docs" / "daemon.md").read_text()
    listed = re.search(r"client CLI \(`ucr ([a-z/-]+)", text)
    assert listed is not None
    names = listed.group(1).split("/")
    usage = subprocess.run(
        [sys.executable, "-m", "tools.cli", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    ).stdout
    known = set(re.findall(r"^    ([a-z][a-z0-9-]*)(?:\s|$)", usage, re.MULTILINE))
    assert "check" in known and "flash" in known
    assert "trajectory" in names
    assert [n for n in names if n not in known] == []
