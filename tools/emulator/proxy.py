"""Pseudo-terminal ends and the proxy thread that moves bytes between them.

Every port of the emulator (the host port, each segment's UART ports, each REPL) is a pty pair:
a user of the port opens the *slave path* (pyserial, mpremote, the firmware's HAL); the emulator
holds the *master* and copies bytes between masters through :class:`~tools.emulator.pipe.Pipe`
objects, which is where plug state, throttling, latency and corruption happen.

The emulator also keeps one fd of each slave open: closing the last user of a slave would make the
master report EIO/HUP until someone reopens it, and the slave's termios settings (raw mode, set here
before anyone connects so no byte is ever echoed or line-edited) would be lost.
"""

from __future__ import annotations

import errno
import os
import selectors
import termios
import threading
import time
from collections import deque
from collections.abc import Callable

from tools.emulator.pipe import Pipe

#: Bytes waiting for a slow reader of one master before new ones are dropped (UART overrun).
MAX_PENDING = 64 * 1024
#: select(2) watches only fds below FD_SETSIZE; past it the proxy uses the default selector.
SELECT_MAX_FD = 1024


def _raw_attrs(attrs: list, *, isig: bool) -> list:
    """termios attributes for a binary port: no echo, no line editing, no CR/LF translation.

    ``isig`` keeps Ctrl-C -> SIGINT (with NOFLSH), which is how a unix-port MicroPython running
    ``main.py`` gets its KeyboardInterrupt when mpremote sends Ctrl-C to the REPL.
    """
    attrs = list(attrs)
    attrs[0] = 0  # iflag: no ICRNL, no IXON, ...
    attrs[1] = 0  # oflag: no OPOST (no \n -> \r\n: mpremote matches exact byte strings)
    attrs[2] = (attrs[2] & ~(termios.CSIZE | termios.PARENB)) | termios.CS8 | termios.CREAD
    attrs[3] = (termios.ISIG | termios.NOFLSH) if isig else 0
    cc = list(attrs[6])
    cc[termios.VMIN] = 1
    cc[termios.VTIME] = 0
    attrs[6] = cc
    return attrs


