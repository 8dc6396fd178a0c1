"""The usable loop rate: feeds :class:`host.link_health.LinkHealth` from each exchange (and each
stall), and turns its decisions into a ``link_degraded`` / ``link_recovered`` event and a new
loop period, which the daemon applies to its parts (``apply_period``).

Kept out of :mod:`host.daemon` so the facade only composes: the link health decides, this part
reports and hands the period on, the daemon says which parts follow it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from host.hwi import HardwareInterface
from host.link_health import LinkHealth
from host.positions import label

log = logging.getLogger("ucr.daemon")


def late_replies(link: Any) -> int:
    """The link's count of replies that came too late to match an exchange (OSError if the
    port failed)."""
    stats = link.stats
    return int(stats.get("unmatched", 0)) + int(stats.get("stale", 0))


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

    def start(self, link: Any) -> None:
        """A fresh link: no stretch of misses yet."""
        self._late_mark = None

    def reset(self) -> None:
        """The chain was rebuilt: start the health window again."""
        self.health.reset()
        self._late_mark = None

    def observe(self, hwi: HardwareInterface, link: Any, now: float) -> None:
        """Feed the link health with the last exchange; apply and report a change."""
        answered = [s is not None for s in hwi.raw_states]
        if all(answered):
            self._late_mark = None  # a complete exchange ends a stretch of misses
        elif self._late_mark is None:
            try:  # one look at the link's counters per stretch, not per cycle
                self._late_mark = late_replies(link)
            except (OSError, AttributeError):
                self._late_mark = None
        change = self.health.observe(
            answered,
            hwi.exchange_s,
            now,
            lambda: late_replies(link),
            reply_timeout=hwi.reply_timeout,
        )
        self._report(hwi, change)

    def stall(self, hwi: HardwareInterface, link: Any, position: int, now: float) -> None:
        """A stall (silence, same chain) at 0-based ``position``: late replies since the
        replies began to miss mean a slow link (link health decides, with its loss rule)."""
        if self._late_mark is None:
            return  # no stretch of misses was seen: nothing to count from
        try:
            count = late_replies(link)
        except (OSError, AttributeError):
            return
        late = count - self._late_mark
        self._late_mark = count
        self._report(hwi, self.health.stall(position, late, now))

    def _report(self, hwi: HardwareInterface, change: dict[str, Any] | None) -> None:
        """Apply and report a change of the usable rate."""
        if change is None:
            return
        self._apply_period(change["period"])
        rate, nominal = change["usable_rate_hz"], round(self.rate_hz, 2)
        if change["change"] == "degraded":
            index = change["position"] - 1  # the change counts from 1, names from 0
            into = hwi.names[index] if index < len(hwi.names) else label(index)
            change["segment"] = into
            if self.health.last is not None:
                self.health.last["segment"] = into  # status()["link_health"]["last_change"]
            msg = (
                f"link {change['link']} (into {into}) is slow: its replies come late, "
                f"{change['loss']:.0%} missed at {change['measured_at_hz']} Hz; "
                f"loop slowed to {rate} Hz (nominal {nominal} Hz)"
            )
            self._emit_event("link_degraded", message=msg, **change)
        else:
            msg = f"link recovered (exchange p90 {change['latency_ms']} ms): loop back to {rate} Hz"
            self._emit_event("link_recovered", message=msg, **change)
        log.warning("%s", msg)
