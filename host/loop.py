"""Fixed-rate loop (read → update → write) in its own thread, with timing statistics.

Per cycle it records: the period (start-to-start, s), the jitter (start minus scheduled start, s),
the compute time of the cycle without bus I/O wait (s, reported by the step function), and
overruns (a cycle that ended after the next scheduled start; of them, those whose own duration
exceeded a period while their compute did not: the wait for the chain's STATEs alone overran,
``overruns_waiting_on_chain``). The schedule is absolute
(start + k·period), so lateness never accumulates; after an overrun the late cycle runs at once
and whole slots already missed are skipped instead of bursting to catch up.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np

from host import realtime


class Stats:
    """Ring buffers of the last ``window`` samples plus running counts."""

    def __init__(self, window: int = 5000):
        self.period: deque[float] = deque(maxlen=window)
        self.jitter: deque[float] = deque(maxlen=window)
        self.compute: deque[float] = deque(maxlen=window)
        self.cycles = 0
        self.overruns = 0
        self.overruns_chain = 0  # of them: the wait for the chain alone overran
        self.skipped = 0
        self.lock = threading.Lock()

    @staticmethod
    def _summary(values: deque[float], scale: float) -> dict[str, float]:
        if not values:
            return {"mean": 0.0, "p99": 0.0, "max": 0.0}
        a = np.fromiter(values, dtype=float) * scale
        return {"mean": float(a.mean()), "p99": float(np.percentile(a, 99)), "max": float(a.max())}

    def snapshot(self, target_period: float) -> dict:
        """Statistics in µs (period, |jitter|, compute) plus counts."""
        with self.lock:
            per, jit, comp = list(self.period), [abs(j) for j in self.jitter], list(self.compute)
            cycles, over, skipped = self.cycles, self.overruns, self.skipped
            over_chain = self.overruns_chain
        return {
            "rate_hz": 1.0 / target_period,
            "target_period_us": target_period * 1e6,
            "cycles": cycles,
            "overruns": over,
            "overruns_waiting_on_chain": over_chain,
            "skipped_slots": skipped,
            "period_us": self._summary(deque(per), 1e6),
            "jitter_us": self._summary(deque(jit), 1e6),
            "compute_us": self._summary(deque(comp), 1e6),
            "window": len(per),
        }

    def reset(self) -> None:
        with self.lock:
            self.period.clear()
            self.jitter.clear()
            self.compute.clear()
            self.cycles = self.overruns = self.overruns_chain = self.skipped = 0


class FixedRateLoop:
    """Calls ``step()`` every ``period`` s in a thread. ``step`` returns its compute time (s,
    excluding I/O wait) or None. Exceptions in ``step`` go to ``on_error`` and the loop goes on."""

    def __init__(
        self,
        period: float,
        step: Callable[[], float | None],
        on_error: Callable[[BaseException], None] | None = None,
        name: str = "ucr-loop",
    ):
        if not period > 0:
            raise ValueError(f"loop period must be > 0 s, got {period}")
        self.period = period
        self.step = step
        self.on_error = on_error
        self.name = name
        self.stats = Stats()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("loop already started")
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=self.name, daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def set_period(self, period: float, keep_counts: bool = False) -> None:
        """Run at ``period`` s from the next cycle on; the statistics restart (``keep_counts``:
        only the timing windows do, cycle/overrun counts go on)."""
        if not period > 0:
            raise ValueError(f"loop period must be > 0 s, got {period}")
        self.period = period
        if keep_counts:
            with self.stats.lock:
                self.stats.period.clear()
                self.stats.jitter.clear()
                self.stats.compute.clear()
        else:
            self.stats.reset()

    def _run(self) -> None:
        realtime.enter("control loop")  # SCHED_FIFO when configured (host/realtime.py)
        st = self.stats
        nxt = time.perf_counter()
        last_start: float | None = None
        while not self._stop.is_set():
            now = time.perf_counter()
            delay = nxt - now
            if delay > 0:
                # Sleep most of the wait, spin the last 200 µs: sleep() overshoots by ~50–100 µs.
                if delay > 0.0004:
                    time.sleep(delay - 0.0002)
                while time.perf_counter() < nxt:
                    pass
            start = time.perf_counter()
            compute = None
            try:
                compute = self.step()
            except BaseException as exc:  # noqa: BLE001 - the loop must survive a bad cycle
                if self.on_error is not None:
                    self.on_error(exc)
            end = time.perf_counter()
            with st.lock:
                st.cycles += 1
                st.jitter.append(start - nxt)
                if last_start is not None:
                    st.period.append(start - last_start)
                st.compute.append(compute if compute is not None else end - start)
                nxt += self.period
                if end > nxt:
                    # Overrun: run the late slot at once, but skip whole slots already missed.
                    st.overruns += 1
                    # the cycle alone took longer than a period, its compute did not: the wait for
                    # the chain's STATEs made it overrun, however on time it started
                    if compute is not None and compute < self.period < end - start:
                        st.overruns_chain += 1
                    missed = int((end - nxt) / self.period)
                    st.skipped += missed
                    nxt += missed * self.period
            last_start = start
