"""The chain floors (docs/protocol.md "Floors", host/floors.py): definitions and the bounds the
daemon's rate warning relies on."""

from __future__ import annotations

import pytest

from host import floors
from host.link import exchange_floor_s
from protocol import messages as M


@pytest.mark.parametrize("n", [1, 3, 8])
def test_line_rate_floor_is_the_bytes_on_link_zero(n: int) -> None:
    sync, state = 40, 70
    assert floors.line_rate_floor_s(n, 921600, sync, state) == pytest.approx(
        (sync + n * state) * 10 / 921600
    )
    assert floors.store_and_forward_floor_s(n, 921600, sync, state) == pytest.approx(
        n * (sync + state) * 10 / 921600
    )


def test_store_and_forward_floor_exceeds_line_rate_floor_beyond_one_segment() -> None:
    assert floors.line_rate_floor_s(1, 115200) == pytest.approx(
        floors.store_and_forward_floor_s(1, 115200)
    )
    for n in (2, 3, 8):
        assert floors.store_and_forward_floor_s(n, 115200) > floors.line_rate_floor_s(n, 115200)


def test_daemon_warning_floor_is_the_store_and_forward_floor() -> None:
    for n in (1, 3, 8):
        assert exchange_floor_s(n, 921600) == floors.store_and_forward_floor_s(n, 921600)
    assert exchange_floor_s(0, 921600) == 0.0


def test_largest_sizes_bound_real_frames() -> None:
    state = M.encode_state(
        7,
        cycle=2**29,
        t_ms=2**29,
        kappa=-2.9,
        phi=3.1,
        servo_angles=[2.9, -2.9, 1.0],
        status=0x3F,
    )
    assert len(state) <= floors.max_state_bytes()
    sync = M.encode_sync(7, 2**29, [(-20.0, 3.1)] * 8)
    assert len(sync) <= floors.max_sync_bytes(8)
    for n in (1, 3, 8):  # the SYNC that ends a HOLD carries the resume key on top
        resume = M.encode_sync(7, 2**30 - 1, [(-20.0, 3.1)] * n, resume=True)
        assert len(resume) <= floors.max_sync_bytes(n)


def test_pipelined_ceiling_is_set_by_the_busiest_direction() -> None:
    assert floors.pipelined_rate_hz(8, 921600, 80, 70) == pytest.approx(92160 / (8 * 70))
    assert floors.pipelined_rate_hz(1, 921600, 80, 70) == pytest.approx(92160 / 80)
