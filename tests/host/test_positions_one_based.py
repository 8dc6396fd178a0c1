"""Issue 12: positions are counted from 1 wherever a user reads them (segment_1 is position 1),
while wire and API data keep the 0-based chain index. Every text goes through host.positions."""

from __future__ import annotations

import ast
from pathlib import Path

from host.positions import label, labels
from host.supervision import describe_event

HOST = Path(__file__).resolve().parents[2] / "host"


def test_labels_count_from_one() -> None:
    assert label(0) == "position 1"
    assert label(2) == "position 3"
    assert labels([0, 2]) == "positions 1, 3"
    assert label(None) == "position None"  # a missing index is shown, never shifted


def test_an_event_of_the_first_segment_names_position_one() -> None:
    descs = [{"name": "segment_1"}, {"name": "segment_2"}]
    text = describe_event({"name": "BOOT", "position": 0}, descs)
    assert text == "segment_1 (position 1): booted"


def test_no_host_message_formats_a_raw_position_index() -> None:
    """A literal 'position {…}' in an f-string bypasses the one place that counts from 1."""
    offenders = []
    for path in HOST.rglob("*.py"):
        if path.name == "positions.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.JoinedStr):
                parts = node.values
                for a, b in zip(parts, parts[1:], strict=False):
                    if (
                        isinstance(a, ast.Constant)
                        and str(a.value).rstrip().endswith(("position", "positions", "segment"))
                        and isinstance(b, ast.FormattedValue)
                        and "pos" in ast.unparse(b.value)
                    ):
                        offenders.append(f"{path.relative_to(HOST.parent)}:{node.lineno}")
    assert not offenders, f"format positions with host.positions.label: {offenders}"


def test_the_topology_listing_counts_positions_from_one() -> None:
    """`topology()` segments (and the /ucr/segments diagnostics built from them) count from 1,
    like events and the CLI (issue 12: positions 1-based wherever a user sees them)."""
    from host.chain_report import describe_chain
    from ucrdf.parser import load

    robot = load(str(Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"))
    descs = [{"position": i, "uid": f"u{i}", "name": f"segment_{i + 1}"} for i in range(3)]
    names = ["segment_1", "segment_2", "segment_3"]
    out = describe_chain(robot, robot, descs, names, None, None)
    assert [(s["position"], s["bendable"]) for s in out["segments"]] == list(
        zip([1, 2, 3], names, strict=True)
    )
