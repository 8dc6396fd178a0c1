"""An emulated segment chain: real firmware in real MicroPython processes, linked through ptys.

Layout (n segments)::

    host port ──link 0── seg 0 ──link 1── seg 1 ── … ──link n-1── seg n-1 ──(tip: nothing)

Each link is two pty pairs (its upper and lower end) joined by two :class:`Pipe` objects (down:
towards the tip, up: towards the host) in the proxy thread, so every link can be unplugged,
throttled, delayed or corrupted at run time. Each segment also has a REPL: the process's
stdin/stdout/stderr is a pty (its controlling terminal, so Ctrl-C raises KeyboardInterrupt in
``main.py``) proxied to a second pty whose path is what mpremote opens.

A supervisor thread restarts a segment whose process exits (a soft reset through mpremote ends a
unix-port process; a crash kills it), as a real board reboots. Like a board, a soft reset from
the raw REPL does not run ``main.py`` (ports/esp32/main.c runs it only in the friendly REPL): the
process comes back with "MPY: soft reboot" in the raw REPL, and ``main.py`` runs again after a
soft reset from the friendly REPL (Ctrl-B, Ctrl-D: what ``ucr flash`` does), a restart or a
power-on. Everything is cleaned up by
``close()`` (context manager exit, atexit, and the children die with the emulator through
PR_SET_PDEATHSIG even if it is killed).
"""

from __future__ import annotations

import atexit
import ctypes
import fcntl
import json
import logging
import math
import os
import secrets
import shutil
import signal
import subprocess
import tempfile
import termios
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from protocol import boards
from tools import mpy as mpy_tools
from tools.emulator.pipe import Pipe
from tools.emulator.proxy import Proxy, PtyEnd, RingLog
from tools.mpvm import REPO, implementation_mpy, micropython_binary

_RAW_BANNER = b"raw REPL; CTRL-B to exit"  # what MicroPython prints entering its raw REPL

DEFAULT_FIRMWARE_DIR = REPO / "device"
DEFAULT_PROTOCOL_DIR = REPO / "protocol"
_log = logging.getLogger("ucr.emulator")

_PR_SET_PDEATHSIG = 1
try:
    _libc: ctypes.CDLL | None = ctypes.CDLL(None, use_errno=True)
except OSError:  # pragma: no cover - non-glibc platforms
    _libc = None


class EmulatorError(RuntimeError):
    """The emulated chain could not be built or used (bad argument, missing firmware, …)."""


#: ``config_for`` entry for a segment flashed without any config.json (the same as None): it refuses
#: to move and says why (docs/firmware.md "Configuration"), as a board does.
NO_CONFIG = None


def default_config() -> dict:
    """The configuration every segment of a chain gets when no ``config_for`` is given: the
    paper's segment (316 mm, three tendons 120° apart at 50 mm, 20 mm spool, κ_max = 60°/316 mm,
    emulated servos at zero offset 0 with a ±π range), written out as its config.json. A
    segment never runs built-in defaults in place of a missing file; the emulator provisions
    this explicitly (docs/emulator.md)."""
    third = 2.0 * math.pi / 3.0
    return {
        "name": "segment",
        "length": 0.316,
        "tendon_angles": [0.0, third, 2.0 * third],
        "tendon_radius": 0.05,
        "spool_radius": 0.02,
        "kappa_max": (math.pi / 3.0) / 0.316,
        "servo_driver": "emulated",
        "servos": [
            {
                "id": i,
                "zero_offset": 0.0,
                "direction": 1,
                "min_angle": -math.pi,
                "max_angle": math.pi,
            }
            for i in range(3)
        ],
        "watchdog_ms": 200,
    }


ConfigSource = Callable[[int], dict | None] | Sequence[dict | None] | None


def _child_setup() -> None:
    """Run in the forked child: own session, REPL pty as controlling tty, die with the emulator."""
    os.setsid()
    fcntl.ioctl(0, termios.TIOCSCTTY, 0)
    if _libc is not None:
        _libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)


