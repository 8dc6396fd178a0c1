"""How a chain position reads for a person: counted from 1 (segment_1 is position 1).

On the wire and in API data a position is a 0-based index (hops from the host); every message
text a user reads goes through :func:`label`, so the two never mix (issue 12: "positions
1-based wherever a user sees them")."""

from __future__ import annotations


def label(index: object) -> str:
    """``position N`` with N counted from 1, for a 0-based chain index (anything else as is)."""
    if isinstance(index, int) and not isinstance(index, bool):
        return f"position {index + 1}"
    return f"position {index}"


def labels(indices: object) -> str:
    """Several positions, counted from 1: ``positions 2, 3``."""
    try:
        nums = [i + 1 if isinstance(i, int) else i for i in indices]  # type: ignore[attr-defined]
    except TypeError:
        return f"positions {indices}"
    return "positions " + ", ".join(str(n) for n in nums)
