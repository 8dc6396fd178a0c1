"""Steady-state device paths allocate nothing on the MicroPython heap (heap_lock proof)."""

from __future__ import annotations

import pytest
from protocol_testkit import HERE, REPO

from tools.mpvm import run_code


@pytest.fixture(scope="module", params=["viper", "pure"])
def alloc_report(request) -> dict[str, str]:
    pure = request.param == "pure"
    out = run_code(f"import mp_alloc\nmp_alloc.main(20, {pure})\n", paths=[REPO, HERE], timeout=60)
    report = {}
    for line in out.splitlines():
        name, _, rest = line.partition(" ")
        report[name] = rest
    return report


@pytest.mark.parametrize(
    "check",
    [
        "rx_cycle",  # (a) reader + (b) SYNC/HEARTBEAT decode + (d) forwarding, one receive cycle
        "scan_only",  # (a)
        "decode_sync8",  # (b)
        "tx_state",  # (c)
        "tx_state_parts",  # (c)
        "forward",  # (d)
        "tx_small",
        "malformed",
    ],
)
def test_device_path_allocates_nothing(alloc_report: dict[str, str], check: str) -> None:
    assert alloc_report[check] == "ok", f"{check}: {alloc_report[check]}"


def test_allocation_is_detected_by_the_harness(alloc_report: dict[str, str]) -> None:
    assert alloc_report["control_allocates"].startswith("ALLOC")


def test_both_loop_variants_are_exercised(alloc_report: dict[str, str], request) -> None:
    pure = request.node.callspec.params["alloc_report"] == "pure"
    assert alloc_report["fast"] == str(not pure)


def test_receive_cycle_really_processed_frames(alloc_report: dict[str, str]) -> None:
    """The locked loop handled frames (21 passes x 5 frames) and counted the garbage."""
    frames, ok, crc_err, framing = (int(x) for x in alloc_report["frames"].split())
    assert frames == 21 * 5
    assert ok >= frames
    assert crc_err + framing >= 21
