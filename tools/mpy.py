"""Precompiled firmware: the ``.mpy`` files ``ucr flash`` deploys and the emulator runs.

A board that imports a module from source runs MicroPython's compiler on its own heap: the parser
and the emitter need several KB of *contiguous* memory, which a segment that has been running for
a while no longer has (its heap is fragmented by the long-lived objects built at boot). So the
firmware goes to a board precompiled with mpy-cross (``.mpy``: bytecode, and machine code for the
``@micropython.viper`` modules where the board has a native emitter); only ``main.py`` and
``boot.py`` stay source, because MicroPython runs only those as ``.py``. The emulator lays out
each segment's "flash" with the same function, so a test on the emulated chain runs what a board
runs (docs/flashing.md, "Precompiled modules").

Fallbacks, each said in the log: no native emitter for the board's architecture → bytecode-only
``.mpy`` (a module that holds viper code then goes as source: its import fails on such a board
and its callers keep their plain-Python paths, protocol/_fast.py); a board that imports no
``.mpy``, or another ``.mpy`` version than the installed mpy-cross writes → source files.

Compiled files are cached by content (source bytes, architecture, mpy-cross version) under
``$XDG_CACHE_HOME/ucr/mpy`` (default ``~/.cache/ucr/mpy``), so starting an emulated chain costs
one mpy-cross run per changed module, not one per module and segment.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path

#: Files that must stay source: MicroPython only runs boot.py/main.py as .py.
KEEP_SOURCE = frozenset({"main.py", "boot.py"})
#: ``sys.implementation._mpy`` bits 10.. name the native architecture (py/persistentcode.h).
MPY_ARCHES = (
    None,
    "x86",
    "x64",
    "armv6",
    "armv6m",
    "armv7m",
    "armv7em",
    "armv7emsp",
    "armv7emdp",
    "xtensa",
    "xtensawin",
    "rv32imc",
    "rv64imc",
)


class MpyError(RuntimeError):
    """mpy-cross could not be run or could not compile a module; the message says which."""


def arch_of(mpy: int) -> str | None:
    """The native architecture ``sys.implementation._mpy`` names (None: no native code)."""
    idx = mpy >> 10
    return MPY_ARCHES[idx] if idx < len(MPY_ARCHES) else None


def version_of(mpy: int) -> tuple[int, int]:
    """(version, sub-version) of the .mpy files a board with ``sys.implementation._mpy`` imports."""
    return mpy & 0xFF, (mpy >> 8) & 3


def mpy_cross() -> str:
    """Path of the mpy-cross executable (next to this interpreter, else on PATH)."""
    here = Path(sys.executable).parent / "mpy-cross"
    return str(here) if here.exists() else (shutil.which("mpy-cross") or str(here))


@functools.cache
def mpy_cross_version() -> tuple[int, int]:
    """(version, sub-version) of the .mpy files the installed mpy-cross writes."""
    try:
        out = subprocess.run([mpy_cross(), "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise MpyError(f"mpy-cross is not usable: {exc}") from exc
    m = re.search(r"mpy v(\d+)\.(\d+)", out.stdout + out.stderr)
    if not m:
        raise MpyError(f"cannot read mpy-cross version from {out.stdout.strip()!r}")
    return int(m.group(1)), int(m.group(2))


def compile_mpy(src: Path, dst: Path, *, arch: str | None) -> None:
    """Precompile one module with mpy-cross (``-march`` for native/viper code)."""
    cmd = [mpy_cross(), "-o", str(dst), "-s", src.name]
    if arch:
        cmd.append(f"-march={arch}")
    cmd.append(str(src))
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise MpyError(f"mpy-cross is not usable: {exc}") from exc
    if proc.returncode != 0:
        raise MpyError(f"mpy-cross failed on {src}: {proc.stderr.strip()}")


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ucr" / "mpy"


def _compiled(src: Path, arch: str | None) -> bytes:
    """The .mpy of ``src`` for ``arch``, from the cache or freshly compiled (then cached)."""
    data = src.read_bytes()
    ver = mpy_cross_version()
    key = hashlib.sha256(
        b"\0".join([data, src.name.encode(), str(arch).encode(), f"{ver[0]}.{ver[1]}".encode()])
    ).hexdigest()
    cached = _cache_dir() / f"{key}.mpy"
    try:
        return cached.read_bytes()
    except OSError:
        pass
    with tempfile.TemporaryDirectory(prefix="ucr-mpy-") as tmp:
        dst = Path(tmp) / (src.stem + ".mpy")
        compile_mpy(src, dst, arch=arch)
        out = dst.read_bytes()
    try:  # the cache is an optimisation: a read-only home only costs time
        cached.parent.mkdir(parents=True, exist_ok=True)
        part = cached.with_suffix(f".{os.getpid()}.part")
        part.write_bytes(out)
        os.replace(part, cached)
    except OSError:
        pass
    return out


def usable(mpy: int, log: Callable[[str], None], verb: str = "flashing") -> bool:
    """Whether a board with ``sys.implementation._mpy`` = ``mpy`` imports what mpy-cross writes
    (else it logs why, ending "<verb> source files")."""
    if mpy == 0:
        log(f"this MicroPython build cannot import .mpy files: {verb} source files")
        return False
    host = mpy_cross_version()
    board = version_of(mpy)
    if host != board:
        log(
            f"the board imports mpy v{board[0]}.{board[1]} but mpy-cross writes "
            f"v{host[0]}.{host[1]}: {verb} source files"
        )
        return False
    return True


def compile_sources(
    sources: Iterable[tuple[str, Path]],
    *,
    mpy: int,
    log: Callable[[str], None],
    verb: str = "flashing",
) -> list[tuple[str, bytes]]:
    """(board path, bytes) for each (board path, source) pair: ``.mpy`` for a board whose
    ``sys.implementation._mpy`` is ``mpy``, with the fallbacks of the module docstring."""
    sources = list(sources)
    if not usable(mpy, log, verb):
        return [(p, src.read_bytes()) for p, src in sources]
    arch = arch_of(mpy)
    files: list[tuple[str, bytes]] = []
    for board_path, src in sources:
        if Path(board_path).name in KEEP_SOURCE or not board_path.endswith(".py"):
            files.append((board_path, src.read_bytes()))
            continue
        try:
            out = _compiled(src, arch)
        except MpyError as exc:
            if not _needs_emitter(exc):
                raise  # a module that does not compile is an error, never flashed as source
            if arch is not None:
                log(f"mpy-cross has no native emitter for {arch}: bytecode-only .mpy files")
                arch = None
                try:
                    out = _compiled(src, None)
                except MpyError as again:
                    if not _needs_emitter(again):
                        raise
                    out = None
            else:
                out = None
        if out is None:
            # native/viper code needs an emitter: the source, whose import falls back to plain
            # Python on a board without one (protocol/_fast.py)
            log(f"{board_path}: native code without an emitter: {verb} it as source")
            files.append((board_path, src.read_bytes()))
            continue
        files.append((board_path[:-3] + ".mpy", out))
    return files


def _needs_emitter(exc: MpyError) -> bool:
    """Whether mpy-cross refused a module only for want of a native emitter ("invalid arch")."""
    return "invalid arch" in str(exc)
