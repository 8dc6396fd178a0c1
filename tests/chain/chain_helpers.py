"""Shared helpers for chain tests: an emulated chain plus a host link, cleaned up on teardown."""

from __future__ import annotations

import re
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from host.link import ChainLink, LinkError
from tools.emulator import EmulatedChain

REPO = Path(__file__).resolve().parents[2]


def wait_discover(link: ChainLink, n: int, timeout: float = 15.0) -> list[dict]:
    """Discover until ``n`` segments answer (processes need a moment to boot)."""
    end = time.monotonic() + timeout
    last: list[dict] | str = []
    while time.monotonic() < end:
        try:
            last = link.discover(timeout=0.5)
        except LinkError as exc:
            last = str(exc)
        if isinstance(last, list) and len(last) == n:
            return last
        time.sleep(0.1)
    raise AssertionError(f"discovery did not find {n} segments within {timeout} s: {last}")


@contextmanager
def chain_and_link(n: int, **kwargs) -> Iterator[tuple[EmulatedChain, ChainLink]]:
    with EmulatedChain(n, **kwargs) as chain:
        link = ChainLink(chain.host_port)
        try:
            yield chain, link
        finally:
            link.close()


def sync_until(link: ChainLink, setpoints, cond, timeout: float = 5.0, period: float = 0.02):
    """Send SYNC at ~50 Hz until ``cond(states)`` holds; return the last states."""
    end = time.monotonic() + timeout
    states = None
    while time.monotonic() < end:
        states = link.sync(setpoints, timeout=0.1)
        if all(s is not None for s in states) and cond(states):
            return states
        time.sleep(period)
    raise AssertionError(f"condition not reached within {timeout} s; last states {states}")


def events_until(link: ChainLink, pred, timeout: float = 2.0, keep_alive=None) -> list[dict]:
    """Collect events until one satisfies ``pred``; ``keep_alive()`` is called meanwhile."""
    end = time.monotonic() + timeout
    seen: list[dict] = []
    while time.monotonic() < end:
        if keep_alive is not None:
            keep_alive()
        seen.extend(link.events())
        if any(pred(e) for e in seen):
            return seen
        time.sleep(0.02)
    raise AssertionError(f"expected event not seen within {timeout} s; got {seen}")


def protocol_speaking(tmp_path: Path, version: int) -> Path:
    """A copy of protocol/ whose firmware build speaks only ``version``."""
    out = tmp_path / "protocol"
    shutil.copytree(REPO / "protocol", out, ignore=shutil.ignore_patterns("vectors", "__pycache__"))
    src = (out / "constants.py").read_text()
    for name in ("VERSION", "VERSION_MIN", "VERSION_MAX"):
        src, count = re.subn(
            rf"^{name} = const\(\d+\)", f"{name} = const({version})", src, flags=re.M
        )
        assert count == 1, name
    (out / "constants.py").write_text(src)
    return out
