"""Every hex example in docs/protocol.md is a committed test vector, byte for byte."""

from __future__ import annotations

from protocol_testkit import REPO, load_vectors

from protocol import cobs

DOC = REPO / "docs" / "protocol.md"


def _doc_examples() -> list[tuple[str, str, str]]:
    """(vector name, raw line, wire line) for every ``vector:`` block in the spec."""
    lines = DOC.read_text().splitlines()
    out = []
    for i, line in enumerate(lines):
        if line.startswith("vector: "):
            raw = lines[i + 1]
            wire = lines[i + 2]
            assert raw.startswith("raw:  ") and wire.startswith("wire: "), line
            out.append((line[8:].strip(), raw[6:], wire[6:]))
    return out


def test_spec_examples_match_the_vectors() -> None:
    vectors = {v["name"]: v for v in load_vectors()}
    examples = _doc_examples()
    assert len(examples) >= 15
    for name, raw, wire in examples:
        w = bytes.fromhex(wire)
        assert w.hex() == vectors[name]["hex"], name
        parts = [bytes.fromhex(p) for p in raw.split("|")]
        assert len(parts) == 4 and len(parts[0]) == 5, name  # header | payload | pad | CRC
        assert parts[2] == b"\x00" and len(parts[3]) == 2, name
        assert b"".join(parts) == cobs.decode(w[:-1]), name


def test_spec_shows_every_message_type() -> None:
    text = DOC.read_text()
    for title in (
        "0x01 DISCOVER",
        "0x02 SYNC",
        "0x03 HEARTBEAT",
        "0x04 PARAM_GET",
        "0x05 PARAM_SET",
        "0x06 HOLD",
        "0x07 ALIVE",
        "0x81 DESCRIPTOR",
        "0x83 STATE",
        "0x84 PARAM_VALUE",
        "0x85 EVENT",
        "0xFF ERROR",
    ):
        assert f"### {title}" in text, title
