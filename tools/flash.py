"""Flash a segment: firmware (device/), protocol/ and its generated config.json, over the REPL.

Uses mpremote's serial transport in-process (pinned mpremote 1.29): enter the raw REPL without a
soft reset (``resume`` semantics, so it also works on an emulated unix-port segment, whose process
would end on a soft reset) within an overall deadline (a device that talks but is no REPL is given
up on), write every file under a temporary name, verify each by SHA-256 computed on the board,
rename them into place (``main.py`` last), then reset the board. Any failure removes the
temporary files and leaves the previous firmware in place and the board at the friendly REPL
(reset, unless ``--no-reset``, so the old firmware runs the chain again). The modules are
precompiled with mpy-cross for the board's bytecode version (``sys.implementation._mpy``;
tools/mpy.py, which also says why and how it falls back); ``--source`` flashes source files.
docs/flashing.md has the details and the facts about mpremote and the unix port.
"""

from __future__ import annotations

import ast
import errno
import hashlib
import json
import os
import re
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import serial
from mpremote.transport import TransportError
from mpremote.transport_serial import SerialTransport

from tools import mpy as mpy_tools
from tools.mpvm import REPO
from tools.mpy import KEEP_SOURCE, compile_mpy, mpy_cross_version  # noqa: F401 - re-exported

DEVICE_DIR = REPO / "device"
PROTOCOL_DIR = REPO / "protocol"
#: What the raw REPL prints when entered (mpremote waits for the ">" that follows itself).
RAW_BANNER = b"raw REPL; CTRL-B to exit\r\n"
#: Suffix of a file while it is being uploaded: renamed into place only once all are verified.
TMP_SUFFIX = ".new"
#: What the firmware prints once it serves the chain (device/main.py ``run``).
UP_LINE = re.compile(rb"\[main\] segment \S+ up")
#: Seconds a reset board gets to print UP_LINE (an emulated segment on a loaded host is slow).
BOOT_TIMEOUT = 15.0
#: Seconds an interrupted board gets to answer the raw REPL again before it is given up on.
RESYNC_TIMEOUT = 3.0
#: Seconds of silence from a board waiting for its raw-REPL prompt or acknowledgement (mpremote
#: waits 10 s there): a board switched off mid-upload is given up on after this. A command's own
#: output keeps mpremote's 10 s (a board may compute that long before it prints).
QUIET_TIMEOUT = 5.0
_DEFAULT = object()


def _bounded_reads(read_until: Callable[..., bytes]) -> Callable[..., bytes]:
    """mpremote's ``read_until`` with :data:`QUIET_TIMEOUT` where its callers rely on its 10 s
    default, and a message saying what happened when the answer does not come (every such caller
    fails then anyway, saying "could not enter raw repl")."""

    def read(min_num_bytes, ending, timeout=_DEFAULT, data_consumer=None, timeout_overall=None):
        if timeout is not _DEFAULT:
            return read_until(min_num_bytes, ending, timeout, data_consumer, timeout_overall)
        data = read_until(min_num_bytes, ending, QUIET_TIMEOUT, data_consumer, timeout_overall)
        if not data.endswith(ending):
            raise TransportError(f"the board sent nothing for {QUIET_TIMEOUT:g} s")
        return data

    return read


class FlashError(RuntimeError):
    """Flashing failed; the message says what happened and what to do."""


class FlashInterrupted(FlashError):
    """Ctrl-C (or SIGTERM) ended the flash; the message says what state the board is left in."""


@dataclass
class BoardInfo:
    """What the board says about itself."""

    implementation: str
    platform: str
    mpy: int  # sys.implementation._mpy (0 if the port does not support .mpy)
    version: str

    @property
    def mpy_version(self) -> tuple[int, int]:
        return mpy_tools.version_of(self.mpy)

    @property
    def arch(self) -> str | None:
        return mpy_tools.arch_of(self.mpy)


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


