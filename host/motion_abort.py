"""Why a hot-plug aborts the running goals: one coherent abort reason (issue 12) — the segment
it concerns and the cause, ``topology_change`` or ``link_loss``.

The rule (docs/daemon.md "Hot-plug"):

- a segment reported the change (DOWNSTREAM_UP/DOWN, BOOT, a misaddressed SYNC, a segment
  answering beyond the tip) or the rediscovery found another chain (other segments, more of
  them): ``topology_change``;
- the replies stopped without any segment reporting a change (silence) and the rediscovery
  found the same chain or only its leading part (nothing, or a prefix: the replies of the rest
  are lost, as on a silent or corrupting link; a pulled cable looks the same until its segment
  reports it): ``link_loss``.

The segment is the one the supervisor's reason concerns (the first silent one, the one that
booted, the neighbour behind a changed downstream port), else the first position where the
chain found differs from the chain known; named as in the description.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


def first_difference(before: Sequence[Any], found: Sequence[Any]) -> int | None:
    """The first 0-based position where two chains (uids in order) differ; None if equal."""
    for i in range(max(len(before), len(found))):
        if i >= len(before) or i >= len(found) or before[i] != found[i]:
            return i
    return None


def hotplug_abort(
    reason: str,
    *,
    silent: bool,
    before: Sequence[Any],
    found: Sequence[Any] | None,
    expected: Sequence[str],
    position: int | None = None,
) -> tuple[str, str, str | None]:
    """``(text, cause, segment)`` for the goals a hot-plug aborts.

    ``reason``: the supervisor's; ``silent``: it was silence, no segment reported anything;
    ``before``/``found``: uids of the chain known and of the one rediscovered (None: the
    rediscovery failed); ``expected``: the description's segment names in chain order;
    ``position``: the 0-based index the reason concerns, if the supervisor knows it."""
    diff = None if found is None else first_difference(before, found)
    if not silent:
        cause = "topology_change"
    elif found is None or diff is None or list(found) == list(before[: len(found)]):
        cause = "link_loss"  # the same chain, or its leading part: replies lost, nothing moved
    else:
        cause = "topology_change"  # other segments answer
    index = position if position is not None else diff
    segment = expected[index] if index is not None and 0 <= index < len(expected) else None
    head = "topology changed" if cause == "topology_change" else "link loss"
    text = f"{head} at {segment}: {reason}" if segment else f"{head}: {reason}"
    return text, cause, segment
