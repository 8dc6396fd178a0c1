"""Flash a segment: firmware (device/), protocol/ and its generated config.json, over the REPL.

Uses mpremote's serial transport in-process (pinned mpremote 1.29): enter the raw REPL without a
soft reset (``resume`` semantics, so it also works on an emulated unix-port segment, whose process
would end on a soft reset), write every file, verify each by SHA-256 computed on the board, then
reset the board. Optionally the modules are precompiled with mpy-cross for the board's bytecode
version (``sys.implementation._mpy``). docs/flashing.md has the details and the facts about
mpremote and the unix port.
"""

from __future__ import annotations

import ast
import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import serial
from mpremote.transport import TransportError
from mpremote.transport_serial import SerialTransport

from tools.mpvm import REPO

DEVICE_DIR = REPO / "device"
PROTOCOL_DIR = REPO / "protocol"
#: Files that must stay source: MicroPython only runs boot.py/main.py as .py.
KEEP_SOURCE = {"main.py", "boot.py"}
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


class FlashError(RuntimeError):
    """Flashing failed; the message says what happened and what to do."""


@dataclass
class BoardInfo:
    """What the board says about itself."""

    implementation: str
    platform: str
    mpy: int  # sys.implementation._mpy (0 if the port does not support .mpy)
    version: str

    @property
    def mpy_version(self) -> tuple[int, int]:
        return self.mpy & 0xFF, (self.mpy >> 8) & 3

    @property
    def arch(self) -> str | None:
        idx = self.mpy >> 10
        return MPY_ARCHES[idx] if idx < len(MPY_ARCHES) else None


def firmware_files(
    device_dir: Path = DEVICE_DIR, protocol_dir: Path = PROTOCOL_DIR
) -> list[tuple[str, Path]]:
    """(board path, host path) of every module to flash: device/ at the top, protocol/ package."""
    if not (device_dir / "main.py").is_file():
        raise FlashError(f"firmware not found: {device_dir / 'main.py'} is missing")
    files: list[tuple[str, Path]] = []
    for path in sorted(device_dir.rglob("*.py")):
        rel = path.relative_to(device_dir)
        if any(p == "__pycache__" or p.startswith(".") for p in rel.parts):
            continue
        files.append((rel.as_posix(), path))
    for path in sorted(protocol_dir.glob("*.py")):
        files.append((f"protocol/{path.name}", path))
    return files