class _CountingSerial:
    """The pyserial port with byte counters (what a transfer really costs on the wire)."""

    def __init__(self, ser: serial.Serial) -> None:
        object.__setattr__(self, "_ser", ser)
        object.__setattr__(self, "tx", 0)
        object.__setattr__(self, "rx", 0)

    def write(self, data: bytes) -> int | None:
        object.__setattr__(self, "tx", self.tx + len(data))
        return self._ser.write(data)

    def read(self, n: int = 1) -> bytes:
        data = self._ser.read(n)
        object.__setattr__(self, "rx", self.rx + len(data))
        return data

    def __getattr__(self, name: str):
        return getattr(self._ser, name)

    def __setattr__(self, name: str, value: object) -> None:
        setattr(self._ser, name, value)


_LINK_ERRORS = (TransportError, OSError, serial.SerialException)


class _Signals:
    """SIGINT and SIGTERM while the board is being changed (main thread only; elsewhere the
    handlers cannot be set and nothing changes). ``mode``: "raise" turns either into
    KeyboardInterrupt (so SIGTERM cleans up like Ctrl-C), "defer" records it for later (a
    cleanup or the final renames must not be cut short)."""

    def __init__(self) -> None:
        self.pending = False
        self._old: dict[int, object] = {}
        self._mode = "raise"

    def _handler(self, signum: int, frame: object) -> None:
        if self._mode == "raise":
            raise KeyboardInterrupt
        self.pending = True

    def mode(self, mode: str) -> None:
        self._mode = mode

    def __enter__(self) -> _Signals:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc: object) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)  # type: ignore[arg-type]


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
        except _LINK_ERRORS as exc:
            raise FlashError(f"cannot open port {port}: {exc}") from exc
        # mpremote reads a pty with read(1) and no serial timeout: a silent device would block it
        # forever. 0.1 s while entering the raw REPL (our own loop keeps the deadline), then 2 s:
        # mpremote's raw-paste handshake reads its 2-byte answer with the serial timeout, and a
        # board (or loaded host) slower than 0.1 s made every exec fail "could not enter raw repl".
        self.t.serial.timeout = 0.1
        self.t.serial = self.wire = _CountingSerial(self.t.serial)
        self.t.read_until = _bounded_reads(self.t.read_until)
        try:
            self._enter_raw_repl(connect_timeout)
            self.t.serial.timeout = 2.0
        except KeyboardInterrupt:
            try:  # Ctrl-C may have stopped main.py: leave any raw REPL, soft-reset to restart it
                self.t.serial.write(b"\r\x03\x03\r\x02\x04")
            except _LINK_ERRORS:
                pass
            self.close()
            raise FlashInterrupted(
                "interrupted while entering the board's REPL; nothing was changed (Ctrl-B, "
                "Ctrl-D sent so its firmware starts again)"
            ) from None
        except (FlashError, *_LINK_ERRORS) as exc:
            self.close()
            raise FlashError(
                f"the device on {port} did not answer like a MicroPython REPL within "
                f"{connect_timeout:g} s of opening the port ({exc}): is it running MicroPython "
                "(see docs/flashing.md to install it) and not stuck? Is it the board's USB/REPL "
                "port and not a chain port? Press its reset button and retry"
            ) from exc

    def _enter_raw_repl(self, timeout: float) -> None:
        """Ctrl-C, Ctrl-A, then the raw REPL banner within ``timeout`` s overall, however much
        the device talks (mpremote's own loop restarts its timeout on every byte it reads).
        Retried every second (a board still booting may miss the first Ctrl-C). Bytes are read
        one at a time so the prompt after the banner stays for mpremote."""
        ser = self.t.serial
        end = time.monotonic() + timeout
        seen = b""
        while time.monotonic() < end:
            ser.write(b"\r\x03\x03")  # stop a running program (resume semantics: no soft reset)
            quiet_until = time.monotonic() + 0.2
            while time.monotonic() < min(quiet_until, end) and ser.read(256):
                pass  # drop what the program printed
            ser.write(b"\r\x01")  # enter the raw REPL
            retry_at = time.monotonic() + 1.0
            while time.monotonic() < min(retry_at, end):
                b = ser.read(1)
                if b:
                    seen = (seen + b)[-256:]
                    if seen.endswith(RAW_BANNER):
                        self.t.in_raw_repl = True
                        return
        text = seen[-60:].decode(errors="replace")
        raise FlashError(f"no raw REPL prompt, last bytes {text!r}" if seen else "no answer")

    def close(self) -> None:
        try:
            self.t.close()
        except _LINK_ERRORS:
            pass

    def __enter__(self) -> Flasher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _exec(self, code: str) -> str:
        try:
            return self.t.exec(code).decode(errors="replace")
        except _LINK_ERRORS as exc:
            raise FlashError(f"command on the board failed: {_why(exc)}") from exc

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

    def remove(self, paths: list[str]) -> None:
        """Delete these files on the board (missing ones are fine)."""
        self._exec(
            f"import os\nfor p in {paths!r}:\n try:\n  os.remove(p)\n except OSError:\n  pass\n"
        )

    def listing(self) -> set[str]:
        """Every file path on the board below the current directory."""
        code = _WALK + "  else:\n   print(p)\n_w('')\n"
        return set(self._exec(code).split())

    def write_files(self, files: list[tuple[str, bytes]]) -> None:
        """Upload (board path, content) pairs under temporary names (``path + TMP_SUFFIX``),
        creating directories; progress per file. Nothing the board runs is touched yet."""
        dirs = sorted({str(Path(p).parent) for p, _ in files if "/" in p})
        for d in dirs:
            self._exec(f"import os\ntry:\n os.mkdir({d!r})\nexcept OSError:\n pass\n")
        total = len(files)
        for i, (path, data) in enumerate(files, 1):
            self.log(f"[{i:>2}/{total}] {path} ({len(data)} bytes)")
            try:
                self.t.fs_writefile(path + TMP_SUFFIX, data, chunk_size=256)
            except _LINK_ERRORS as exc:
                raise FlashError(f"copying {path} failed: {_why(exc)}") from exc

    def verify(self, files: list[tuple[str, bytes]], *, suffix: str = TMP_SUFFIX) -> None:
        """Compare the SHA-256 of every uploaded file computed on the board with the host's."""
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
        ) % [p + suffix for p, _ in files]
        got = dict(line.split() for line in self._exec(code).splitlines() if line.strip())
        bad = [p for p, data in files if got.get(p + suffix) != hashlib.sha256(data).hexdigest()]
        if bad:
            raise FlashError(f"verification failed (hash differs on the board): {', '.join(bad)}")
        self.log(f"verified {len(files)} files by SHA-256 on the board")

    def commit(self, files: list[tuple[str, bytes]]) -> set[str]:
        """Rename every verified upload into place in one script (``main.py`` last, as listed),
        then remove a stale ``.py``/``.mpy`` twin a new file would be shadowed by or shadow, and
        the uploads (``*.new``) an earlier interrupted flash left. Returns the board's listing
        from before the renames."""
        existing = self.listing()
        names = {p for p, _ in files}
        stale = []
        for p, _ in files:
            other = p[:-3] + ".mpy" if p.endswith(".py") else p[:-4] + ".py"
            if (
                p.endswith((".py", ".mpy"))
                and other in existing
                and other not in names
                and Path(other).name not in KEEP_SOURCE
            ):
                stale.append(other)
        finals = [p for p, _ in files]
        earlier = sorted(
            p for p in existing if p.endswith(TMP_SUFFIX) and p[: -len(TMP_SUFFIX)] not in names
        )
        code = (
            f"import os\nT = {TMP_SUFFIX!r}\n"
            f"for p in {finals!r}:\n"
            " try:\n"
            "  os.rename(p + T, p)\n"
            " except OSError:\n"
            "  os.remove(p)\n"
            "  os.rename(p + T, p)\n"
            f"for p in {stale!r}:\n"
            " os.remove(p)\n"
            f"for p in {earlier!r}:\n"
            " try:\n"
            "  os.remove(p)\n"
            " except OSError:\n"
            "  print('left', p)\n"
        )
        left = {ln.split(" ", 1)[1] for ln in self._exec(code).splitlines() if ln[:5] == "left "}
        for p in stale:
            self.log(f"      removed stale {p}")
        for p in earlier:
            if p not in left:
                self.log(f"      removed stale {p} (left by an earlier flash)")
        if left:
            raise FlashError(f"cannot remove stale uploads {', '.join(sorted(left))}")
        return existing

    def resync(self, timeout: float = RESYNC_TIMEOUT) -> None:
        """Back to an idle raw REPL after an interruption: the board may be half-way through a
        command (a raw-paste upload, a running script). Ctrl-C ends either, Ctrl-A re-enters."""
        self.t.in_raw_repl = False
        self.t.serial.timeout = 0.1
        try:
            self._enter_raw_repl(timeout)
        finally:
            self.t.serial.timeout = 2.0
        self.t.in_raw_repl = True

    def abort(self, files: list[tuple[str, bytes]], *, reset: bool, info: BoardInfo | None) -> str:
        """After a failure or an interruption: bring the board back to an idle raw REPL, remove
        every temporary upload (``*.new``), leave the raw REPL and (``reset``) restart the previous
        firmware, watching it come up. Returns what was really done, for the message."""
        try:
            self.resync()
        except (FlashError, *_LINK_ERRORS):
            return (
                "the board did not answer any more (switched off, unplugged or stuck?): "
                f"temporary files (*{TMP_SUFFIX}) may be left on it and its firmware is stopped; "
                "once it answers, run `ucr flash` again (it removes them) or press its reset button"
            )
        done = []
        try:
            left = self.remove_uploads()
            done.append(
                "temporary files removed"
                if not left
                else f"temporary files left: {', '.join(sorted(left))} (a later `ucr flash` "
                "removes them)"
            )
        except FlashError as exc:
            done.append(
                f"temporary files (*{TMP_SUFFIX}) may be left ({exc}; a later `ucr flash` "
                "removes them)"
            )
        try:
            if reset and info is not None:
                self.reset(info)
                state, detail = self.watch_boot()
                done.append(
                    {
                        "up": "the board was reset to its previous firmware, which runs again",
                        "error": "the board was reset but its previous firmware does not start "
                        f"({detail})",
                        "closed": "the board was reset to its previous firmware (the port closed "
                        "during the reset: check it with `ucr doctor`)",
                        "silent": "the board was reset to its previous firmware (no start-up line "
                        f"within {BOOT_TIMEOUT:g} s: check it with `ucr doctor`)",
                    }[state]
                )
            else:
                self.leave()
                done.append("the board is at its REPL with its previous firmware")
        except _LINK_ERRORS as exc:
            done.append(f"leaving the raw REPL failed ({_why(exc)}): press its reset button")
        return "; ".join(done)

    def remove_uploads(self) -> set[str]:
        """Remove every ``*.new`` on the board (this flash's and an earlier failed one's);
        return those that could not be removed."""
        code = (
            _WALK + f"  elif p.endswith({TMP_SUFFIX!r}):\n"
            "   try:\n"
            "    os.remove(p)\n"
            "   except OSError:\n"
            "    print('left', p)\n"
            "_w('')\n"
        )
        return {ln.split(" ", 1)[1] for ln in self._exec(code).splitlines() if ln[:5] == "left "}

    def watch_boot(self, timeout: float = BOOT_TIMEOUT) -> tuple[str, str]:
        """After a reset: read the REPL until the firmware's "up" line or a traceback. Returns
        ("up", ""), ("error", the traceback's error line), ("closed", why: the port went away,
        e.g. a native-USB board re-enumerating) or ("silent", "") after ``timeout`` s."""
        ser = self.t.serial
        ser.timeout = 0.1
        end = time.monotonic() + timeout
        seen = b""
        try:
            while time.monotonic() < end:
                seen += ser.read(256)
                if UP_LINE.search(seen):
                    return "up", ""
                error = _traceback_error(seen)
                if error:
                    return "error", error
        except _LINK_ERRORS as exc:
            return "closed", _why(exc)
        return "silent", ""

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
            except _LINK_ERRORS:
                pass  # the board resets before it can answer
            self.t.in_raw_repl = False

    def leave(self) -> None:
        """Back to the friendly REPL without a reset."""
        self.t.exit_raw_repl()


