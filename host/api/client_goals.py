"""The client's trajectory-goal helpers (:mod:`host.api.client`): progress callbacks run on a
thread of their own, so a callback may call the client (on the reader thread, which delivers the
replies, a call from a callback waited out its whole timeout), and the checks of the numbers a
script passes to :func:`~host.api.client.connect`."""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Callable
from typing import Any

from host.api.client_errors import ApiConnectionError

log = logging.getLogger("ucr.api.client")

#: How long a finished wait gives the goal's last progress callbacks to run (s).
FLUSH_S = 5.0


class Callbacks:
    """Runs ``progress`` callbacks in order on one thread, started at the first one."""

    def __init__(self) -> None:
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()

    def put(self, fn: Callable[[dict], None], status: dict) -> None:
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(
                    target=self._run, name="ucr-api-callbacks", daemon=True
                )
                self._thread.start()
        self._q.put((fn, status))

    def flush(self) -> None:
        """Wait (at most :data:`FLUSH_S`) until the callbacks queued so far have run; at once
        from a callback itself."""
        th = self._thread
        if th is None or threading.current_thread() is th:
            return
        done = threading.Event()
        self._q.put(done)
        done.wait(FLUSH_S)

    def close(self) -> None:
        if self._thread is not None:
            self._q.put(None)

    def _run(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            if isinstance(item, threading.Event):
                item.set()
                continue
            fn, status = item
            try:
                fn(status)
            except Exception:  # noqa: BLE001 - a script's callback: said, never fatal
                log.warning("a trajectory progress callback raised", exc_info=True)


def final_or_raise(goal: Any, status: dict) -> dict:
    """A goal's final status; :class:`ApiConnectionError` when the API could only say that the
    daemon went away (the goal's end is unknown), not a status that looks like a result."""
    if status.get("state") == "unknown" and status.get("error"):
        raise ApiConnectionError(
            f"trajectory {goal}: {status['error']}; how the goal ended is unknown"
        )
    return status


def positive_seconds(value: Any, what: str = "timeout") -> float:
    """``value`` as a positive, finite number of seconds, else ValueError naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{what} must be a number of seconds, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be a positive number of seconds, got {value!r}")
    return float(value)
