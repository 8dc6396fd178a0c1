"""Start ``ucr view`` as its own process (the demo does this): the daemon never waits for it."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import threading
import time

from view.cli import INSTALL_HINT


class ViewProcess:
    """A running ``ucr view`` child process and the URL it printed (with the page token when
    the page has controls: the URL to open); ``lines``: what it printed so far."""

    def __init__(self, proc: subprocess.Popen, url: str, lines: list[str] | None = None):
        self.proc, self.url = proc, url
        self.lines = lines if lines is not None else []

    def stop(self, timeout: float = 5.0) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)


def start_view_process(
    api_url: str, port: int = 0, timeout: float = 60.0, rate_hz: float | None = None
) -> ViewProcess:
    """Run ``ucr view --url API_URL --port PORT [--rate RATE_HZ]``; returns once it prints its
    URL.

    RuntimeError with a one-line reason if viser is missing or the view does not come up."""
    if importlib.util.find_spec("viser") is None:
        raise RuntimeError(INSTALL_HINT)
    cmd = [sys.executable, "-m", "tools.cli", "view", "--url", api_url, "--port", str(port),
           "--exit-with-parent"]  # fmt: skip
    if rate_hz is not None:
        cmd += ["--rate", f"{rate_hz:g}"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    )
    found: list[str] = []
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line.rstrip())
            if line.startswith("ucr view: http") and not found:
                found.append(line.split()[2])
            elif found and (line.startswith("ucr view:") or " AUDIT view " in line):
                # its warnings and its audit (what each page client did), once it runs
                print(line.rstrip(), file=sys.stderr, flush=True)
        # (keeps draining so the child never blocks on a full pipe)

    threading.Thread(target=read, name="ucr-view-output", daemon=True).start()
    end = time.monotonic() + timeout
    while not found and proc.poll() is None and time.monotonic() < end:
        time.sleep(0.05)
    if not found:
        rc = proc.poll()
        ViewProcess(proc, "").stop()
        why = next((ln for ln in reversed(lines) if ln.startswith("ucr")), None)
        if why is None:  # no line of its own: say how it ended and what it printed last
            how = f"exited with status {rc}" if rc is not None else f"no URL in {timeout:g} s"
            last = next((ln for ln in reversed(lines) if ln.strip()), "")
            why = f"{how}{'; its last output: ' + last[:300] if last else ', no output'}"
        raise RuntimeError(f"view did not start: {why}")
    return ViewProcess(proc, found[0], lines)