def _traceback_error(out: bytes) -> str | None:
    """The error line of the first complete MicroPython traceback in ``out``, else None."""
    at = out.find(b"Traceback (most recent call last):")
    if at < 0:
        return None
    for line in out[at:].split(b"\n")[1:-1]:  # complete lines only
        if line and not line[:1].isspace():
            return line.strip().decode(errors="replace")
    return None


def _why(exc: BaseException) -> str:
    """One line for a transport or OS error (EIO on a vanished port says so)."""
    if isinstance(exc, OSError) and exc.errno == errno.EIO:
        return "input/output error: the port went away (board unplugged or reset?)"
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[-1] if text else type(exc).__name__


def build_files(
    config: dict,
    *,
    mpy: bool = True,
    info: BoardInfo | None = None,
    device_dir: Path = DEVICE_DIR,
    protocol_dir: Path = PROTOCOL_DIR,
    log: Callable[[str], None] = print,
) -> list[tuple[str, bytes]]:
    """(board path, bytes) of everything to flash: modules precompiled to .mpy for the board
    (``mpy``, the default; tools/mpy.py says why and how it falls back), else source files."""
    sources = firmware_files(device_dir, protocol_dir)
    if mpy:
        assert info is not None
        try:
            files = mpy_tools.compile_sources(sources, mpy=info.mpy, log=log)
        except mpy_tools.MpyError as exc:
            raise FlashError(str(exc)) from exc
    else:
        files = [(p, src.read_bytes()) for p, src in sources]
    files.append(("config.json", (json.dumps(config, indent=1) + "\n").encode()))
    # main.py last: a flash interrupted half-way never boots a new main.py with old modules.
    files.sort(key=lambda f: Path(f[0]).name in KEEP_SOURCE)
    return files