def _firmware_sources(firmware_dir: Path, protocol_dir: Path | None) -> list[tuple[str, Path]]:
    """(path in the segment's flash, host path) of every file a segment gets: the firmware tree
    (``*.py``, ``*.json``) at the top and the ``protocol/`` package's top-level modules (its
    vectors/ and tests are host-side material)."""
    out = []
    for path in sorted(firmware_dir.rglob("*")):
        rel = path.relative_to(firmware_dir)
        if any(part == "__pycache__" or part.startswith(".") for part in rel.parts):
            continue
        if path.is_file() and path.suffix in (".py", ".json"):
            out.append((rel.as_posix(), path))
    if protocol_dir is not None:
        if not protocol_dir.is_dir():
            raise EmulatorError(f"protocol directory {protocol_dir} does not exist")
        out.extend((f"protocol/{path.name}", path) for path in sorted(protocol_dir.glob("*.py")))
    return out


def populate_segment_dir(
    seg_dir: Path,
    *,
    firmware_dir: Path = DEFAULT_FIRMWARE_DIR,
    protocol_dir: Path | None = DEFAULT_PROTOCOL_DIR,
    config: dict | None = None,
    mpy: bool = True,
) -> None:
    """Lay out a segment's "flash": firmware files at the top, ``protocol/`` package, config.json.

    This is what ``ucr flash`` writes to a real board: modules precompiled to ``.mpy`` for the
    VM by the same function (tools/mpy.py), ``main.py`` as source; ``mpy=False`` lays out source
    files (the board then compiles each module on its own heap at import, as after
    ``ucr flash --source``).
    """
    firmware_dir = Path(firmware_dir)
    if not (firmware_dir / "main.py").is_file():
        raise EmulatorError(f"no main.py in firmware directory {firmware_dir}")
    sources = _firmware_sources(firmware_dir, None if protocol_dir is None else Path(protocol_dir))
    if mpy:
        try:
            files = mpy_tools.compile_sources(
                sources, mpy=implementation_mpy(), log=_log.warning, verb="running"
            )
        except mpy_tools.MpyError as exc:
            raise EmulatorError(f"cannot precompile the firmware: {exc}") from exc
    else:
        files = [(p, src.read_bytes()) for p, src in sources]
    seg_dir.mkdir(parents=True, exist_ok=True)
    for board_path, data in files:
        target = seg_dir / board_path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
        # the twin a reused directory may hold: MicroPython imports a .py before a .mpy
        twin = target.with_suffix(".py" if target.suffix == ".mpy" else ".mpy")
        if target.suffix in (".py", ".mpy") and twin.exists():
            twin.unlink()
    cfg_path = seg_dir / "config.json"
    if config is not None:
        cfg_path.write_text(json.dumps(config, indent=1) + "\n")
    elif cfg_path.exists():
        cfg_path.unlink()


class _Link:
    """Link k: ``upper`` (host or segment k-1's down port) and ``lower`` (segment k's up port)."""

    def __init__(self, index: int, upper: PtyEnd, lower: PtyEnd, seed: int) -> None:
        self.index = index
        self.upper = upper
        self.lower = lower
        self.down = Pipe(f"link{index}.down", seed=seed * 2 + 1)
        self.up = Pipe(f"link{index}.up", seed=seed * 2 + 2)
        self.plugged = True


class _Segment:
    def __init__(self, index: int, seg_dir: Path, uid: str) -> None:
        self.board = boards.DEFAULT_BOARD
        self.cpu_factor = 1.0
        self.index = index
        self.dir = seg_dir
        self.uid = uid
        self.faults: str | None = None
        self.proc: subprocess.Popen | None = None
        self.started_at = 0.0
        self.restarts = 0
        self.exit_codes: list[int] = []
        self.spawn_errors: list[str] = []
        self.retry_at = 0.0
        self.log = RingLog()
        self.repl_inner: PtyEnd
        self.repl_outer: PtyEnd
        self.up: PtyEnd
        self.down: PtyEnd
        self.powered = True
        self.repl_to_proc: Pipe
        self.repl_from_proc: Pipe
        self.raw_repl = False  # the REPL mode the process last showed (raw banner vs ">>> ")
        self.raw_boot = False  # the next start is a raw-REPL soft reset: no main.py
        self.to_raw = False  # put the process in the raw REPL once it shows its prompt


_SPEEDS = {
    getattr(termios, f"B{r}"): r
    for r in (
        9600,
        19200,
        38400,
        57600,
        115200,
        230400,
        460800,
        500000,
        576000,
        921600,
        1000000,
        1152000,
        1500000,
        2000000,
    )
    if hasattr(termios, f"B{r}")
}


