"""What the flash tests share: waiting for a flashed (emulated) segment to answer."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from host.link import ChainLink
from tools.emulator import EmulatedChain


def discover_name(
    link: ChainLink, timeout: float = 20.0, chain: EmulatedChain | None = None
) -> str:
    """The name the first segment's DESCRIPTOR reports, once it answers DISCOVER. If it does not,
    the error holds what ``chain`` knows about segment 0 (REPL output, counters)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        descs = link.discover(timeout=0.3)
        if descs:
            return descs[0]["name"]
        time.sleep(0.1)
    why = ""
    if chain is not None:
        why = (
            f"; emulator: {chain.stats()}; link: {link.stats()}"
            f"; REPL output of segment 0:\n{chain.repl_output(0)[-4000:]}"
        )
    raise AssertionError("segment did not answer DISCOVER" + why)


@contextmanager
def one_segment_named(name: str) -> Iterator[tuple[EmulatedChain, ChainLink]]:
    """A one-segment emulated chain configured as ``name``, answering, with a link to it."""
    with EmulatedChain(1, config_for=[{"name": name}]) as ch:
        link = ChainLink(ch.host_port)
        assert discover_name(link, chain=ch) == name
        try:
            yield ch, link
        finally:
            link.close()
