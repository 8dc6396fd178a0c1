"""Connecting again to a daemon that went away: one back-off for every long-running API client
(``ucr view``'s live source, the ``ucr zenoh`` bridge). The first attempt waits
:data:`RECONNECT_FIRST_S`, each failure multiplies the wait by :data:`RECONNECT_FACTOR`, up to
:data:`RECONNECT_MAX_S`: a restarting daemon is found within a second, an absent one costs a
connection attempt every few seconds."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

RECONNECT_FIRST_S, RECONNECT_FACTOR, RECONNECT_MAX_S = 0.5, 2.0, 5.0


def reconnect(
    connect: Callable[[], Any],
    stop: threading.Event,
    on_retry: Callable[[str, int, float], None],
    tick: Callable[[], None] | None = None,
    tick_s: float = 1.0,
) -> tuple[Any, int] | None:
    """``connect()`` again and again with the back-off until it returns: (its result, the
    attempt that made it); None once ``stop`` is set. ``on_retry(why, attempt, next_wait_s)``
    after each failure; ``tick()`` every ``tick_s`` while waiting (to keep saying that the
    daemon is away)."""
    delay, attempt = RECONNECT_FIRST_S, 0
    while True:
        end = time.monotonic() + delay
        while (left := end - time.monotonic()) > 0:
            if stop.wait(min(left, tick_s)):
                return None
            if tick is not None:
                tick()
        attempt += 1
        try:
            return connect(), attempt
        except Exception as exc:  # noqa: BLE001 - any failure: said, retried
            delay = min(delay * RECONNECT_FACTOR, RECONNECT_MAX_S)
            on_retry(str(exc) or type(exc).__name__, attempt, delay)
