"""Link health: a slow or lossy chain lowers the usable loop rate instead of stalling it.

Fed once per cycle with which positions answered the last exchange and how long it took, it keeps
a short window and decides the *usable* period: when replies from some position keep missing
(loss: a reply later than the reply time counts as missing), the loop slows down (period ×2,
never slower than half the segments' watchdog); once every position has answered every exchange
for ``recover_s`` at the lower rate, the loop tries the nominal rate again.
A return that fails at once doubles the clean time asked for next (up to 12 s): a link that
stays bad is not probed at full rate over and over.

One rule slows the loop, on either path (:meth:`LinkHealth.observe` every cycle,
:meth:`LinkHealth.stall` after a silent stretch that found the same chain): a position missed
≥ DEGRADE_LOSS of the exchanges in the window *and* at least DEGRADE_LATE replies arrived late
meanwhile (the caller counts them since that position began to miss, never from longer ago).
The stall path only does not wait for a full window.

Positions in what it reports (``position``, ``link``) count from 1, like every position a user
sees (:mod:`host.positions`): ``link`` k is the cable into the k-th segment. The ``loss`` list
is indexed by chain order.

It decides and reports; the daemon applies the period (loop, reply timeout, supervision).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

DEGRADE_WINDOW = 30  # cycles looked at for loss (a burst of host load is shorter)
DEGRADE_LOSS = 0.6  # a position missing in this share of the window, with at least
DEGRADE_LATE = 3  # this many replies arriving late meanwhile, degrades the link
RECOVER_S = 1.5  # clean time at the lower rate before trying the nominal rate again (s)
#: An exchange that returned this much later than its reply timeout was held up in this process
#: (a garbage collection or another thread holding the interpreter lock delays the link reader
#: and the loop alike), not on the link: its misses say nothing about the link (s).
HOST_STALL_S = 0.002
#: A silent stretch (a stall) within this long of a held-up exchange is the process's, too (s).
HOST_STALL_HOLD_S = 0.5


class LinkHealth:
    """Usable period for a chain whose nominal period is ``period`` (s). ``min_rate_hz``: the
    slowest rate allowed (keeps the segments' watchdogs fed)."""

    def __init__(self, period: float, reply_share: float = 0.8, min_rate_hz: float = 10.0) -> None:
        self.nominal = period
        self.period = period
        self.reply_share = reply_share
        self.min_period = max(period, 1.0 / min_rate_hz)
        self.recover_s = RECOVER_S
        self._answered: deque[tuple[bool, ...]] = deque(maxlen=DEGRADE_WINDOW)
        self._misses: list[int] = []  # per position: exchanges in the window it did not answer
        self._latency: deque[float] = deque(maxlen=50)
        self._clean_since: float | None = None
        self._late_seen: int | None = None
        self._t_restored: float | None = None
        self.degradations = 0
        self.host_stalls = 0  # exchanges left out: held up in this process (HOST_STALL_S)
        self._host_stall_at: float | None = None  # when the last one was seen
        self.last: dict[str, Any] | None = None  # what the last change measured

    @property
    def degraded(self) -> bool:
        return self.period > self.nominal * 1.001

    def reset(self) -> None:
        """Forget the window (a rebuild changes the chain)."""
        self._answered.clear()
        self._misses = []
        self._latency.clear()
        self._clean_since = None

    def observe(
        self,
        answered: list[bool],
        exchange_s: float,
        now: float,
        late_replies: Callable[[], int] = lambda: 1,
        reply_timeout: float | None = None,
    ) -> dict[str, Any] | None:
        """One cycle: ``answered[i]`` whether position i answered; ``exchange_s`` how long
        the exchange waited; ``late_replies()`` a running count of replies that came after
        their exchange ended (asked only when replies miss). Missing replies that do arrive
        late mean a slow link: slowing down helps. Missing replies that never come (a cut, a
        corrupting link) are reported in the loss figures and left to supervision. An exchange
        with misses that returned more than HOST_STALL_S after ``reply_timeout`` (s) was held up
        in this process: it is left out (counted in ``host_stalls``), not taken for the link's.
        Returns a change ``{"period", "change", ...}`` or None."""
        if not answered:
            return None
        if (
            reply_timeout is not None
            and exchange_s > reply_timeout + HOST_STALL_S
            and not all(answered)
        ):
            self.host_stalls += 1
            self._host_stall_at = now
            return None
        if self._answered and len(self._answered[-1]) != len(answered):
            self.reset()
        self._push(tuple(answered))
        if all(answered):
            self._latency.append(exchange_s)
        loss = self.loss()
        worst = max(range(len(loss)), key=loss.__getitem__)
        lossy = len(self._answered) == DEGRADE_WINDOW and loss[worst] >= DEGRADE_LOSS
        late = 0
        if lossy:
            count = late_replies()
            if self._late_seen is None:
                self._late_seen = count
            late = count - self._late_seen
        else:
            self._late_seen = None
        if lossy and late >= DEGRADE_LATE and self.period < self.min_period * 0.999:
            # the first position whose replies miss: the slow link is the one into it (or, for
            # a throughput limit, one before it whose own replies still fit)
            first = next(i for i, x in enumerate(loss) if x >= loss[worst] / 2)
            return self._degrade(first, loss[worst], now)
        if not self.degraded:
            return None
        clean = len(self._answered) == DEGRADE_WINDOW and max(loss) == 0.0
        if not clean:
            self._clean_since = None
            return None
        if self._clean_since is None:
            self._clean_since = now
            return None
        if now - self._clean_since < self.recover_s:
            return None
        p90 = self._latency_p90()
        measured_at = 1.0 / self.period
        self.period = self.nominal
        self._t_restored = now
        self.reset()
        self.last = {
            "position": None,
            "link": None,
            "loss": 0.0,
            "measured_at_hz": round(measured_at, 2),
            "latency_ms": round(p90 * 1e3, 2),
            "usable_rate_hz": round(1.0 / self.period, 2),
            "cause": "recovered",
        }
        return {"period": self.period, "change": "restored", **self.last}

    def _degrade(self, position: int, loss: float, now: float) -> dict[str, Any]:
        """Halve the rate (not below the floor); the change as reported (0-based
        ``position`` in, 1-based ``position``/``link`` out)."""
        p90 = self._latency_p90()
        if self._t_restored is not None and now - self._t_restored < 2 * self.recover_s:
            self.recover_s = min(self.recover_s * 2, 12.0)  # the return failed at once
        self._t_restored = None
        measured_at = 1.0 / self.period  # the rate the loss was measured at
        self.period = min(self.period * 2, self.min_period)
        self.degradations += 1
        self.reset()
        self._late_seen = None
        self.last = {
            "position": position + 1,  # 1-based, as a user reads it
            "link": position + 1,  # the cable into that segment, as the emulator counts links
            "loss": round(loss, 3),
            "measured_at_hz": round(measured_at, 2),
            "latency_ms": round(p90 * 1e3, 2),
            "usable_rate_hz": round(1.0 / self.period, 2),
            "cause": "loss",
        }
        return {"period": self.period, "change": "degraded", **self.last}

    def stall(self, position: int, late: int, now: float) -> dict[str, Any] | None:
        """Supervision found a silent stretch and the very same chain behind it (a stall) at
        0-based ``position``: when that position missed ≥ DEGRADE_LOSS of the exchanges in the
        window so far and ``late`` ≥ DEGRADE_LATE replies (counted since it began to miss)
        arrived late meanwhile, the link is slow — degrade at once, without waiting for a full
        window; unless an exchange was held up in this process less than HOST_STALL_HOLD_S ago
        (:meth:`observe`). Returns a change as :meth:`observe` does."""
        if late < DEGRADE_LATE or self.period >= self.min_period * 0.999:
            return None
        if self._host_stall_at is not None and now - self._host_stall_at < HOST_STALL_HOLD_S:
            return None  # the process was held up meanwhile (see observe), not the link
        loss = self.loss()
        if not 0 <= position < len(loss) or loss[position] < DEGRADE_LOSS:
            return None  # the same threshold as a full window: a few misses are no slow link
        return self._degrade(position, loss[position], now)

    def _push(self, answered: tuple[bool, ...]) -> None:
        """Adds one exchange to the window, keeping the per-position miss counts (the cycle
        pays a few integer operations, not a pass over the window)."""
        if not self._misses:
            self._misses = [0] * len(answered)
        if len(self._answered) == DEGRADE_WINDOW:
            for i, ok in enumerate(self._answered[0]):
                self._misses[i] -= not ok
        self._answered.append(answered)
        for i, ok in enumerate(answered):
            self._misses[i] += not ok

    def _latency_p90(self, at_least: int = 5) -> float:
        """p90 of the recent complete exchanges (s); 0 with fewer than ``at_least`` (or none)."""
        if len(self._latency) < max(1, at_least):
            return 0.0
        ordered = sorted(self._latency)
        return ordered[int(0.9 * (len(ordered) - 1))]

    def loss(self) -> list[float]:
        """Share of the window in which each position did not answer."""
        if not self._answered:
            return []
        n = len(self._answered)
        return [m / n for m in self._misses]

    def snapshot(self) -> dict[str, Any]:
        """For status: nominal and usable rate, per-position loss, exchange latency p90."""
        lat = self._latency_p90(at_least=1) * 1e3 if self._latency else None
        return {
            "degraded": self.degraded,
            "nominal_rate_hz": round(1.0 / self.nominal, 2),
            "usable_rate_hz": round(1.0 / self.period, 2),
            "loss": [round(x, 3) for x in self.loss()],
            "latency_ms_p90": None if lat is None else round(lat, 2),
            "degradations": self.degradations,
            "host_stalls": self.host_stalls,
            "last_change": dict(self.last) if self.last else None,
        }