def mpy_cross_version() -> tuple[int, int]:
    """(version, sub-version) of the .mpy files the installed mpy-cross writes."""
    exe = shutil.which("mpy-cross") or str(Path(sys.executable).parent / "mpy-cross")
    try:
        out = subprocess.run([exe, "--version"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise FlashError(f"mpy-cross is not usable: {exc}") from exc
    m = re.search(r"mpy v(\d+)\.(\d+)", out.stdout + out.stderr)
    if not m:
        raise FlashError(f"cannot read mpy-cross version from {out.stdout.strip()!r}")
    return int(m.group(1)), int(m.group(2))


def compile_mpy(src: Path, dst: Path, *, arch: str | None) -> None:
    """Precompile one module with mpy-cross (``-march`` for native/viper code)."""
    exe = shutil.which("mpy-cross") or str(Path(sys.executable).parent / "mpy-cross")
    cmd = [exe, "-o", str(dst), "-s", src.name]
    if arch:
        cmd.append(f"-march={arch}")
    cmd.append(str(src))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    if proc.returncode != 0:
        raise FlashError(f"mpy-cross failed on {src}: {proc.stderr.strip()}")


def check_port(port: str) -> None:
    """Clear errors for a missing or busy port before mpremote gets to it."""
    if "://" not in port and not os.path.exists(port):
        raise FlashError(
            f"port {port} does not exist: is the board plugged in? (list ports: "
            "`.venv/bin/python -m serial.tools.list_ports`)"
        )
    try:
        # exclusive (flock) is what reveals a port someone else holds; URLs do not support it
        kwargs = {} if "://" in port else {"exclusive": True}
        ser = serial.serial_for_url(port, baudrate=115200, **kwargs)
    except serial.SerialException as exc:
        text = str(exc)
        if "lock" in text.lower() or "busy" in text.lower() or "Errno 16" in text:
            raise FlashError(
                f"port {port} is busy: another program has it open (mpremote, a serial "
                "terminal, `ucr daemon`?); close it and retry"
            ) from exc
        raise FlashError(f"cannot open port {port}: {text}") from exc
    ser.close()


class Flasher:
    """One flashing session on ``port`` (see module docstring). ``log`` receives progress lines."""

    def __init__(
        self,
        port: str,
        *,
        baudrate: int = 115200,
        log: Callable[[str], None] = print,
        connect_timeout: float = 5.0,
    ) -> None:
        self.port = port
        self.log = log
        check_port(port)
        self._TransportError = TransportError
        try:
            self.t = SerialTransport(port, baudrate=baudrate, exclusive="://" not in port)
        except TransportError as exc:
            raise FlashError(f"cannot open port {port}: {exc}") from exc
        # mpremote reads a pty with read(1) and no serial timeout: a silent device would block it
        # forever; with a short timeout its own overall timeout works.
        self.t.serial.timeout = 0.1
        try:
            # resume semantics: no soft reset (it would end an emulated segment's process).
            with contextlib.redirect_stdout(io.StringIO()):  # mpremote prints what it got
                self.t.enter_raw_repl(soft_reset=False, timeout_overall=connect_timeout)
        except (TransportError, OSError) as exc:
            self.t.close()
            raise FlashError(
                f"the device on {port} did not answer like a MicroPython REPL ({exc}): is it "
                "running MicroPython (see docs/flashing.md to install it) and not stuck? "
                "Press its reset button and retry"
            ) from exc

    def close(self) -> None:
        try:
            self.t.close()
        except OSError:
            pass

    def __enter__(self) -> Flasher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _exec(self, code: str) -> str:
        try:
            return self.t.exec(code).decode(errors="replace")
        except self._TransportError as exc:
            raise FlashError(f"command on the board failed: {exc}") from exc

    def board_info(self) -> BoardInfo:
        out = self._exec(
            "import sys\nprint(repr((sys.implementation.name, sys.platform, "
            "getattr(sys.implementation, '_mpy', 0), sys.version)))"
        )
        try:
            name, platform, mpy, version = ast.literal_eval(out.strip())
        except (ValueError, SyntaxError) as exc:
            raise FlashError(f"unexpected answer from the board: {out!r}") from exc
        if name != "micropython":
            raise FlashError(f"the board runs {name}, not MicroPython")
        return BoardInfo(name, platform, int(mpy), version)

    def listing(self) -> set[str]:
        """Every file path on the board below the current directory."""
        code = (
            "import os\n"
            "def _w(d):\n"
            " for e in os.ilistdir(d or '.'):\n"
            "  p = d + '/' + e[0] if d else e[0]\n"
            "  if e[1] == 0x4000:\n"
            "   _w(p)\n"
            "  else:\n"
            "   print(p)\n"
            "_w('')\n"
        )
        return set(self._exec(code).split())

    def write_files(self, files: list[tuple[str, bytes]]) -> None:
        """Write (board path, content) pairs, creating directories; progress per file."""
        existing = self.listing()
        dirs = sorted({str(Path(p).parent) for p, _ in files if "/" in p})
        for d in dirs:
            self._exec(f"import os\ntry:\n os.mkdir({d!r})\nexcept OSError:\n pass\n")
        # A stale .py next to a new .mpy (or the reverse) would shadow it: .py is imported first.
        names = {p for p, _ in files}
        for p, _ in files:
            other = p[:-3] + ".mpy" if p.endswith(".py") else p[:-4] + ".py"
            if (
                p.endswith((".py", ".mpy"))
                and other in existing
                and other not in names
                and Path(other).name not in KEEP_SOURCE
            ):
                self._exec(f"import os\nos.remove({other!r})")
                self.log(f"      removed stale {other}")
        total = len(files)
        for i, (path, data) in enumerate(files, 1):
            self.log(f"[{i:>2}/{total}] {path} ({len(data)} bytes)")
            try:
                self.t.fs_writefile(path, data, chunk_size=256)
            except (self._TransportError, OSError) as exc:
                raise FlashError(f"copying {path} failed: {exc}") from exc

    def verify(self, files: list[tuple[str, bytes]]) -> None:
        """Compare the SHA-256 of every file computed on the board with the host's."""
        code = (
            "import hashlib, binascii\n"
            "def _h(p):\n"
            " h = hashlib.sha256()\n"
            " b = bytearray(256)\n"
            " with open(p, 'rb') as f:\n"
            "  while True:\n"
            "   n = f.readinto(b)\n"
            "   if not n:\n"
            "    break\n"
            "   h.update(b if n == 256 else b[:n])\n"
            " return binascii.hexlify(h.digest()).decode()\n"
            "for p in %r:\n"
            " try:\n"
            "  print(p, _h(p))\n"
            " except OSError:\n"
            "  print(p, 'missing')\n"
        ) % [p for p, _ in files]
        got = dict(line.split() for line in self._exec(code).splitlines() if line.strip())
        bad = [p for p, data in files if got.get(p) != hashlib.sha256(data).hexdigest()]
        if bad:
            raise FlashError(f"verification failed (hash differs on the board): {', '.join(bad)}")
        self.log(f"verified {len(files)} files by SHA-256 on the board")

    def reset(self, info: BoardInfo) -> None:
        """Restart the board so it boots the new firmware.

        Unix port (emulated segment): Ctrl-D at the friendly REPL ends the process, the emulator
        restarts it. A real board: ``machine.reset()`` (a hard reset: peripherals start clean).
        """
        if info.platform == "linux":
            self.t.exit_raw_repl()
            self.t.serial.write(b"\x04")
            self.t.serial.flush()
            time.sleep(0.05)
        else:
            try:
                self.t.exec_raw_no_follow("import machine\nmachine.reset()")
            except (self._TransportError, OSError):
                pass  # the board resets before it can answer
            self.t.in_raw_repl = False

    def leave(self) -> None:
        """Back to the friendly REPL without a reset."""
        self.t.exit_raw_repl()


def build_files(
    config: dict,
    *,
    mpy: bool = False,
    info: BoardInfo | None = None,
    device_dir: Path = DEVICE_DIR,
    protocol_dir: Path = PROTOCOL_DIR,
) -> list[tuple[str, bytes]]:
    """(board path, bytes) of everything to flash, compiled to .mpy if asked."""
    sources = firmware_files(device_dir, protocol_dir)
    files: list[tuple[str, bytes]] = []
    if mpy:
        assert info is not None
        if info.mpy == 0:
            raise FlashError("this MicroPython build cannot import .mpy files; flash without --mpy")
        host_ver = mpy_cross_version()
        if host_ver[0] != info.mpy_version[0] or host_ver[1] != info.mpy_version[1]:
            raise FlashError(
                f"the board imports mpy v{info.mpy_version[0]}.{info.mpy_version[1]} but "
                f"mpy-cross writes v{host_ver[0]}.{host_ver[1]}: flash without --mpy, or use "
                "a matching MicroPython/mpy-cross version"
            )
        with tempfile.TemporaryDirectory(prefix="ucr-mpy-") as tmp:
            for board_path, src in sources:
                if Path(board_path).name in KEEP_SOURCE:
                    files.append((board_path, src.read_bytes()))
                    continue
                dst = Path(tmp) / (board_path[:-3] + ".mpy")
                dst.parent.mkdir(parents=True, exist_ok=True)
                compile_mpy(src, dst, arch=info.arch)
                files.append((board_path[:-3] + ".mpy", dst.read_bytes()))
    else:
        files = [(p, src.read_bytes()) for p, src in sources]
    files.append(("config.json", (json.dumps(config, indent=1) + "\n").encode()))
    # main.py last: a flash interrupted half-way never boots a new main.py with old modules.
    files.sort(key=lambda f: Path(f[0]).name in KEEP_SOURCE)
    return files


def flash(
    port: str,
    config: dict,
    *,
    mpy: bool = False,
    reset: bool = True,
    log: Callable[[str], None] = print,
    device_dir: Path = DEVICE_DIR,
    protocol_dir: Path = PROTOCOL_DIR,
) -> BoardInfo:
    """Flash firmware + protocol + ``config`` to the board on ``port``; return what it reported."""
    if "://" not in port and not os.path.exists(port):
        check_port(port)  # the clearest error first
    firmware_files(device_dir, protocol_dir)  # fail early, before touching the board
    t0 = time.monotonic()
    with Flasher(port, log=log) as fl:
        info = fl.board_info()
        log(
            f"board: {info.version.strip()} on {info.platform}, mpy v{info.mpy_version[0]}."
            f"{info.mpy_version[1]}{' ' + info.arch if info.arch else ''}"
        )
        files = build_files(
            config, mpy=mpy, info=info, device_dir=device_dir, protocol_dir=protocol_dir
        )
        fl.write_files(files)
        fl.verify(files)
        if reset:
            fl.reset(info)
            log("board reset: it boots the new firmware")
        else:
            fl.leave()
            log("not reset (--no-reset): the firmware runs after the next reset")
    log(f"flashed {len(files)} files in {time.monotonic() - t0:.1f} s")
    return info