#: Board-side walk of every file below the current directory: ``_w('')`` visits each path ``p``
#: (directories recursed); a caller appends the ``else``/``elif`` branch for files and the call.
_WALK = (
    "import os\n"
    "def _w(d):\n"
    " for e in os.ilistdir(d or '.'):\n"
    "  p = d + '/' + e[0] if d else e[0]\n"
    "  if e[1] == 0x4000:\n"
    "   _w(p)\n"
)

#: what ``ucr calibrate`` persists on a segment (device/calib_store.py), which wins at boot
CALIBRATION_FILES = frozenset({"calibration.json", "calibration.tmp"})


def flash(
    port: str,
    config: dict,
    *,
    mpy: bool = True,
    reset: bool = True,
    log: Callable[[str], None] = print,
    device_dir: Path = DEVICE_DIR,
    protocol_dir: Path = PROTOCOL_DIR,
    connect_timeout: float = 5.0,
    forget_calibration: bool = False,
) -> BoardInfo:
    """Flash firmware + protocol + ``config`` to the board on ``port``; return what it reported.
    A calibration stored on the board (``calibration.json``, which overrides the configuration's
    zero offsets and directions at boot) is kept and said so, or removed with
    ``forget_calibration``.

    Raises FlashError with one line on any failure; the board then still has its previous
    firmware (see module docstring)."""
    if "://" not in port and not os.path.exists(port):
        check_port(port)  # the clearest error first
    firmware_files(device_dir, protocol_dir)  # fail early, before touching the board
    t0 = time.monotonic()
    with _Signals() as sigs, Flasher(port, log=log, connect_timeout=connect_timeout) as fl:
        info: BoardInfo | None = None
        files: list[tuple[str, bytes]] = []
        try:
            info = fl.board_info()
            log(
                f"board: {info.version.strip()} on {info.platform}, mpy v{info.mpy_version[0]}."
                f"{info.mpy_version[1]}{' ' + info.arch if info.arch else ''}"
            )
            files = build_files(
                config,
                mpy=mpy,
                info=info,
                device_dir=device_dir,
                protocol_dir=protocol_dir,
                log=log,
            )
            fl.write_files(files)
            fl.verify(files)
            sigs.mode("defer")  # the renames and the reset run to their end
            stored = CALIBRATION_FILES & fl.commit(files)
            if stored and forget_calibration:
                fl.remove(sorted(stored))
                log("removed the stored calibration: the robot file's zero offsets apply")
            elif stored:
                log(
                    "kept the calibration stored on the board (calibration.json, from `ucr "
                    "calibrate`): it overrides the robot file's zero offsets and directions; "
                    "write it into the robot file (`ucr calibrate --robot ...`) or flash with "
                    "--forget-calibration"
                )
        except (FlashError, KeyboardInterrupt, *_LINK_ERRORS) as exc:
            sigs.mode("defer")  # the cleanup is not cut short by a second Ctrl-C
            what = fl.abort(files, reset=reset, info=info)
            if isinstance(exc, KeyboardInterrupt):
                raise FlashInterrupted(f"interrupted; nothing was changed ({what})") from None
            if isinstance(exc, FlashError):
                raise FlashError(f"{exc}; nothing was changed ({what})") from exc
            raise FlashError(f"the link failed: {_why(exc)}; nothing was changed ({what})") from exc
        try:
            if reset:
                fl.reset(info)
                state, detail = fl.watch_boot()
                if state == "error":
                    hint = (
                        " (--source: the board compiles every module on its own heap; flash "
                        "without --source)"
                        if not mpy and "MemoryError" in detail
                        else ""
                    )
                    raise FlashError(
                        f"the new firmware is in place but does not start: {detail}{hint}; see "
                        "`mpremote connect PORT repl` for its output"
                    )
                log(
                    {
                        "up": "board reset: it boots the new firmware",
                        "closed": f"board reset ({detail}): check it with `ucr doctor`",
                        "silent": f"board reset: no start-up line within {BOOT_TIMEOUT:g} s, "
                        "check it with `ucr doctor`",
                    }[state]
                )
            else:
                fl.leave()
                log("not reset (--no-reset): the firmware runs after the next reset")
        except _LINK_ERRORS as exc:
            raise FlashError(
                f"the new firmware is in place but the reset failed ({_why(exc)}): press the "
                "board's reset button"
            ) from exc
        wire = fl.wire.tx + fl.wire.rx
    if sigs.pending:
        log("interrupt received during the final renames and reset: held back until they ended")
    log(summary_line(len(files), time.monotonic() - t0, wire, port, config))
    return info