def _baud_gate(end: PtyEnd, baud: int, feed: Callable[[bytes, float], None] | None):
    """``feed`` passing bytes through only while the host port is set to ``baud`` bit/s; at any
    other rate each byte arrives garbled (a UART sampling at the wrong rate)."""

    def on_read(data: bytes, now: float) -> None:
        if feed is None:
            return
        try:
            speed = _SPEEDS.get(termios.tcgetattr(end.slave)[4])
        except termios.error:
            speed = None
        if speed != baud:
            data = bytes(b ^ 0xA5 for b in data)
        feed(data, now)

    return on_read


class EmulatedChain:
    """``n`` emulated segments behind one host port. Use as a context manager.

    Parameters: ``workdir`` (segment directories go to ``workdir/seg<N>``, N counted from 1;
    default a temporary directory removed on close), ``firmware_dir`` (default ``device/``),
    ``protocol_dir`` (default ``protocol/``), ``config_for`` (position -> config dict, or None =
    ``NO_CONFIG`` for no config.json at all; or a list; not given: ``default_config()`` for each),
    ``faults_for`` (position -> UCR_FAULTS spec), ``uids`` (hex ids; default random but stable
    for the chain's life), ``heap`` (``-X heapsize``; default the board's heap budget),
    ``reuse_dirs`` (keep existing segment directories, e.g. flashed ones, instead of
    repopulating), ``seed`` (corruption RNG), ``board`` (run every segment as this board; default
    each configuration's ``board``, else esp32), ``timing`` (the board's timing model: RTOS-tick
    waits and compute stretched by ``cpu_factor``, default measured, tools/emulator/timing.py),
    ``line_baud`` (the first segment's UART rate: bytes the host sends at another rate, as set
    on the host port by termios, arrive garbled, as on a real UART; default: any rate works),
    ``mpy`` (run the modules precompiled, as ``ucr flash`` deploys them, the default; False:
    source files, compiled by each segment at import).
    """

    def __init__(
        self,
        n: int,
        workdir: str | os.PathLike | None = None,
        *,
        firmware_dir: str | os.PathLike = DEFAULT_FIRMWARE_DIR,
        protocol_dir: str | os.PathLike | None = DEFAULT_PROTOCOL_DIR,
        config_for: ConfigSource = None,
        faults_for: Callable[[int], str | None] | None = None,
        uids: Sequence[str] | None = None,
        heap: str | None = None,
        reuse_dirs: bool = False,
        seed: int = 0,
        restart_delay_s: float = 0.05,
        board: str | None = None,
        timing: bool = False,
        cpu_factor: float | None = None,
        line_baud: int | None = None,
        mpy: bool = True,
    ) -> None:
        if not isinstance(n, int) or n < 1:
            raise EmulatorError(f"a chain needs at least one segment, got {n!r}")
        if uids is not None and len(uids) != n:
            raise EmulatorError(f"{len(uids)} uids given for {n} segments")
        self.n = n
        self._heap = heap
        self._line_baud = line_baud
        self._mpy = mpy
        if board is not None and board not in boards.BOARDS:
            raise EmulatorError(f"unknown board {board!r} (boards: {', '.join(boards.NAMES)})")
        self.board = board
        self.timing = timing
        self._cpu_factor = cpu_factor
        self._binary = micropython_binary()
        self._restart_delay_s = restart_delay_s
        self._closed = False
        self._closing = threading.Event()
        self._own_workdir = workdir is None
        self.workdir = Path(tempfile.mkdtemp(prefix="ucr-emu-") if workdir is None else workdir)
        self._proxy = Proxy()
        self._supervisor: threading.Thread | None = None
        self._segments: list[_Segment] = []
        self._links: list[_Link] = []
        self._host_silenced = False
        atexit.register(self.close)
        try:
            self._build(
                n, Path(firmware_dir), protocol_dir, config_for, faults_for, uids, reuse_dirs, seed
            )
            self._proxy.start()
            for seg in self._segments:
                self._spawn(seg)
            self._supervisor = threading.Thread(
                target=self._supervise, name="ucr-emulator-supervisor", daemon=True
            )
            self._supervisor.start()
        except BaseException:
            self.close()
            raise

    # -- construction ---------------------------------------------------------------------------
    def _build(
        self, n, firmware_dir, protocol_dir, config_for, faults_for, uids, reuse_dirs, seed
    ) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        prefix = secrets.token_hex(4)
        # Directories count from 1 like everything a user reads ("segment 1: … dir …/seg1"). A
        # --keep workdir made before (seg0, seg1, …: 0-based) keeps its names, so a reused flash
        # never lands on the neighbouring segment.
        first = 0 if reuse_dirs and (self.workdir / "seg0").is_dir() else 1
        for k in range(n):
            seg_dir = self.workdir / f"seg{k + first}"
            uid = uids[k] if uids is not None else f"{prefix}{k:04x}"
            if not (reuse_dirs and (seg_dir / "main.py").is_file()):
                populate_segment_dir(
                    seg_dir,
                    firmware_dir=firmware_dir,
                    protocol_dir=None if protocol_dir is None else Path(protocol_dir),
                    config=self._config(config_for, k),
                    mpy=self._mpy,
                )
            seg = _Segment(k, seg_dir, uid)
            seg.faults = faults_for(k) if faults_for is not None else None
            seg.board = self._board_of(seg_dir)
            seg.cpu_factor = self.cpu_factor(seg.board) if self.timing else 1.0
            self._segments.append(seg)
        proxy = self._proxy
        self._host = proxy.add_end("host")
        upper = self._host
        for k, seg in enumerate(self._segments):
            seg.up = proxy.add_end(f"seg{k}.up")
            seg.down = proxy.add_end(f"seg{k}.down")
            link = _Link(k, upper, seg.up, seed * 1000 + k)
            proxy.connect(link.upper, link.down, link.lower)
            proxy.connect(link.lower, link.up, link.upper)
            self._links.append(link)
            upper = seg.down
            # REPL: process side (controlling tty, Ctrl-C -> SIGINT) and user side (mpremote).
            seg.repl_inner = proxy.add_end(f"seg{k}.repl.proc", isig=True)
            seg.repl_outer = proxy.add_end(f"seg{k}.repl")
            to_proc, from_proc = Pipe(f"seg{k}.repl.in"), Pipe(f"seg{k}.repl.out")
            proxy.connect(seg.repl_outer, to_proc, seg.repl_inner)
            proxy.route(from_proc, seg.repl_outer)
            seg.repl_to_proc, seg.repl_from_proc = to_proc, from_proc
            seg.repl_inner.on_read = self._tee(seg.log, from_proc, seg)
        # The tip's downstream port has nothing plugged in: its bytes are read and dropped.
        self._segments[-1].down.on_read = None
        if self._line_baud is not None:
            self._host.on_read = _baud_gate(self._host, self._line_baud, self._host.on_read)

    @staticmethod
    def _tee(
        log: RingLog, pipe: Pipe, seg: _Segment | None = None
    ) -> Callable[[bytes, float], None]:
        def on_read(data: bytes, now: float) -> None:
            log.add(data)
            if seg is not None:  # which REPL the process shows: the later marker wins
                raw, friendly = data.rfind(_RAW_BANNER), data.rfind(b">>> ")
                if raw >= 0 or friendly >= 0:
                    seg.raw_repl = raw > friendly
                if seg.to_raw and friendly >= 0:
                    # only now: Ctrl-A sent before the REPL set up its terminal would be flushed
                    seg.to_raw = False
                    seg.repl_to_proc.feed(b"\x01", now)
            pipe.feed(data, now)

        return on_read

    @staticmethod
    def _config(config_for: ConfigSource, k: int) -> dict | None:
        """Segment ``k``'s config.json content; None: no file (``NO_CONFIG``). Without any
        ``config_for`` every segment gets ``default_config()``, written out."""
        if config_for is None:
            return default_config()
        if callable(config_for):
            return config_for(k)
        return config_for[k]

    def _board_of(self, seg_dir: Path) -> str:
        """The board segment ``seg_dir`` runs as: ``board`` if given, else its config's."""
        if self.board is not None:
            return self.board
        try:
            cfg = json.loads((seg_dir / "config.json").read_text())
        except (OSError, ValueError):
            cfg = {}
        name = cfg.get("board") if isinstance(cfg, dict) else None
        if not isinstance(name, str) or name not in boards.BOARDS:
            driver = cfg.get("servo_driver") if isinstance(cfg, dict) else None
            name = boards.default_board(driver)
        return name

    def cpu_factor(self, board: str) -> float:
        """The timing model's CPU factor for ``board`` (given, or measured once on this host)."""
        if self._cpu_factor is not None:
            return self._cpu_factor
        from tools.emulator.timing import cpu_factor  # noqa: PLC0415 - runs the VM once

        return cpu_factor(board)

    # -- processes ------------------------------------------------------------------------------
    def _spawn(self, seg: _Segment) -> None:
        env = dict(os.environ)
        env["MICROPYPATH"] = f".frozen:{seg.dir}"
        env["UCR_UP_PORT"] = seg.up.path
        env["UCR_DOWN_PORT"] = seg.down.path
        env["UCR_UID"] = seg.uid
        env.pop("UCR_FAULTS", None)
        if seg.faults:
            env["UCR_FAULTS"] = seg.faults
        for key in ("UCR_BOARD", "UCR_TIMING", "UCR_CPU_FACTOR"):
            env.pop(key, None)
        if self.board is not None:
            env["UCR_BOARD"] = self.board
        if self.timing:
            env["UCR_TIMING"] = "1"
            env["UCR_CPU_FACTOR"] = f"{seg.cpu_factor:.3f}"
        heap = self._heap or f"{boards.profile(seg.board)['heap'] // 1024}k"
        seg.repl_inner.reset_terminal()  # a killed REPL leaves ISIG off: Ctrl-C must work again
        seg.repl_inner.flush_input()
        fd = seg.repl_inner.slave
        raw_boot, seg.raw_boot, seg.raw_repl, seg.to_raw = seg.raw_boot, False, False, False
        script = [] if raw_boot else ["-i", "main.py"]
        if raw_boot:  # a board soft-reset in its raw REPL says so and stays in the raw REPL
            seg.repl_from_proc.feed(b"MPY: soft reboot\r\n", time.monotonic())
            seg.to_raw = True
        seg.proc = subprocess.Popen(
            [self._binary, "-X", f"heapsize={heap}", *script],
            cwd=seg.dir,
            env=env,
            stdin=fd,
            stdout=fd,
            stderr=fd,
            close_fds=True,
            preexec_fn=_child_setup,  # noqa: PLW1509 - only async-signal-safe calls
        )
        seg.started_at = time.monotonic()

    def _supervise(self) -> None:
        while not self._closing.wait(0.02):
            for seg in self._segments:
                with self._proxy._lock:
                    if self._closing.is_set():
                        return
                    proc = seg.proc
                    if proc is None:
                        if seg.powered and seg.retry_at and time.monotonic() >= seg.retry_at:
                            self._respawn(seg)  # an earlier start failed
                        continue
                    if not seg.powered or proc.poll() is None:
                        continue
                    seg.exit_codes.append(proc.returncode)
                    # The REPL mode it was left in is in its last output, which the proxy
                    # thread may not have read yet (Ctrl-B then Ctrl-D: the friendly prompt,
                    # then the exit): read it first, else a stale "raw" restarts it without
                    # main.py, silent on the chain (a failed flash's reset under load did).
                    self._proxy.drain(seg.repl_inner)
                    # Ctrl-D in the raw REPL ends the process normally: a raw-REPL soft reset
                    seg.raw_boot = seg.raw_repl and proc.returncode == 0
                    # A process that dies right after starting (broken firmware) is retried slowly.
                    quick = time.monotonic() - seg.started_at < 0.5
                    seg.proc = None
                if quick:
                    time.sleep(0.5)
                elif self._restart_delay_s:
                    time.sleep(self._restart_delay_s)
                with self._proxy._lock:
                    if self._closing.is_set() or not seg.powered or seg.proc is not None:
                        continue
                    self._respawn(seg)

    def _respawn(self, seg: _Segment) -> None:
        """Start the segment again (counted); a failed start is retried 0.5 s later."""
        seg.restarts += 1
        seg.retry_at = 0.0
        try:
            self._spawn(seg)
        except OSError as exc:  # e.g. fork failed under memory pressure
            seg.proc = None
            seg.spawn_errors.append(str(exc))
            seg.retry_at = time.monotonic() + 0.5

    # -- public API -----------------------------------------------------------------------------
    def __enter__(self) -> EmulatedChain:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def host_port(self) -> str:
        """Pty path the host opens (pyserial ``serial_for_url`` works on it)."""
        return self._host.path

    def repl_port(self, k: int) -> str:
        """Pty path of segment ``k``'s REPL (what mpremote opens)."""
        return self._seg(k).repl_outer.path

    def board_of(self, k: int) -> str:
        """The board segment ``k`` runs as."""
        return self._seg(k).board

    def cpu_factor_of(self, k: int) -> float:
        """Segment ``k``'s CPU factor under the timing model (1.0 without it)."""
        return self._seg(k).cpu_factor

    def segment_dir(self, k: int) -> Path:
        """Segment ``k``'s flash directory (firmware, protocol/, config.json)."""
        return self._seg(k).dir

    def uid(self, k: int) -> str:
        return self._seg(k).uid

    def pid(self, k: int) -> int | None:
        proc = self._seg(k).proc
        return proc.pid if proc is not None else None

    def repl_output(self, k: int) -> str:
        """The last ~16 KiB the segment printed on its REPL (tracebacks, banners)."""
        with self._proxy._lock:
            return self._seg(k).log.text()

    def unplug(self, k: int) -> None:
        """Pull the cable between segment ``k`` and its upstream side (host or segment k-1).

        Bytes are dropped both ways on link ``k``, so the chain is cut there: segments k.. n-1 are
        unreachable until :meth:`plug`.
        """
        link = self._link(k)
        self._proxy.call(lambda: self._set_plugged(link, False))

    def plug(self, k: int) -> None:
        """Plug segment ``k`` back in (link ``k`` carries bytes again)."""
        link = self._link(k)
        self._proxy.call(lambda: self._set_plugged(link, True))

    def _set_plugged(self, link: _Link, plugged: bool) -> None:
        link.plugged = plugged
        link.up.set_enabled(plugged)
        link.down.set_enabled(plugged and not (link.index == 0 and self._host_silenced))

    def set_link(
        self,
        k: int,
        *,
        baud: int | None | bool = False,
        latency: float | None = None,
        corrupt_rate: float | None = None,
        direction: str = "both",
        seed: int | None = None,
    ) -> None:
        """Set link ``k``'s baud throttle (None = unthrottled), latency (s), corruption rate (0..1).

        ``direction`` is "down" (towards the tip), "up" (towards the host) or "both". Arguments
        left out keep their value.
        """
        link = self._link(k)
        pipes = {"down": [link.down], "up": [link.up], "both": [link.down, link.up]}.get(direction)
        if pipes is None:
            raise EmulatorError(f"direction must be 'down', 'up' or 'both', got {direction!r}")

        def apply() -> None:
            for pipe in pipes:
                pipe.configure(baud=baud, latency_s=latency, corrupt_rate=corrupt_rate, seed=seed)

        try:
            self._proxy.call(apply)
        except ValueError as exc:
            raise EmulatorError(str(exc)) from exc

    def set_all_links(self, **settings: Any) -> None:
        """:meth:`set_link` on every link."""
        for k in range(self.n):
            self.set_link(k, **settings)

    def inject(self, k: int, data: bytes, *, direction: str = "down") -> None:
        """Put raw bytes on link ``k`` as if the upper ("down") or lower ("up") end sent them."""
        link = self._link(k)
        if direction not in ("down", "up"):
            raise EmulatorError(f"direction must be 'down' or 'up', got {direction!r}")
        pipe = link.down if direction == "down" else link.up
        self._proxy.call(lambda: pipe.feed(bytes(data), time.monotonic()))

    def kill_host_link(self) -> None:
        """The host falls silent: nothing it writes reaches segment 0 (it still hears the chain)."""
        self._host_silenced = True
        self._proxy.call(lambda: self._set_plugged(self._links[0], self._links[0].plugged))

    def restore_host_link(self) -> None:
        """Undo :meth:`kill_host_link`."""
        self._host_silenced = False
        self._proxy.call(lambda: self._set_plugged(self._links[0], self._links[0].plugged))

    def set_faults(self, k: int, spec: str | None) -> None:
        """UCR_FAULTS for segment ``k`` from its next (re)start."""
        self._seg(k).faults = spec

    def restart(self, k: int, *, timeout: float = 5.0) -> None:
        """Reboot segment ``k``: kill its process; the supervisor starts a fresh one (counted)."""
        seg = self._seg(k)
        with self._proxy._lock:
            proc = seg.proc
            before = seg.restarts
        if proc is not None and proc.poll() is None:
            proc.kill()
        self._wait(
            lambda: seg.restarts > before and seg.proc is not None,
            timeout,
            f"segment {k} did not restart",
        )

    def power_off(self, k: int) -> None:
        """Switch segment ``k`` off: its process is stopped and not restarted until power_on."""
        seg = self._seg(k)
        with self._proxy._lock:
            seg.powered = False
            proc = seg.proc
            seg.proc = None
        if proc is not None:
            _stop_process(proc)

    def power_on(self, k: int) -> None:
        seg = self._seg(k)
        with self._proxy._lock:
            if seg.powered and seg.proc is not None:
                return
            seg.powered = True
            seg.restarts += 1
            seg.raw_boot = False  # power-on: boot.py and main.py run
            self._spawn(seg)

    def wait_restarts(self, k: int, count: int, timeout: float = 5.0) -> None:
        """Block until segment ``k`` has been restarted at least ``count`` times in total."""
        seg = self._seg(k)
        self._wait(
            lambda: seg.restarts >= count and seg.proc is not None,
            timeout,
            f"segment {k} restarted {seg.restarts} times, expected {count}",
        )

    def stats(self) -> dict:
        """Counters: per link (plug state, settings, bytes in/out, dropped, corrupted) and per
        segment (pid, restarts, exit codes)."""
        if self._proxy.error is not None:
            raise EmulatorError(f"emulator proxy thread failed: {self._proxy.error!r}")
        with self._proxy._lock:
            return {
                "host_port": self._host.path,
                "host_silenced": self._host_silenced,
                "links": [
                    {
                        "index": link.index,
                        "plugged": link.plugged,
                        "down": link.down.stats(),
                        "up": link.up.stats(),
                        "overrun": link.upper.overrun + link.lower.overrun,
                    }
                    for link in self._links
                ],
                "segments": [
                    {
                        "index": seg.index,
                        "uid": seg.uid,
                        "dir": str(seg.dir),
                        "repl_port": seg.repl_outer.path,
                        "pid": seg.proc.pid if seg.proc is not None else None,
                        "running": seg.proc is not None and seg.proc.poll() is None,
                        "powered": seg.powered,
                        "restarts": seg.restarts,
                        "exit_codes": list(seg.exit_codes),
                        "spawn_errors": list(seg.spawn_errors),
                    }
                    for seg in self._segments
                ],
            }

    def close(self) -> None:
        """Stop every process, the threads, close every pty; remove a temporary workdir."""
        if self._closed:
            return
        self._closed = True
        self._closing.set()
        if self._supervisor is not None and self._supervisor.is_alive():
            self._supervisor.join(timeout=2.0)
        for seg in self._segments:
            if seg.proc is not None:
                _stop_process(seg.proc)
        self._proxy.close()
        if self._own_workdir:
            shutil.rmtree(self.workdir, ignore_errors=True)
        atexit.unregister(self.close)

    # -- helpers --------------------------------------------------------------------------------
    def _seg(self, k: int) -> _Segment:
        if not isinstance(k, int) or not 0 <= k < self.n:
            raise EmulatorError(f"segment position must be 0..{self.n - 1}, got {k!r}")
        return self._segments[k]

    def _link(self, k: int) -> _Link:
        if not isinstance(k, int) or not 0 <= k < self.n:
            raise EmulatorError(f"link index must be 0..{self.n - 1}, got {k!r}")
        return self._links[k]

    @staticmethod
    def _wait(cond: Callable[[], bool], timeout: float, message: str) -> None:
        end = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > end:
                raise EmulatorError(message)
            time.sleep(0.01)


def _stop_process(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL after 1 s; always reaped."""
    if proc.poll() is None:
        try:
            proc.terminate()
            proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=2.0)
        except ProcessLookupError:
            pass
    else:
        proc.wait()
