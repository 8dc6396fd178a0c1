"""Issue 12: positions are counted from 1 wherever a user reads them (segment_1 is position 1),
while the wire keeps the 0-based chain index. Every text goes through host.positions, and every
record a user reads (API replies, events) shows ``index + 1``."""

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


# Records that stay on the wire side (0-based chain index by design); everything built from them
# for a user goes through host.supervision, which counts from 1.
_WIRE_RECORDS = {"link_frames.py"}


def test_no_host_record_shows_a_raw_position_index() -> None:
    """A ``{"position": pos}`` (or ``self.position``) dict handed out raw shows a 0-based index
    next to messages that say "position 1": a shown position is ``pos + 1`` (or None)."""
    offenders = []
    for path in HOST.rglob("*.py"):
        if path.name in _WIRE_RECORDS:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Dict):
                continue
            for key, value in zip(node.keys, node.values, strict=True):
                if (
                    isinstance(key, ast.Constant)
                    and key.value == "position"
                    and isinstance(value, ast.Name | ast.Attribute | ast.Subscript)
                    and "pos" in ast.unparse(value)
                ):
                    offenders.append(f"{path.relative_to(HOST.parent)}:{value.lineno}")
    assert not offenders, f"show positions counted from 1 (index + 1): {offenders}"


def test_topology_differences_count_positions_from_one() -> None:
    """`topology()["differences"][i]["position"]` agrees with its message ("position 1")."""
    from host.chain_report import describe_chain
    from host.topology import compare
    from ucrdf.parser import load

    robot = load(str(Path(__file__).resolve().parents[2] / "robots" / "softrobot3.ucrdf"))
    cmp = compare(robot, [{"model": "ppc", "length": 0.316}])
    out = describe_chain(robot, robot, [{"position": 0}], [], cmp, None)
    shown = [(d["kind"], d["position"], d["message"]) for d in out["differences"]]
    assert shown[0][:2] == ("count", None)
    model = [s for s in shown if s[0] == "model"]
    assert model and model[0][1] == 1 and model[0][2].startswith("position 1 (segment_1)")
    for _, pos, msg in shown[1:]:
        assert msg.startswith(f"position {pos} "), (pos, msg)