#: The UART speed of a board's REPL behind a USB-UART bridge (ESP32 devkits).
REPL_BAUD = 115200


def repl_is_uart(port: str, config: dict) -> bool:
    """Does the REPL run over a 115200-baud UART (a USB-UART bridge)? Not on a board whose REPL
    is native USB (``*-usbrepl``), nor on an emulated segment (a pty or a URL: no line rate)."""
    from protocol.boards import default_board  # noqa: PLC0415

    board = config.get("board") or default_board(config.get("servo_driver"))
    if str(board).endswith("-usbrepl") or "://" in port:
        return False
    real = os.path.realpath(port)
    return not real.startswith(("/dev/pts/", "/dev/ptmx"))


def summary_line(n: int, seconds: float, wire: int, port: str, config: dict) -> str:
    """The last line of a flash: files, time, bytes over the REPL and the rate measured; the
    115200-baud floor only where the REPL is such a UART (:func:`repl_is_uart`)."""
    rate = wire / seconds / 1000.0 if seconds > 0 else 0.0
    text = f"flashed {n} files in {seconds:.1f} s ({wire} bytes over the REPL, {rate:.1f} kB/s"
    if repl_is_uart(port, config):
        text += f"; a {REPL_BAUD}-baud UART REPL needs at least {wire * 10 / REPL_BAUD:.1f} s"
    return text + ")"
