"""When the API server gives memory back to the OS (docs/api.md "Memory").

Bursts (a crowd of connections, large requests) leave free heap behind that the process would
otherwise keep at its peak. :class:`MemoryRelease` decides, once a second, whether to collect
garbage and return free pages (glibc ``malloc_trim``): once a crowd of 32 or more connections has
shrunk to an eighth; or, after a second without requests, once the requests read since the last
release add up to :data:`RELEASE_AFTER_BYTES` or (in the API's own process only) the process's
resident size has grown by :data:`RELEASE_AFTER_GROWTH` since then (three 10,000-waypoint goals,
2026-11-27: 15 MiB kept, under the byte threshold). A release is a full ``gc.collect()`` holding
the interpreter lock, so it waits for a quiet second and never repeats without new growth; and
in the daemon's process, where the control loop would wait for it, the growth rule is off.
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import os

#: request bytes after which a quiet second returns free memory to the OS
RELEASE_AFTER_BYTES = 8 * 1024 * 1024
#: growth of the resident size (bytes) since the last release after which a quiet second does,
#: in the API's own process (ServerOptions.release_after_growth)
RELEASE_AFTER_GROWTH = 4 * 1024 * 1024


def rss_bytes() -> int | None:
    """This process's resident size (bytes), None where /proc cannot tell."""
    try:
        with open("/proc/self/statm", "rb") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return None


def release_memory() -> None:
    """Collect garbage and return free heap pages to the OS (glibc ``malloc_trim``)."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


class MemoryRelease:
    """The release rule, ticked once a second by the connection janitor; ``growth``: the
    resident-size growth rule's threshold in bytes (0: off)."""

    def __init__(self, growth: int = 0) -> None:
        self.growth = growth
        self.peak = 0  # most TCP connections seen since the last release
        self.seen = self.released = 0  # bytes read: at the last tick, at the last release
        self.floor = rss_bytes()  # resident size after the last release (or at start)

    def tick(self, connections: int, bytes_in: int) -> bool:
        """One second passed with ``connections`` open and ``bytes_in`` read in all; True when
        memory was released now."""
        self.peak = max(self.peak, connections)
        crowd_gone = self.peak >= 32 and connections <= self.peak // 8
        quiet = bytes_in == self.seen
        self.seen = bytes_in
        rss = rss_bytes()
        known = self.growth > 0 and rss is not None and self.floor is not None
        grown = known and rss - self.floor >= self.growth
        read = bytes_in - self.released >= RELEASE_AFTER_BYTES
        if not (crowd_gone or (quiet and (read or grown))):
            return False
        self.peak, self.released = connections, bytes_in
        release_memory()
        self.floor = rss_bytes()
        return True