class PtyEnd:
    """One pty pair: ``path`` is what users open; the emulator reads/writes ``master``."""

    def __init__(self, name: str, *, isig: bool = False) -> None:
        self.name = name
        self.isig = isig
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self.reset_terminal()
        os.set_blocking(self.master, False)
        self.pending = bytearray()
        self.overrun = 0  # bytes dropped because the reader of this port did not keep up
        self.on_read: Callable[[bytes, float], None] | None = None
        self.closed = False

    def reset_terminal(self) -> None:
        """The pty's modes as set up (raw; ``isig``: Ctrl-C is SIGINT). A process's REPL changes
        them (the unix port's friendly REPL turns ISIG off) and a killed one cannot restore them:
        a restart calls this, as a board's UART comes up the same after every reset."""
        attrs = _raw_attrs(termios.tcgetattr(self.slave), isig=self.isig)
        termios.tcsetattr(self.slave, termios.TCSANOW, attrs)

    def flush_input(self) -> None:
        """Discard bytes waiting to be read from the slave (e.g. before a board restarts)."""
        termios.tcflush(self.slave, termios.TCIFLUSH)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class Proxy:
    """A thread copying bytes between pty masters through pipes, with timers for delayed bytes.

    All public methods are thread-safe (one lock); ``call(fn)`` runs ``fn`` under that lock.
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        # select(2) takes a µs timeout; epoll and poll round it up to whole ms, which would delay
        # every throttled release by up to 1 ms per hop. The proxy watches a few dozen fds.
        self._sel = selectors.SelectSelector()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._ends: list[PtyEnd] = []
        self._routes: list[tuple[Pipe, PtyEnd]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ucr-emulator-proxy", daemon=True)
        self.error: BaseException | None = None

    # -- wiring ---------------------------------------------------------------------------------
    def add_end(self, name: str, *, isig: bool = False) -> PtyEnd:
        with self._lock:
            end = PtyEnd(name, isig=isig)
            self._ends.append(end)
            if isinstance(self._sel, selectors.SelectSelector) and end.master >= SELECT_MAX_FD:
                self._use_default_selector()
            self._sel.register(end.master, selectors.EVENT_READ, end)
            return end

    def _use_default_selector(self) -> None:
        """Move every registration to epoll/poll (ms timeouts, but no fd-number limit)."""
        new = selectors.DefaultSelector()
        for key in self._sel.get_map().values():
            new.register(key.fileobj, key.events, key.data)
        old, self._sel = self._sel, new
        old.close()  # a select() running on it returns by its timeout; the next loop uses `new`
        self._wake()

    def connect(self, src: PtyEnd, pipe: Pipe, dst: PtyEnd) -> None:
        """Bytes read from ``src`` travel through ``pipe`` and are written to ``dst``."""
        with self._lock:
            src.on_read = pipe.feed
            self._routes.append((pipe, dst))
            self._wake()

    def route(self, pipe: Pipe, dst: PtyEnd) -> None:
        """Deliver what ``pipe`` releases to ``dst`` (for pipes fed by something else)."""
        with self._lock:
            self._routes.append((pipe, dst))
            self._wake()

    def start(self) -> None:
        self._thread.start()

    def call(self, fn: Callable[[], object]) -> object:
        """Run ``fn`` under the proxy lock and wake the loop (settings take effect at once)."""
        with self._lock:
            result = fn()
            self._wake()
            return result

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"x")
        except BlockingIOError:
            pass

    # -- loop -----------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                with self._lock:
                    timeout = self._next_timeout(time.monotonic())
                events = self._sel.select(timeout)
                with self._lock:
                    now = time.monotonic()
                    for key, mask in events:
                        end = key.data
                        if end is None:
                            try:
                                os.read(self._wake_r, 4096)
                            except BlockingIOError:
                                pass
                            continue
                        if mask & selectors.EVENT_READ:
                            self._read(end, now)
                        if mask & selectors.EVENT_WRITE:
                            self._flush(end)
                    now = time.monotonic()
                    for pipe, dst in self._routes:  # (no call for the idle ones: 30+ pipes)
                        queue = pipe.queue
                        if queue and queue[0][0] <= now:
                            self._write(dst, pipe.due(now))
        except BaseException as exc:  # surfaced by EmulatedChain.stats()/close()
            self.error = exc
            raise

    def _next_timeout(self, now: float) -> float:
        soonest = now + 0.1
        for pipe, _ in self._routes:
            queue = pipe.queue
            if queue and queue[0][0] < soonest:
                soonest = queue[0][0]
        return max(0.0, soonest - now)

    def drain(self, end: PtyEnd) -> None:
        """Read now, on the caller's thread, everything waiting on ``end`` that the loop has not
        read yet, and hand it on as the loop would. For a process that just ended: its last
        output (e.g. the prompt of the REPL mode it was left in) must be seen before it is
        restarted, however late the loop thread gets to run on a loaded host."""
        with self._lock:
            while self._read(end, time.monotonic()):
                pass

    def _read(self, end: PtyEnd, now: float) -> int:
        """Read one chunk from ``end`` and pass it to its reader; return its length (0: none)."""
        try:
            data = os.read(end.master, 4096)
        except BlockingIOError:
            return 0
        except OSError as exc:
            if exc.errno != errno.EIO:
                raise
            return 0
        if data and end.on_read is not None:
            end.on_read(data, now)
        return len(data)

    def _write(self, end: PtyEnd, data: bytes) -> None:
        if end.closed:
            return
        room = MAX_PENDING - len(end.pending)
        if len(data) > room:
            end.overrun += len(data) - max(room, 0)
            data = data[: max(room, 0)]
        end.pending += data
        self._flush(end)

    def _flush(self, end: PtyEnd) -> None:
        if end.closed:
            return
        while end.pending:
            try:
                n = os.write(end.master, end.pending)
            except BlockingIOError:
                break
            except OSError as exc:
                if exc.errno != errno.EIO:
                    raise
                end.overrun += len(end.pending)
                end.pending.clear()
                break
            del end.pending[:n]
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if end.pending else 0)
        self._sel.modify(end.master, events, end)

    # -- teardown -------------------------------------------------------------------------------
    def close(self) -> None:
        self._stop.set()
        self._wake()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        with self._lock:
            for end in self._ends:
                try:
                    self._sel.unregister(end.master)
                except (KeyError, ValueError):
                    pass
                end.close()
            self._sel.close()
            for fd in (self._wake_r, self._wake_w):
                try:
                    os.close(fd)
                except OSError:
                    pass


class RingLog:
    """The last ``size`` bytes seen (a segment's REPL output, for diagnostics)."""

    def __init__(self, size: int = 16384) -> None:
        self._chunks: deque[bytes] = deque()
        self._size = size
        self._len = 0

    def add(self, data: bytes) -> None:
        self._chunks.append(data)
        self._len += len(data)
        while self._len > self._size and len(self._chunks) > 1:
            self._len -= len(self._chunks.popleft())

    def text(self) -> str:
        return b"".join(self._chunks)[-self._size :].decode(errors="replace")
