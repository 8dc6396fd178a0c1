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
        self._late_mark: int | None = None  # link's late-reply count at the last stall

    def start(self, link: Any) -> None:
        """Count late replies from now on (a fresh link)."""
        try:
            self._late_mark = late_replies(link)
        except (OSError, AttributeError):
            self._late_mark = None

    def reset(self) -> None:
        """The chain was rebuilt: start the health window again."""
        self.health.reset()

    def observe(self, hwi: HardwareInterface, link: Any, now: float) -> None:
        """Feed the link health with the last exchange; apply and report a change."""
        change = self.health.observe(
            [s is not None for s in hwi.raw_states],
            hwi.exchange_s,
            now,
            lambda: late_replies(link),
            reply_timeout=hwi.reply_timeout,
        )
        self._report(hwi, change)

    def stall(self, hwi: HardwareInterface, link: Any, position: int, now: float) -> None:
        """A stall (silence, same chain): late replies meanwhile mean a slow link."""
        try:
            count = late_replies(link)
        except OSError:
            return
        late = count - (self._late_mark if self._late_mark is not None else 0)
        self._late_mark = count
        self._report(hwi, self.health.stall(position, late, now))

    def _report(self, hwi: HardwareInterface, change: dict[str, Any] | None) -> None:
        """Apply and report a change of the usable rate."""
        if change is None:
            return
        self._apply_period(change["period"])
        rate, nominal = change["usable_rate_hz"], round(self.rate_hz, 2)
        if change["change"] == "degraded":
            pos = change["position"]
            into = hwi.names[pos] if pos < len(hwi.names) else label(pos)
            msg = (
                f"link {pos + 1} (into {into}) is slow: its replies come late, "
                f"{change['loss']:.0%} missed at {round(1.0 / (change['period'] / 2), 2)} Hz; "
                f"loop slowed to {rate} Hz (nominal {nominal} Hz)"
            )
            self._emit_event("link_degraded", message=msg, link=pos + 1, segment=into, **change)
        else:
            msg = f"link recovered (exchange p90 {change['latency_ms']} ms): loop back to {rate} Hz"
            self._emit_event("link_recovered", message=msg, **change)
        log.warning("%s", msg)
