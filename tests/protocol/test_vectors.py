"""The committed vectors (protocol/vectors/vectors.jsonl) hold on CPython and on MicroPython."""

from __future__ import annotations

import mp_runner
import pytest
from protocol_testkit import approx_equal, load_vectors

VECTORS = load_vectors()
CHECKED = ("hex", "decoded", "device", "error")


def _assert_matches(expected: dict, got: dict, where: str) -> None:
    for key in CHECKED:
        assert (key in expected) == (key in got), f"{where} {expected['name']}: {key} presence"
        if key in expected:
            assert approx_equal(expected[key], got[key]), (
                f"{where} {expected['name']} {key}: expected {expected[key]!r}, got {got[key]!r}"
            )


def test_vector_file_covers_every_message_type() -> None:
    calls = {v["call"] for v in VECTORS}
    for needed in (
        "encode_discover",
        "encode_sync",
        "encode_heartbeat",
        "encode_param_get",
        "encode_param_set",
        "encode_hold",
        "encode_alive",
        "encode_descriptor",
        "encode_state",
        "encode_param_value",
        "encode_event",
        "encode_error",
        "device.state_frame",
        "forward",
    ):
        assert needed in calls, needed


@pytest.mark.parametrize("vector", VECTORS, ids=[v["name"] for v in VECTORS])
def test_vector_reproduced_on_cpython(vector: dict) -> None:
    _assert_matches(vector, mp_runner.run_vector(vector), "CPython")


def test_vectors_reproduced_on_micropython(mp_batch) -> None:
    job, res = mp_batch
    got = {r["name"]: r for r in res["vectors"]}
    for v in VECTORS:
        _assert_matches(v, got[v["name"]], "MicroPython")


def test_known_answer_vectors() -> None:
    """Independent anchors: published CRC check value and COBS example."""
    by = {v["name"]: v for v in VECTORS}
    assert by["crc_check"]["hex"] == "29b1"  # CRC-16/CCITT-FALSE check value (reveng catalogue)
    assert by["cobs_basic"]["hex"] == "0311220233"  # COBS paper / Wikipedia example
    assert by["cobs_zeros"]["hex"] == "010101"
