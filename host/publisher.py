"""State publication: fan-out of published messages (cJSB joint states, cRSP transforms, events,
topology) to subscriber queues, and the publisher thread that runs work handed over by the control
cycle (e.g. cRSP's FK) so it never lengthens a cycle.

Neither can stall the loop: a full subscriber queue drops its oldest message, a full publisher
queue drops the new work; both are counted (``Fanout.dropped``, ``PublisherThread.dropped``).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger("ucr.daemon")

KINDS = ("joint_states", "transforms", "event", "topology")


class PublisherThread:
    """Runs work handed over by the control cycle (e.g. cRSP's FK) in its own thread, so that work
    never lengthens a cycle. Bounded: when it falls behind, new work is dropped and counted."""

    def __init__(self, maxsize: int = 8):
        self._q: queue.Queue = queue.Queue(maxsize=maxsize)
        self._thread: threading.Thread | None = None
        self.done = 0
        self.dropped = 0
        self.busy_s = 0.0

    def start(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._run, name="ucr-publisher", daemon=True)
            self._thread.start()

    def stop(self, timeout: float = 1.0) -> None:
        if self._thread is not None:
            try:
                self._q.put(None, timeout=timeout)
            except queue.Full:
                pass
            self._thread.join(timeout)
            self._thread = None

    def submit(self, fn: Callable[[], None]) -> None:
        if self._thread is None:
            fn()  # not started (e.g. timed by a benchmark): run inline
            return
        try:
            self._q.put_nowait(fn)
        except queue.Full:
            self.dropped += 1

    def stats(self) -> dict[str, Any]:
        mean = self.busy_s / self.done * 1e6 if self.done else 0.0
        return {"done": self.done, "dropped": self.dropped, "mean_us": mean}

    def _run(self) -> None:
        while True:
            fn = self._q.get()
            if fn is None:
                return
            t0 = time.perf_counter()
            try:
                fn()
            except Exception:  # noqa: BLE001 - a failing publisher must not stop the others
                log.exception("publisher task failed")
            self.busy_s += time.perf_counter() - t0
            self.done += 1


class Fanout:
    """Subscriber queues by message kind; ``publish`` never blocks (a full queue drops its
    oldest message). ``emit_event`` also keeps the last 50 events for ``recent_events``."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.subs: dict[Any, set[str]] = {}
        self.dropped = 0
        self.recent_events: deque[dict] = deque(maxlen=50)

    def subscribe(
        self, kinds: list[str] | tuple[str, ...] | str, maxsize: int = 1000, into: Any = None
    ) -> Any:
        """A queue receiving published messages of these kinds (joint_states, transforms,
        event(s), topology). Full queues drop their oldest message. ``into``: a queue-like
        object of the caller's to use instead (``put_nowait``/``get_nowait`` raising
        ``queue.Full``/``queue.Empty``; called from the publishing thread, it must never block:
        the API bridge's feed, host/api/feed.py)."""
        if isinstance(kinds, str):
            kinds = [kinds]
        want = {"event" if k == "events" else k for k in kinds}
        bad = want - set(KINDS)
        if bad or not want:
            raise ValueError(
                f"unknown subscription kind(s) {sorted(bad)} (known: {', '.join(KINDS)})"
            )
        q = queue.Queue(maxsize=maxsize) if into is None else into
        with self._lock:
            self.subs[q] = want
        return q

    def unsubscribe(self, q: queue.Queue) -> None:
        with self._lock:
            self.subs.pop(q, None)

    def publish(self, msg: dict) -> None:
        kind = msg.get("kind")
        with self._lock:
            subs = [q for q, kinds in self.subs.items() if kind in kinds]
        for q in subs:
            try:
                q.put_nowait(msg)
            except queue.Full:
                try:  # drop the oldest: a slow subscriber never blocks the loop
                    q.get_nowait()
                    q.put_nowait(msg)
                except (queue.Empty, queue.Full):
                    pass
                self.dropped += 1

    def emit_event(self, event: str, message: str = "", **fields: Any) -> None:
        msg = {"kind": "event", "t": time.monotonic(), "event": event, "message": message, **fields}
        # kept without a goal's waypoint lists: 50 events of 500 waypoints would keep ~10^5
        # objects alive for the garbage collector to traverse (host/realtime.freeze_heap)
        self.recent_events.append(
            {k: v for k, v in msg.items() if k != "waypoints"} if "waypoints" in msg else msg
        )
        self.publish(msg)
