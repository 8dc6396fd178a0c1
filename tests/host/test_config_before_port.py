"""Issue 12 finding 5: errors in the config file's API section are reported before the chain port
is opened (today the port is opened, DISCOVER sent and the chain driven before the API refuses)."""

from __future__ import annotations

import os
import select
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
ROBOT = REPO / "robots" / "softrobot3.ucrdf"


def test_api_config_error_is_reported_before_the_port_is_opened(tmp_path) -> None:
    master, slave = os.openpty()
    try:
        port = os.ttyname(slave)
        cfg = tmp_path / "daemon.yaml"
        cfg.write_text("api:\n  bind: 0.0.0.0\n")  # no token: refused
        res = subprocess.run(
            [
                sys.executable,
                "-m",
                "tools.cli",
                "daemon",
                "--robot",
                str(ROBOT),
                "--config",
                str(cfg),
                "--port",
                port,
            ],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert res.returncode != 0
        assert "without a token" in res.stderr and "daemon.yaml" in res.stderr, res.stderr
        assert "Traceback" not in res.stderr
        # nothing was sent on the chain port: it was never opened
        ready, _, _ = select.select([master], [], [], 0.2)
        assert not ready, os.read(master, 256)
    finally:
        os.close(master)
        os.close(slave)
