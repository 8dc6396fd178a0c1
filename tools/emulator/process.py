"""An emulated chain in a process of its own: ``ucr emulate`` driven through its control socket.

Benchmarks of the host side use it so that the host's threads have their interpreter to
themselves, as on a Pi wired to real segments. An :class:`~tools.emulator.EmulatedChain` in the
host's own process runs its proxy thread there, which wakes for every few bytes of a throttled
link and takes the interpreter lock from the link's reader between the STATEs (8 segments at
921600 baud: about 1.5 ms more per round trip on this machine, 2026-11-27).
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tools.emulator.chain import EmulatedChain, EmulatorError

REPO = Path(__file__).resolve().parents[2]


class EmulatorProcess:
    """``n`` emulated segments in a child ``ucr emulate``; ``host_port`` is the chain's port.

    ``timing``: the ESP32 timing model (``--timing-model``). Link settings go through the
    control socket (:meth:`command`, the lines of docs/emulator.md). Close it, or use ``with``.
    """

    def __init__(self, n: int, *, timing: bool = False, boot_timeout_s: float = 60.0) -> None:
        self.n = n
        self.host_port = ""
        self._factor = 1.0
        self._io = self._sock = None
        self._dir = tempfile.TemporaryDirectory(prefix="ucr_emulate_")
        base = Path(self._dir.name)
        self._sock_path = base / "control.sock"
        self._log_path = base / "emulate.log"
        cmd = [sys.executable, "-m", "tools.cli", "emulate", str(n), "--no-stdin",
               "--control-socket", str(self._sock_path)]  # fmt: skip
        if timing:
            cmd.append("--timing-model")
        with open(self._log_path, "wb") as log:  # a file: output never blocks the emulator
            self._proc = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        try:
            self._wait_running(boot_timeout_s)
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            self._sock.connect(str(self._sock_path))
            self._io = self._sock.makefile("rwb")
        except BaseException:
            self.close()
            raise

    def _wait_running(self, timeout_s: float) -> None:
        end = time.monotonic() + timeout_s
        while True:
            text = self._log_path.read_text(errors="replace")
            if "\nrunning;" in "\n" + text and self._sock_path.exists():
                break
            if self._proc.poll() is not None or time.monotonic() > end:
                why = "exited" if self._proc.poll() is not None else f"not up in {timeout_s:.0f} s"
                raise EmulatorError(f"ucr emulate {why}:\n" + "\n".join(text.splitlines()[-20:]))
            time.sleep(0.05)
        for line in text.splitlines():
            if line.startswith("host port: "):
                self.host_port = line.split(": ", 1)[1].strip()
            got = re.search(r" x(\d+(?:\.\d+)?)$", line.rstrip())
            if line.startswith("segment 1:") and got:
                self._factor = float(got.group(1))

    def cpu_factor_of(self, k: int) -> float:
        """The CPU factor of the timing model (every segment is the same board here)."""
        return self._factor

    def command(self, line: str) -> str:
        """One control line (e.g. ``baud 1 921600``); its answer. EmulatorError if refused."""
        if self._io is None:
            raise EmulatorError("the emulator process is closed")
        self._io.write(line.encode() + b"\n")
        self._io.flush()
        answer = []
        while (got := self._io.readline()) not in (b"\n", b""):
            answer.append(got.decode(errors="replace").rstrip())
        text = "\n".join(answer)
        if not answer or text.startswith("error"):
            raise EmulatorError(f"ucr emulate refused {line!r}: {text or 'no answer'}")
        return text

    def set_all_links(self, *, baud: int | None) -> None:
        """Throttle every link to ``baud`` bit/s (None: unthrottled)."""
        for k in range(1, self.n + 1):
            self.command(f"baud {k} {'off' if baud is None else baud}")

    def close(self) -> None:
        if self._io is not None:
            self._io.close()
            self._io = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        if self._proc.poll() is None:
            self._proc.terminate()
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        self._dir.cleanup()

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def emulated_chain(n: int, *, timing: bool = False, where: str = "process"):
    """A chain of ``n`` emulated segments for a benchmark: in a process of its own
    (``where="process"``, :class:`EmulatorProcess`) or in this one (``"thread"``,
    :class:`~tools.emulator.EmulatedChain`, as the tests run it). Use it with ``with``."""
    if where == "process":
        return EmulatorProcess(n, timing=timing)
    if where == "thread":
        return EmulatedChain(n, timing=timing)
    raise ValueError(f"where must be 'process' or 'thread', got {where!r}")
