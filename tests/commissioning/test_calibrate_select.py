"""Review 3 defects C and D: ``ucr calibrate --segment`` counts positions from 1 (as every
message does) and refuses a name two segments share, listing their positions."""

from __future__ import annotations

import pytest

from host.calibrate_cli import find_segment

DESCS = [
    {"position": 0, "name": "segment_1", "uid": "aa01"},
    {"position": 1, "name": "segment_2", "uid": "bb02"},
]


def test_a_position_counts_from_1() -> None:
    assert find_segment(DESCS, "1")["name"] == "segment_1"
    assert find_segment(DESCS, "2")["name"] == "segment_2"
    with pytest.raises(ValueError) as info:
        find_segment(DESCS, "3")
    message = str(info.value)
    assert "position 1: segment_1 (aa01)" in message
    assert "position 2: segment_2 (bb02)" in message
    assert "0:" not in message


def test_a_name_two_segments_share_is_refused_with_their_positions() -> None:
    twins = [dict(DESCS[0]), {"position": 1, "name": "segment_1", "uid": "bb02"}]
    with pytest.raises(ValueError) as info:
        find_segment(twins, "segment_1")
    message = str(info.value)
    assert "2 segments are named 'segment_1'" in message
    assert "position 1 (aa01)" in message and "position 2 (bb02)" in message
    assert find_segment(twins, "bb02")["position"] == 1  # the uid still picks one
    assert find_segment(twins, "2")["uid"] == "bb02"
