"""Link health: a slow or lossy chain lowers the usable loop rate instead of stalling it.

Fed once per cycle with which positions answered the last exchange and how long it took, it keeps
a short window and decides the *usable* period: when replies from some position keep missing
(loss: a reply later than the reply time counts as missing), the loop slows down (period ×2,
never slower than the floor that keeps the segments' watchdogs fed); once every position has
answered every exchange within the lower rate's reply time for ``recover_s`` (and
RECOVER_MIN_EXCHANGES exchanges), RECOVER_FIT_SHARE of them within the nominal rate's, the loop
tries the nominal rate again (the others would be late replies there: fewer than slow it).
A return that fails at once (within RECOVER_FAIL_S) doubles the clean time asked for next (up
to RECOVER_MAX_S): a link that stays bad is not probed at full rate over and over; a return
that holds RECOVER_HOLD_S resets it, so the next slow spell returns as promptly as the first.
Such a stretch with fewer of them within the nominal rate's reply time climbs to the rate they
need (``eased``, :meth:`LinkHealth._ease`): a link partly restored is used at what it now
carries, and one reported too slow is no longer (``too_slow`` cleared).

One rule slows the loop, on either path (:meth:`LinkHealth.observe` every cycle,
:meth:`LinkHealth.stall` after a silent stretch that found the same chain): a position missed
≥ DEGRADE_LOSS of the exchanges in the window *and* its replies arrived late: at least
DEGRADE_LATE, and at least DEGRADE_LATE_SHARE of its misses (late replies are counted per
exchange in the window, per position when the link tells them apart; the stall path counts
them since that position began to miss, never from longer ago). The stall path only does not
wait for a full window. At the floor rate a link that is still slow is *too slow*: reported
once (``too_slow``) by either path, the rate cannot go lower.

Loss without late replies (a corrupting link, frames dropped) is *lossy*, never slowed for —
a lower rate would not bring those replies back: a position missing ≥ LOSSY_LOSS of a full
window, with fewer than DEGRADE_LATE late replies, for a window's worth of exchanges in a row
(time for late replies to come) or while the link receives garbled frames (:meth:`garbled`),
is reported once (``lossy``, which link, its loss) until
its loss is below LOSSY_CLEAR, its link leaves the chain or the chain is rebuilt
(``loss_cleared``, ``reason``); supervision (gap rule, rejoin) handles
the missing replies.

Positions in what it reports (``position``, ``link``) count from 1, like every position a user
sees (:mod:`host.positions`): ``link`` k is the cable into the k-th segment. The ``loss`` list
is indexed by chain order.

It decides and reports; the daemon applies the period (loop, reply timeout, supervision).

One piece: the slow, lossy and too-slow rules and the recovery stretch read and reset the same
window of per-position misses and late replies and change the same period; split, each part
would hand that state back and forth every cycle.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import Any

DEGRADE_WINDOW = 30  # cycles looked at for loss (a burst of host load is shorter)
DEGRADE_LOSS = 0.6  # a position missing in this share of the window, with at least
DEGRADE_LATE = 3  # this many replies arriving late meanwhile, degrades the link
RECENT = 10  # at the floor, the last exchanges must still miss as much: not a backlog draining
#: ... and late replies for at least this share of its misses: a slow link's replies arrive
#: late, a corrupting link's never arrive (a lossy link, reported, never slowed for)
DEGRADE_LATE_SHARE = 0.5
#: a position missing this share of a full window, its replies not late, is a lossy link
LOSSY_LOSS = 0.2
LOSSY_CLEAR = 0.05  # ... until its loss over a full window is below this
GARBLED_S = 1.0  # garbled frames this recent make missing replies lost ones at once (s)
RECOVER_S = 1.0  # clean time at the lower rate before trying the nominal rate again (s)
RECOVER_MIN_EXCHANGES = 10  # ... and at least this many clean exchanges
#: ... of which at least this share fit the nominal rate's reply time: the rest would be late
#: replies at the nominal rate, at most half of what slows the loop (DEGRADE_LOSS). A clean chain
#: has some too (a host's hiccups; on the emulated chain ~10 % of exchanges pass 8 ms at 100 Hz):
#: asking for none kept the loop slow for ever on a link that works as well as before its fault
RECOVER_FIT_SHARE = 0.7
#: a lowered rate whose exchanges all fit its reply time, the last not the nominal one's, for
#: RECOVER_S climbs to the rate they need with this to spare (``eased``) ...
EASE_SPARE = 1.25
EASE_STEP = 0.8  # ... when that period is below this share of the current one
RECOVER_MAX_S = 12.0  # the back-off of returns that fail at once stops here (s)
#: a return to the nominal rate followed by a slow link this soon failed at once (the link
#: was not good enough for the nominal rate yet): the clean time asked for next doubles (s)
RECOVER_FAIL_S = 1.0
#: a return to the nominal rate that holds this long (no slow link meanwhile) was good: the
#: back-off starts again from RECOVER_S (a later slow spell is a new one) (s)
RECOVER_HOLD_S = 5.0
#: An exchange whose wait for replies returned this much later than its deadline was held up in
#: this process (a garbage collection or another thread holding the interpreter lock delays the
#: link reader and the loop alike), not on the link: its misses say nothing about the link (s).
#: Measured on the wait itself, not the whole exchange: sending the request and decoding the
#: replies put an exchange 2-6 ms past its reply time on a loaded 2-core host, which made nearly
#: every exchange of a slow link "held up" — its degrade waited for 9 silent stretches, not 1.
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
        self._late_win: deque[tuple[int, ...]] = deque(maxlen=DEGRADE_WINDOW)
        self._late: list[int] = []  # per position: its late replies over the window
        self._late_prev: list[int] | None = None  # the link's last late-reply reading
        self._late_seen: object = None  # ... the very object read (a repeated one adds none)
        self._latency: deque[float] = deque(maxlen=50)
        # the recovery stretch: since when every exchange was complete within the current
        # (lowered) rate's reply time, and how long each took (s)
        self._fit_since: float | None = None
        self._fit_times: list[float] = []
        self._cleared: dict[str, Any] | None = None  # a loss_cleared change not returned yet
        self._lossy_n = 0  # exchanges in a row that looked lossy
        self._garbled_at: float | None = None  # when the link last received garbled frames
        self._t_restored: float | None = None
        self.lossy: dict[str, Any] | None = None  # the lossy link reported, while it is
        self.too_slow: dict[str, Any] | None = None  # the link too slow for the floor rate
        self.degradations = 0
        self.host_stalls = 0  # exchanges left out: held up in this process (HOST_STALL_S)
        self._host_stall_at: float | None = None  # when the last one was seen
        self.last: dict[str, Any] | None = None  # what the last change measured

    @property
    def degraded(self) -> bool:
        return self.period > self.nominal * 1.001

    def reset(self) -> None:
        """Forget the window and the lossy link reported (a rebuild changes the chain: its
        loss is measured again, reported again if it stays); the ``loss_cleared`` change comes
        with the next :meth:`observe`."""
        self._forget()
        if self.lossy is not None:
            self._cleared = self._loss_cleared("rebuilt")

    def _loss_cleared(self, reason: str) -> dict[str, Any]:
        """Clear the lossy link reported; the change that says so (``reason``: why)."""
        lossy, self.lossy = self.lossy or {}, None
        change = {"period": self.period, "change": "loss_cleared", "reason": reason}
        change.update(self._measured(lossy.get("position", 1) - 1, 0.0))
        if "segment" in lossy:
            change["segment"] = lossy["segment"]
        return change

    def _forget(self) -> None:
        """Forget the window (the rate or the chain changed)."""
        self._answered.clear()
        self._misses = []
        self._late_win.clear()
        self._late = []
        self._late_prev = None
        self._latency.clear()
        self._fit_since = None
        self._fit_times = []
        self._lossy_n = 0

    def observe(
        self,
        answered: list[bool],
        exchange_s: float,
        now: float,
        late_replies: Callable[[], int | list[int]] = lambda: 1,
        reply_timeout: float | None = None,
        held_s: float | None = None,
    ) -> dict[str, Any] | None:
        """One cycle: ``answered[i]`` whether position i answered; ``exchange_s`` how long
        the exchange waited; ``late_replies()`` a running count of replies that came after
        their exchange ended — per position (a list) when the link tells them apart, else one
        total, counted for the first position missing (asked only while replies miss).
        Missing replies that arrive late mean a slow link: slowing down helps. Missing
        replies that never come (a cut, a corrupting link) make a lossy link: reported
        (``lossy``), left to supervision. An exchange with misses whose wait for replies
        returned more than HOST_STALL_S after its deadline (``held_s``, s; without it,
        ``exchange_s`` past ``reply_timeout``) was held up in this process: it is left out
        (counted in ``host_stalls``), not taken for the link's.
        Returns a change ``{"period", "change", ...}`` or None."""
        if not answered:
            return None
        if self.lossy is not None and self.lossy["position"] > len(answered):
            self._cleared = None
            return self._loss_cleared("left_chain")  # its link is not in the chain now
        if self._cleared is not None:
            change, self._cleared = self._cleared, None
            if change["position"] > len(answered):
                change["reason"] = "left_chain"
            return change
        complete = all(answered)
        if held_s is None and reply_timeout is not None:
            held_s = exchange_s - reply_timeout  # (sending and decoding count too: coarser)
        if held_s is not None and held_s > HOST_STALL_S and not complete:
            self.host_stalls += 1
            self._host_stall_at = now
            return None
        if self._answered and len(self._answered[-1]) != len(answered):
            self.reset()
        late = self._late_now(answered, complete, late_replies)
        self._push(tuple(answered), late)
        if complete:
            self._latency.append(exchange_s)
        loss = self.loss()
        worst = max(range(len(loss)), key=loss.__getitem__)
        full = len(self._answered) == DEGRADE_WINDOW
        # the first position whose replies miss: the slow link is the one into it (or, for
        # a throughput limit, one before it whose own replies still fit: see usable_rate)
        first = next(i for i, x in enumerate(loss) if x >= loss[worst] / 2)
        if full and loss[worst] >= DEGRADE_LOSS:
            floor = self.period >= self.min_period * 0.999
            if not floor and self._slow(first):
                return self._degrade(first, loss[worst], now)
            # at the floor any late replies say slow (a throughput limit below the floor's
            # needs drops more and more of them: the link's queue overflows) — unless the
            # misses are dying out (a backlog from the faster rate draining)
            if floor and self.too_slow is None and self._late[first] >= DEGRADE_LATE:
                if self._still_missing(first):
                    return self.too_slow_now(first, loss[worst])
        change = self._lossy(full, loss, first, worst, now)
        if change is not None:
            return change
        if not self.degraded:
            if self._t_restored is not None and now - self._t_restored >= RECOVER_HOLD_S:
                self._t_restored = None  # the return held: the next one is prompt again
                self.recover_s = RECOVER_S
            return None
        # the recovery stretch: every position answered, within the current rate's reply time
        if not complete or exchange_s > self.reply_share * self.period:
            self._fit_since = None
            self._fit_times = []
            return None
        return self._recover(exchange_s, now)

    def _recover(self, exchange_s: float, now: float) -> dict[str, Any] | None:
        """One more exchange of the recovery stretch (all complete within the lowered rate's
        reply time). After ``recover_s`` (and RECOVER_MIN_EXCHANGES) of them: when at least
        RECOVER_FIT_SHARE fit the nominal rate's reply time, return to it (``restored``; the
        slower ones would be late replies there, at most half the share that slows the loop);
        otherwise climb to what they need (:meth:`_ease`)."""
        if self._fit_since is None:
            self._fit_since, self._fit_times = now, []
        self._fit_times.append(exchange_s)
        if now - self._fit_since < self.recover_s or len(self._fit_times) < RECOVER_MIN_EXCHANGES:
            return None
        times = sorted(self._fit_times)
        fit = sum(t <= self.reply_share * self.nominal for t in times)
        if fit < RECOVER_FIT_SHARE * len(times):
            return self._ease(times, now)
        p90 = self._latency_p90()
        measured_at = 1.0 / self.period
        self.period = self.nominal
        self._t_restored = now
        self.too_slow = None
        self._forget()
        self.last = self._faster(measured_at, p90, "recovered")
        return {"period": self.period, "change": "restored", **self.last}

    def _faster(self, measured_at: float, p90: float, cause: str) -> dict[str, Any]:
        """What a change to a faster rate reports (``last_change``)."""
        return {
            "position": None,
            "link": None,
            "loss": 0.0,
            "measured_at_hz": round(measured_at, 2),
            "latency_ms": round(p90 * 1e3, 2),
            "usable_rate_hz": round(1.0 / self.period, 2),
            "cause": cause,
        }

    def _ease(self, times: list[float], now: float) -> dict[str, Any] | None:
        """A recovery stretch (``times``: its exchanges, sorted, s) that fits the lowered rate
        but not the nominal one: the line carries more than the current rate — climb to the
        rate the longest of them needs with EASE_SPARE to spare, when that is a step
        (EASE_STEP) up; and a link reported too slow is not (``too_slow`` cleared).
        Change ``eased`` (event ``link_recovered``)."""
        need = times[-1]
        target = max(self.nominal, EASE_SPARE * need / self.reply_share)
        climb = target < EASE_STEP * self.period
        if not climb and self.too_slow is None:
            self._fit_since = None  # nothing to change: measure afresh
            self._fit_times = []
            return None
        measured_at = 1.0 / self.period
        was_too_slow = self.too_slow is not None
        if climb:
            self.period = target
            self._t_restored = now  # a climb that fails at once backs off like a return
        self.too_slow = None
        self._forget()
        self.last = self._faster(measured_at, need, "eased")
        return {
            "period": self.period,
            "change": "eased",
            "too_slow_cleared": was_too_slow,
            **self.last,
        }

    def _late_now(
        self, answered: list[bool], complete: bool, late_replies: Callable[[], int | list[int]]
    ) -> tuple[int, ...]:
        """Late replies per position since the last exchange (read only while replies miss)."""
        n = len(answered)
        if complete and not any(self._misses):
            self._late_prev = None
            return (0,) * n
        count = late_replies()
        if isinstance(count, int):  # one total: the first position missing takes it
            at = next((i for i, ok in enumerate(answered) if not ok), None)
            if at is None:
                at = next((i for i, m in enumerate(self._misses) if m), 0)
            now_ = [0] * n
            now_[min(at, n - 1)] = count
            prev = self._late_prev
            total_prev = None if prev is None else sum(prev)
            self._late_prev = [count]
            if total_prev is None:
                return (0,) * n
            now_[min(at, n - 1)] = max(count - total_prev, 0)
            return tuple(now_)
        if count is self._late_seen and self._late_prev is not None:
            return (0,) * n  # the same reading again (read at most every so often): none new
        self._late_seen = count
        count = list(count)[:n] + [0] * max(n - len(count), 0)
        prev, self._late_prev = self._late_prev, count
        if prev is None or len(prev) != n:
            return (0,) * n
        return tuple(max(c - p, 0) for c, p in zip(count, prev, strict=True))

    def _slow(self, position: int) -> bool:
        """The position's misses in the window came late: enough of them (DEGRADE_LATE, and
        DEGRADE_LATE_SHARE of its misses) for a slow link, not a lossy one."""
        if not self._late or position >= len(self._late):
            return False
        late = self._late[position]
        return late >= DEGRADE_LATE and late >= DEGRADE_LATE_SHARE * self._misses[position]

    def garbled(self, now: float) -> None:
        """The link received garbled frames (CRC or framing errors) while replies missed: a
        corrupting link — its loss is reported without waiting for late replies."""
        self._garbled_at = now

    def _lossy(
        self, full: bool, loss: list[float], first: int, worst: int, now: float
    ) -> dict[str, Any] | None:
        """Report a lossy link (replies missing, not late) once; and when its loss ended."""
        if not full:
            return None
        if self.lossy is not None:
            at = self.lossy["position"] - 1  # in the chain (observe cleared it otherwise)
            if loss[at] >= LOSSY_CLEAR:
                self.lossy["loss"] = round(loss[at], 3)  # status: the loss measured now
                return None
            self.lossy = None
            return {"period": self.period, "change": "loss_cleared", **self._measured(at, 0.0)}
        if loss[worst] < LOSSY_LOSS or self._late[first] >= DEGRADE_LATE:
            self._lossy_n = 0  # replies that come late are a slow link's, not lost
            return None
        self._lossy_n += 1
        garbled = self._garbled_at is not None and now - self._garbled_at < GARBLED_S
        if self._lossy_n < DEGRADE_WINDOW and not garbled:
            return None  # held for a window (late replies had time to come), or frames garbled
        self._lossy_n = 0
        self.lossy = {**self._measured(first, loss[first]), "cause": "lossy"}
        return {"period": self.period, "change": "lossy", **self.lossy}

    def _measured(self, position: int, loss: float) -> dict[str, Any]:
        """What a change reports about the link into 0-based ``position``."""
        return {
            "position": position + 1,  # 1-based, as a user reads it
            "link": position + 1,  # the cable into that segment, as the emulator counts links
            "loss": round(loss, 3),
            "measured_at_hz": round(1.0 / self.period, 2),
            "latency_ms": round(self._latency_p90() * 1e3, 2),
            "usable_rate_hz": round(1.0 / self.period, 2),
        }

    def too_slow_now(self, position: int, loss: float) -> dict[str, Any]:
        """At the floor rate and still slow (or measured to need a slower one): reported once
        until the line carries the floor rate again (:meth:`_ease`) or the rate returns to
        nominal (the rate cannot go lower)."""
        self.too_slow = {**self._measured(position, loss), "cause": "too_slow"}
        return {"period": self.period, "change": "too_slow", **self.too_slow}

    def _degrade(self, position: int, loss: float, now: float) -> dict[str, Any]:
        """Halve the rate (not below the floor); the change as reported (0-based
        ``position`` in, 1-based ``position``/``link`` out)."""
        p90 = self._latency_p90()
        if self._t_restored is not None and now - self._t_restored < RECOVER_FAIL_S:
            self.recover_s = min(self.recover_s * 2, RECOVER_MAX_S)  # the return failed at once
        self._t_restored = None
        measured_at = 1.0 / self.period  # the rate the loss was measured at
        self.period = min(self.period * 2, self.min_period)
        self.degradations += 1
        self._forget()
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

    def _still_missing(self, position: int) -> bool:
        """The last RECENT exchanges (at least that many in the window) missed ``position`` in
        at least DEGRADE_LOSS of them: not a backlog from a faster rate draining."""
        recent = list(self._answered)[-RECENT:]
        return len(recent) == RECENT and sum(not a[position] for a in recent) >= (
            DEGRADE_LOSS * RECENT
        )

    def held_up(self, now: float) -> bool:
        """An exchange was held up in this process less than HOST_STALL_HOLD_S ago."""
        return self._host_stall_at is not None and now - self._host_stall_at < HOST_STALL_HOLD_S

    def stall(self, position: int, late: int, now: float) -> dict[str, Any] | None:
        """Supervision found a silent stretch and the very same chain behind it (a stall) at
        0-based ``position``: when that position missed ≥ DEGRADE_LOSS of the exchanges in the
        window so far and ``late`` ≥ DEGRADE_LATE replies (counted since it began to miss)
        arrived late meanwhile, the link is slow — degrade at once, without waiting for a full
        window; unless an exchange was held up in this process less than HOST_STALL_HOLD_S ago
        (:meth:`observe`). At the floor rate such a link is *too slow* (reported once, as by
        :meth:`observe`) once RECENT exchanges there missed as much (not a backlog from the
        faster rate draining): a chain that a too-slow link keeps silent may never hold still
        for a full window there. Returns a change as :meth:`observe` does."""
        floor = self.period >= self.min_period * 0.999
        if late < DEGRADE_LATE or (floor and self.too_slow is not None):
            return None
        if self._misses and 0 <= position < len(self._misses):
            if late < DEGRADE_LATE_SHARE * self._misses[position]:
                return None  # most of its replies never came: lossy, not slow
        if self.held_up(now):
            return None  # the process was held up meanwhile (see observe), not the link
        loss = self.loss()
        if not 0 <= position < len(loss) or loss[position] < DEGRADE_LOSS:
            return None  # the same threshold as a full window: a few misses are no slow link
        if floor:
            if not self._still_missing(position):
                return None
            return self.too_slow_now(position, loss[position])
        return self._degrade(position, loss[position], now)

    def _push(self, answered: tuple[bool, ...], late: tuple[int, ...]) -> None:
        """Adds one exchange to the window, keeping the per-position miss and late-reply
        counts (the cycle pays a few integer operations, not a pass over the window)."""
        if not self._misses:
            self._misses = [0] * len(answered)
            self._late = [0] * len(answered)
        if len(self._answered) == DEGRADE_WINDOW:
            for i, ok in enumerate(self._answered[0]):
                self._misses[i] -= not ok
            for i, k in enumerate(self._late_win[0]):
                self._late[i] -= k
        self._answered.append(answered)
        self._late_win.append(late)
        for i, ok in enumerate(answered):
            self._misses[i] += not ok
        for i, k in enumerate(late):
            self._late[i] += k

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
            "lossy": dict(self.lossy) if self.lossy else None,
            "too_slow": dict(self.too_slow) if self.too_slow else None,
        }
