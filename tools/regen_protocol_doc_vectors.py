"""Rewrite the ``raw:``/``wire:`` lines of every ``vector:`` block in docs/protocol.md from
protocol/vectors/vectors.jsonl (run after tests/protocol/make_vectors.py;
tests/protocol/test_docs.py checks the result byte for byte)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from protocol import cobs  # noqa: E402

DOC = REPO / "docs" / "protocol.md"
VECTORS = REPO / "protocol" / "vectors" / "vectors.jsonl"


def _sp(b: bytes) -> str:
    return " ".join(f"{x:02x}" for x in b)


def main() -> int:
    vectors = {}
    for line in VECTORS.read_text().splitlines():
        if line.strip():
            v = json.loads(line)
            vectors[v["name"]] = v
    lines = DOC.read_text().splitlines()
    for i, line in enumerate(lines):
        if not line.startswith("vector: "):
            continue
        name = line[8:].strip()
        wire = bytes.fromhex(vectors[name]["hex"])
        raw = cobs.decode(wire[:-1])
        lines[i + 1] = (
            f"raw:  {_sp(raw[:5])} | {_sp(raw[5:-3])} | {_sp(raw[-3:-2])} | {_sp(raw[-2:])}"
        )
        lines[i + 2] = f"wire: {_sp(wire)}"
    DOC.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
