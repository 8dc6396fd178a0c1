"""What the flash tests share: waiting for a flashed (emulated) segment to answer."""

from __future__ import annotations

import time

from host.link import ChainLink


def discover_name(link: ChainLink, timeout: float = 20.0) -> str:
    """The name the first segment's DESCRIPTOR reports, once it answers DISCOVER."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        descs = link.discover(timeout=0.3)
        if descs:
            return descs[0]["name"]
        time.sleep(0.1)
    raise AssertionError("segment did not answer DISCOVER")
