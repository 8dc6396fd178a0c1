"""Real-time scheduling for the daemon's two time-critical threads (Linux ``SCHED_FIFO``).

The control loop thread and the chain link's reader thread (which hands the loop its STATEs)
each call :func:`enter` when they start; with a priority configured (``realtime_priority`` in
the daemon config, ``ucr daemon --rt-priority``), the calling thread — only that thread — runs
``SCHED_FIFO`` at that priority, so API clients, recordings, the view or a compiler on the same
Pi wait for the loop instead of the loop waiting for them (docs/daemon.md "Real-time
scheduling"; measured with ``benchmarks/bench_api.py --rt-priority``). ``SCHED_RESET_ON_FORK``
keeps it from spreading: a thread or process started by a real-time thread starts normal.

Refused (not root, no ``RLIMIT_RTPRIO``, a sandbox that forbids it) → a warning, and the thread
runs at normal priority: the daemon still works, and :func:`report` says what each thread got.
Priority 0 (the default) leaves scheduling alone.
"""

from __future__ import annotations

import gc
import logging
import os
import threading

log = logging.getLogger("ucr.daemon")

#: Highest priority accepted: 99 is left to the kernel's own watchdog threads.
MAX_PRIORITY = 98

_lock = threading.Lock()
_priority = 0
_state: dict[str, str] = {}


def check_priority(value: int) -> int:
    """``value`` if it is a usable priority (0 = off, 1..MAX_PRIORITY), else ValueError."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"real-time priority must be an integer, got {value!r}")
    if not 0 <= value <= MAX_PRIORITY:
        raise ValueError(f"real-time priority must be 0 (off) or 1..{MAX_PRIORITY}, got {value}")
    return value


def configure(priority: int) -> None:
    """Set the priority the time-critical threads take from now on (0: normal scheduling)."""
    global _priority
    with _lock:
        _priority = check_priority(priority)
        _state.clear()


def priority() -> int:
    return _priority


def enter(role: str) -> str:
    """Put the calling thread under the configured policy; return what it got, for humans."""
    prio = _priority
    if not prio:
        got = "normal"
    elif not hasattr(os, "sched_setscheduler"):
        got = "normal (SCHED_FIFO needs Linux)"
    else:
        policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
        try:
            os.sched_setscheduler(0, policy, os.sched_param(prio))  # 0: this thread
            got = f"SCHED_FIFO {prio}"
        except OSError as exc:
            got = f"normal (SCHED_FIFO {prio} refused: {exc.strerror or exc})"
            log.warning(
                "%s thread: cannot run SCHED_FIFO %d (%s); it runs at normal priority. Run as "
                "root, or give the daemon's user an RLIMIT_RTPRIO >= %d (LimitRTPRIO= in the "
                'service unit, docs/daemon.md "Real-time scheduling")',
                role,
                prio,
                exc.strerror or exc,
                prio,
            )
    with _lock:
        _state[role] = got
    return got


def report() -> dict[str, str]:
    """What each time-critical thread got so far: ``{role: "SCHED_FIFO 10" | "normal ..."}``."""
    with _lock:
        return dict(_state)


def freeze_heap() -> int:
    """Keep the cyclic garbage collector's full collections short (call once the daemon is
    built, before its loop starts; docs/daemon.md "Garbage collection").

    A full (generation 2) collection runs in whichever thread's allocation triggers it and
    holds the interpreter lock for as long as it traverses every tracked object — tens of ms in
    the running daemon (benchmarks/bench_goal.py), during which the control loop cannot run.
    ``gc.freeze()`` moves everything alive now (modules, the robot model, controllers, numpy)
    out of the collector's reach for good, so a collection traverses only what came later; the
    ``gc.collect()`` before it frees the garbage there is, so nothing unreachable is frozen.
    Returns the number of objects frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()
