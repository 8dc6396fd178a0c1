"""The usable loop rate: feeds :class:`host.link_health.LinkHealth` from each exchange (and each
stall), and turns its decisions into a ``link_degraded`` / ``link_recovered`` event and a new
loop period, which the daemon applies to its parts (``apply_period``).

Kept out of :mod:`host.daemon` so the facade only composes: the link health decides, this part
reports and hands the period on, the daemon says which parts follow it.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable
from typing import Any

from host.hwi import HardwareInterface
from host.link_frames import SLOW_LINE_SHARE
from host.link_health import DEGRADE_WINDOW, GARBLED_S, LinkHealth
from host.positions import label

log = logging.getLogger("ucr.daemon")


#: a step in added delay smaller than this says nothing about which link is slow (s)
DELAY_STEP_S = 0.001
#: this many garbled frames within GARBLED_S while replies miss make the loss a corrupting link's
GARBLED_FRAMES = 3
#: a clean chain's arrival times are taken as the baseline at most this often (s)
BASELINE_EVERY_S = 1.0
#: while replies miss, the link's counters (garbled frames, late replies per position) are
#: read at most this often (s): a cycle with a miss costs a few µs more, not a copy of them
LOOK_EVERY_S = 0.1


def late_replies(link: Any) -> int:
    """The link's count of replies that came too late to match an exchange (OSError if the
    port failed)."""
    by_position = getattr(link, "late_by_position", None)
    if by_position is not None:
        return sum(by_position())
    stats = link.stats
    return int(stats.get("unmatched", 0)) + int(stats.get("stale", 0))


def late_count(link: Any) -> int | None:
    """:func:`late_replies`, or None when the link cannot say (its port failed)."""
    try:
        return late_replies(link)
    except (OSError, AttributeError):
        return None


def late_by_position(link: Any) -> int | list[int]:
    """Late STATEs per position when the link tells them apart, else its one total."""
    by_position = getattr(link, "late_by_position", None)
    return by_position() if by_position is not None else late_replies(link)


def slow_link(base: list[float | None], now: list[float | None]) -> tuple[int, float] | None:
    """Which link added delay (0-based position of the segment behind it, the added delay s)
    from per-position reply arrival times after the request, clean (``base``) and now: a
    slow cable delays the replies of every segment behind it, so the added delay steps up at
    the first segment behind the slow link (a throughput limit adds a little more for every
    further reply, a latency nothing). None when no step stands out (DELAY_STEP_S)."""
    added: list[float] = []
    for b, n in zip(base, now, strict=False):
        if b is None or n is None:
            break
        added.append(n - b)
    if not added:
        return None
    steps = [added[0]] + [added[i] - added[i - 1] for i in range(1, len(added))]
    top = max(steps)
    if top < DELAY_STEP_S:
        return None
    first = next(i for i, x in enumerate(steps) if x >= top / 2)
    return first, added[first]


def slow_by_rate(rates: list[float | None], configured: Any) -> tuple[int, float] | None:
    """Which link is slow from the rate each position's frames arrive at (0-based position of
    the segment behind it, its bit/s): the first position measured below SLOW_LINE_SHARE of the
    configured baud rate (``ChainLink.line_rate_by_position``); None if none is (or unknown)."""
    if not isinstance(configured, int) or configured <= 0:
        return None
    for pos, bps in enumerate(rates):
        if bps is not None and bps < SLOW_LINE_SHARE * configured:
            return pos, bps
    return None


class UsableRate:
    """Link health → events and the period the loop runs at (nominal ``rate_hz``)."""

    def __init__(
        self,
        health: LinkHealth,
        rate_hz: float,
        emit_event: Callable[..., None],
        apply_period: Callable[[float], None],
    ) -> None:
        self.health = health
        self.rate_hz = rate_hz
        self._emit_event = emit_event
        self._apply_period = apply_period
        # the link's late-reply count when replies began to miss (the first incomplete exchange
        # after a complete one); None while every position answers. A stall counts late
        # replies from there: never from an older stretch (a burst long ago is no slow link).
        self._late_mark: int | None = None
        # per-position reply arrival times on a clean chain (link.arrival_offsets), and when
        self._base: list[float | None] | None = None
        self._base_at = -1e9
        self._too_slow: tuple[int, float] | None = None  # measured: (position, period needed)
        self._bad_hist: deque[tuple[float, int]] = deque()  # (when, garbled frames so far)
        self._looked_at = -1e9  # when the garbled-frame count was last read
        self._late_read: tuple[float, int | list[int]] | None = None  # (when, late replies)
        # the exchange last observed (HWI, its exchange count): a cycle that ended in
        # supervision sends none, and the next one reads no new states — seen once only
        self._seen: tuple[object, int] | None = None

    def start(self, link: Any) -> None:
        """A fresh link: no stretch of misses yet."""
        self._late_mark = None
        self._base = None
        self._base_at = -1e9

    def reset(self) -> None:
        """The chain was rebuilt: start the health window again."""
        self.health.reset()
        self._late_mark = None

    def observe(self, hwi: HardwareInterface, link: Any, now: float) -> None:
        """Feed the link health with the last exchange (once: the same exchange again is
        left out); apply and report a change."""
        count = getattr(hwi, "exchanges", None)
        if count is not None:
            seen = self._seen
            if seen is not None and seen[0] is hwi and seen[1] == count:
                return
            self._seen = (hwi, count)
        answered = [s is not None for s in hwi.raw_states]
        if all(answered):
            self._late_mark = None  # a complete exchange ends a stretch of misses
        else:
            if now - self._looked_at >= LOOK_EVERY_S:
                self._looked_at = now
                self._look_for_garbled(link, now)
            if self._late_mark is None:  # one look per stretch, not per cycle
                self._late_mark = late_count(link)
        change = self.health.observe(
            answered,
            hwi.exchange_s,
            now,
            lambda: self._late_replies(link, now),
            reply_timeout=hwi.reply_timeout,
            held_s=getattr(hwi, "wait_overrun_s", None),
        )
        if change is not None:
            self._restart_late_count(link)  # a new rate (or report): late replies count afresh
            self._name_link(link, change, len(answered))
        elif now - self._base_at >= BASELINE_EVERY_S and self._clean():
            offsets = getattr(link, "arrival_offsets", None)
            if offsets is not None:  # the chain's reply times while every link is clean
                self._base, self._base_at = offsets(), now
        self._report(hwi, change)
        self._report_too_slow(hwi, change)

    def _restart_late_count(self, link: Any) -> None:
        """The stretch of misses goes on, but its late replies count from here."""
        if self._late_mark is not None:
            self._late_mark = late_count(link)

    def _late_replies(self, link: Any, now: float) -> int | list[int]:
        """The link's late replies (per position when it tells them apart), read at most every
        LOOK_EVERY_S: in between the last reading stands (the link health counts differences)."""
        got = self._late_read
        if got is None or not 0 <= now - got[0] < LOOK_EVERY_S:
            got = self._late_read = now, late_by_position(link)
        return got[1]

    def _report_too_slow(self, hwi: HardwareInterface, change: dict[str, Any] | None) -> None:
        """The bytes of a cycle measured not to fit even the floor rate's period: too slow."""
        if self._too_slow is None or change is None:
            return
        position, need = self._too_slow
        self._too_slow = None
        slow = self.health.too_slow_now(position, change["loss"])
        for key in ("named_by", "delay_ms", "line_rate_bps", "measured_at_hz"):
            if key in change:
                slow[key] = self.health.too_slow[key] = change[key]
        slow["needed_rate_hz"] = self.health.too_slow["needed_rate_hz"] = round(1.0 / need, 2)
        self._report(hwi, slow)

    def _look_for_garbled(self, link: Any, now: float) -> None:
        """Replies missing while the link receives garbled frames: tell the link health."""
        try:
            stats = link.stats
            bad = int(stats.get("crc_errors", 0)) + int(stats.get("framing_errors", 0))
        except (OSError, AttributeError, TypeError, ValueError):
            return
        hist = self._bad_hist
        while hist and now - hist[0][0] > GARBLED_S:
            hist.popleft()
        hist.append((now, bad))
        if bad - hist[0][1] >= GARBLED_FRAMES:  # a few, not one torn frame at a change
            self.health.garbled(now)

    def _clean(self) -> bool:
        """A full window at the nominal rate without a miss."""
        h = self.health
        return not h.degraded and len(h._answered) == h._answered.maxlen and not any(h._misses)

    def _name_link(self, link: Any, change: dict[str, Any], n: int) -> None:
        """Name the slow link from the measured delays (:func:`slow_link`) rather than from
        the first position whose replies miss (with a throughput limit the replies of the
        segment just behind the slow cable may still fit). ``delay_ms``: the delay added at
        that link; ``named_by``: ``delay`` (measured) or ``loss`` (the first position
        missing: the slow link is that one or one before it)."""
        if change["change"] not in ("degraded", "too_slow"):
            return
        found = by_rate = None
        per_position = getattr(link, "line_rate_by_position", None)
        if per_position is not None:
            try:
                by_rate = slow_by_rate(per_position(), getattr(link, "baudrate", None))
            except (OSError, AttributeError, TypeError):
                by_rate = None
        offsets = getattr(link, "arrival_offsets", None)
        if by_rate is None and self._base is not None and offsets is not None:
            try:
                found = slow_link(self._base, offsets())
            except (OSError, AttributeError):
                found = None
        if by_rate is not None:
            position, _bps = by_rate
            change.update(position=position + 1, link=position + 1, named_by="line_rate")
        elif found is None:
            change["named_by"] = "loss"
        else:
            position, added = found
            change.update(position=position + 1, link=position + 1, delay_ms=round(added * 1e3, 2))
            change["named_by"] = "delay"
        rate = getattr(link, "line_rate_bps", None)
        try:
            bps = rate() if rate is not None else None
        except (OSError, RuntimeError):  # not measured: the change stands as decided
            bps = None
        configured = getattr(link, "baudrate", None)
        if bps is not None and isinstance(configured, int) and bps < 0.5 * configured:
            change["line_rate_bps"] = round(bps)
            if change["change"] == "degraded":
                self._to_needed_rate(link, change, bps, n)
        last = self.health.too_slow if change["change"] == "too_slow" else self.health.last
        if last is not None:
            for key in ("position", "link", "delay_ms", "named_by", "line_rate_bps"):
                if key in change:
                    last[key] = change[key]

    def stall(self, hwi: HardwareInterface, link: Any, position: int, now: float) -> None:
        """A stall (silence, same chain) at 0-based ``position``: late replies since the
        replies began to miss at this rate mean a slow link (link health decides, with its
        loss rule; at the floor rate: too slow)."""
        if self._late_mark is None:
            return  # no stretch of misses was seen: nothing to count from
        count = late_count(link)
        if count is None:
            return
        # late replies over the stretch of misses at this rate (a stretch can hold several
        # stalls): counted from the last stall only, they fell below half the misses the
        # window holds from that stretch, and the stall was taken for a lossy link's
        late = count - self._late_mark
        change = self.health.stall(position, late, now)
        if change is not None or self.health.held_up(now):
            # a new rate: its late replies count afresh; a stall the process's own hold-up
            # excused: the late replies of its held-up exchanges (left out of the window)
            # never count for a later one
            self._late_mark = count
        if change is not None:
            self._name_link(link, change, len(hwi.raw_states))
        self._report(hwi, change)
        self._report_too_slow(hwi, change)

    def _to_needed_rate(self, link: Any, change: dict[str, Any], bps: float, n: int) -> None:
        """A line measured slow (a throughput limit): slow straight to the rate its bytes
        need — one SYNC and a STATE per position at the measured byte rate, within the reply
        share of the period, with a quarter to spare — instead of halving step by step (each
        step waits a window of misses). Never below the floor rate; when even the bare need
        (nothing to spare) is below the floor, the link is too slow (reported after this)."""
        health = self.health
        try:
            stats = link.stats
            sync = stats["tx_bytes"] / max(stats["tx_frames"], 1)
            state = stats["rx_bytes"] / max(stats["frames_ok"], 1)
        except (OSError, AttributeError, KeyError, TypeError):
            return
        bare = (sync + n * state) * 10.0 / bps / health.reply_share  # nothing to spare
        need = 1.25 * bare
        if bare > health.min_period and health.too_slow is None:
            self._too_slow = change["position"] - 1, bare  # reported after this change
        if need <= health.period:
            return
        health.period = min(need, health.min_period)
        rate = round(1.0 / health.period, 2)
        change.update(period=health.period, usable_rate_hz=rate)
        if health.last is not None:
            health.last["usable_rate_hz"] = rate

    def _report(self, hwi: HardwareInterface, change: dict[str, Any] | None) -> None:
        """Apply and report a change: ``link_degraded`` (slowed), ``link_recovered``,
        ``link_too_slow`` (slow at the floor rate), ``link_lossy`` / ``link_loss_cleared``."""
        if change is None:
            return
        kind = change["change"]
        if kind in ("degraded", "restored", "eased"):
            self._apply_period(change["period"])
        rate, nominal = change["usable_rate_hz"], round(self.rate_hz, 2)
        if kind in ("restored", "eased"):
            msg = f"link recovered (exchange p90 {change['latency_ms']} ms): loop back to {rate} Hz"
            if kind == "eased":
                msg = (
                    f"link better (exchanges up to {change['latency_ms']} ms): loop "
                    + ("up to" if rate > change["measured_at_hz"] else "stays at")
                    + f" {rate} Hz (nominal {nominal} Hz)"
                    + ("; no longer too slow for the floor" if change["too_slow_cleared"] else "")
                )
            self._emit_event("link_recovered", message=msg, **change)
            log.warning("%s", msg)
            return
        index = change["position"] - 1  # the change counts from 1, names from 0
        into = change.get("segment") or (
            hwi.names[index] if index < len(hwi.names) else label(index)
        )
        change["segment"] = into
        last = {
            "degraded": self.health.last,
            "too_slow": self.health.too_slow,
            "lossy": self.health.lossy,
        }.get(kind)
        if last is not None:
            last["segment"] = into  # status()["link_health"]
        where = f"link {change['link']} (into {into})"
        why = ""
        if change.get("named_by") == "delay":
            why = f"replies from {into} on come {change['delay_ms']} ms later than on a clean chain"
        elif kind in ("degraded", "too_slow"):
            why = (
                f"its replies come late (the first segment whose replies miss is {into}: "
                f"the slow link is link {change['link']} or one before it)"
            )
        if "line_rate_bps" in change:
            why += f"; bytes reach the host at about {change['line_rate_bps']} bit/s"
        if kind == "degraded":
            msg = (
                f"{where} is slow: {why}, {change['loss']:.0%} missed at "
                f"{change['measured_at_hz']} Hz; loop slowed to {rate} Hz (nominal {nominal} Hz)"
            )
            self._emit_event("link_degraded", message=msg, **change)
        elif kind == "too_slow":
            msg = (
                f"{where} too slow for the {rate} Hz floor: {why}, {change['loss']:.0%} "
                f"missed at {change['measured_at_hz']} Hz"
                + (
                    f" (a cycle's bytes need {change['needed_rate_hz']} Hz)"
                    if "needed_rate_hz" in change
                    else ""
                )
                + f"; {rate} Hz is the slowest rate that keeps the segments' watchdogs fed; "
                f"the segments behind it are not reliably under control: restore the link "
                f"(its baud rate or latency)"
            )
            self._emit_event("link_too_slow", message=msg, **change)
        elif kind == "lossy":
            msg = (
                f"{where} is lossy: {change['loss']:.0%} of the replies from {into} lost over "
                f"the last {DEGRADE_WINDOW} exchanges, not late (corrupted or dropped frames); "
                f"the loop stays at {rate} Hz (slowing down would not bring them back)"
            )
            self._emit_event("link_lossy", message=msg, **change)
        else:  # loss_cleared
            msg = f"{where} is no longer lossy" + {
                "left_chain": " (it left the chain)",
                "rebuilt": " (the chain was rebuilt: its loss is measured afresh)",
            }.get(change.get("reason"), "")
            self._emit_event("link_loss_cleared", message=msg, **change)
        log.warning("%s", msg)
