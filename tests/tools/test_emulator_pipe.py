"""Pipe: one direction of an emulated link, on plain byte streams with an explicit clock."""

from __future__ import annotations

import time

import pytest

from tools.emulator import Pipe


def drain(pipe: Pipe, until: float, step: float = 1e-4) -> list[tuple[float, bytes]]:
    out, t = [], 0.0
    while t <= until:
        data = pipe.due(t)
        if data:
            out.append((t, data))
        t += step
    return out


def test_unthrottled_bytes_pass_at_once_in_order() -> None:
    pipe = Pipe("p")
    pipe.feed(b"abc", 1.0)
    pipe.feed(b"def", 1.0)
    assert pipe.due(1.0) == b"abcdef"
    assert pipe.bytes_out == 6 and pipe.next_deadline() is None


def test_throttle_takes_ten_bits_per_byte_and_keeps_order() -> None:
    pipe = Pipe("p")
    pipe.configure(baud=10_000)  # 1 ms per byte
    pipe.feed(bytes(range(50)), 0.0)
    pipe.feed(b"\xaa" * 10, 0.001)  # queued behind the first burst
    chunks = drain(pipe, 0.1)
    data = b"".join(d for _, d in chunks)
    assert data == bytes(range(50)) + b"\xaa" * 10
    first_done = next(t for t, _ in chunks if t >= 0.0499)
    assert chunks[-1][0] == pytest.approx(0.060, abs=2e-4)
    assert first_done == pytest.approx(0.050, abs=2e-4)
    assert chunks[0][0] > 0.0  # nothing arrives before its bytes were on the wire


def test_a_fast_link_delivers_a_frame_in_small_pieces_not_whole() -> None:
    """At 921600 baud a STATE frame (34 bytes) lasts 0.37 ms. A UART with the RX FIFO threshold
    at 1 (how the firmware opens the chain UARTs on an ESP32, docs/firmware.md) hands its first
    bytes on while the rest are still on the wire; a relaying segment then forwards them
    cut-through. Released in 0.5 ms chunks, the whole frame came at once, after its last byte:
    every hop was store-and-forward, whatever the firmware did."""
    pipe = Pipe("p")
    pipe.configure(baud=921_600, now=0.0)
    byte_s = 10 / 921_600
    frame = bytes(range(1, 35))
    pipe.feed(frame, 0.0)
    first = pipe.due(10 * byte_s)
    assert 0 < len(first) <= 10  # the first bytes, before the frame has ended
    rest = pipe.due(len(frame) * byte_s + 1e-9)
    assert first + rest == frame
    # no piece is released before its last byte was on the wire
    pipe.feed(frame, 1.0)
    assert pipe.due(1.0 + 7 * byte_s) == b""


def test_latency_delays_every_byte() -> None:
    pipe = Pipe("p")
    pipe.configure(latency_s=0.005)
    pipe.feed(b"x", 1.0)
    assert pipe.due(1.004) == b""
    assert pipe.due(1.005) == b"x"


def test_corruption_changes_and_counts_bytes_reproducibly() -> None:
    outs = []
    for _ in range(2):
        pipe = Pipe("p", seed=3)
        pipe.configure(corrupt_rate=0.1)
        payload = bytes(1000)
        pipe.feed(payload, 0.0)
        out = pipe.due(0.0)
        changed = sum(a != b for a, b in zip(out, payload, strict=True))
        assert changed == pipe.corrupted
        assert 50 < changed < 150
        outs.append(out)
    assert outs[0] == outs[1]  # seeded


def test_unplugged_pipe_drops_and_counts_including_bytes_in_flight() -> None:
    pipe = Pipe("p")
    pipe.configure(baud=1000)
    pipe.feed(b"12345", 0.0)
    pipe.set_enabled(False)
    pipe.feed(b"678", 0.0)
    assert pipe.dropped == 8 and drain(pipe, 0.1, 1e-3) == []
    pipe.set_enabled(True)
    pipe.configure(baud=None)
    pipe.feed(b"9", 1.0)
    assert pipe.due(1.0) == b"9"


@pytest.mark.parametrize(
    "kwargs", [{"baud": 0}, {"baud": -5}, {"latency_s": -1.0}, {"corrupt_rate": 1.5}]
)
def test_bad_settings_are_refused(kwargs) -> None:
    with pytest.raises(ValueError):
        Pipe("p").configure(**kwargs)


def test_bytes_in_flight_follow_a_latency_change() -> None:
    """Review 2026-11-26: `latency 1 1e9` then `latency 1 0` left the link dead behind bytes
    still due in 30 years; now bytes in flight follow the new setting, and a latency beyond a
    minute is refused."""
    p = Pipe("x")
    p.configure(latency_s=50.0)
    p.feed(b"abc", now=0.0)
    assert p.due(1.0) == b""
    p.configure(latency_s=0.0)
    assert p.due(0.0) == b"abc"
    with pytest.raises(ValueError, match="latency must be within"):
        p.configure(latency_s=1e9)


def test_removing_the_throttle_frees_the_bytes_waiting_at_once() -> None:
    """Audit (issue 14): `baud 1 9600`, then `baud 1 off` left every byte already queued at
    9600 baud at its old time (and bytes fed later queued behind them), so the link stayed dead
    for as long as the backlog lasted; after `baud 1 1` for ever. Now the byte being shifted out
    completes at the old rate and everything behind it leaves at once."""
    p = Pipe("x")
    p.configure(baud=1000, now=0.0)  # 10 ms per byte
    p.feed(b"0123456789", now=0.0)  # on the wire 0..100 ms
    assert p.due(0.025) == b"01"
    p.configure(baud=None, now=0.025)  # byte "2" is half sent
    assert p.due(0.0299) == b""
    assert p.due(0.030) == b"23456789"  # "2" at the old rate, the rest at once
    p.feed(b"ab", now=0.031)
    assert p.due(0.031) == b"ab" and p.in_flight() == 0

    p = Pipe("y")  # on the proxy's clock (the default), as the control socket does it
    p.configure(baud=1)  # 10 s per byte
    t0 = time.monotonic()
    for _ in range(50):
        p.feed(b"z", now=t0)
    p.configure(baud=None)
    p.feed(b"new", now=time.monotonic())
    assert p.due(t0 + 9.9) == b""
    assert p.due(t0 + 10.5) == b"z" * 50 + b"new"  # not 500 s later
    assert p.in_flight() == 0


def test_a_new_rate_retimes_the_bytes_waiting_and_keeps_the_latency() -> None:
    p = Pipe("x")
    p.configure(baud=1000, latency_s=0.005, now=0.0)
    p.feed(bytes(10), now=0.0)
    p.configure(baud=10_000, now=0.0)  # nothing on the wire yet: all of it at 1 ms per byte
    chunks = drain(p, 0.1, step=1e-5)
    assert sum(len(d) for _, d in chunks) == 10
    assert chunks[-1][0] == pytest.approx(0.015, abs=1e-4)
    p.configure(baud=100, now=1.0)
    p.feed(b"ab", now=1.0)  # 100 ms per byte from here
    assert p.due(1.104) == b""
    assert p.due(1.105) == b"a"
    p.configure(baud=None, now=1.15)  # "b" is on the wire: done at 1.2, then the latency
    assert p.due(1.204) == b"" and p.due(1.205) == b"b"
