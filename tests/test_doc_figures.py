"""Every performance figure in the docs comes from one source and names how it was produced
(issue 19): `tools/docfigures.py` renders the regions, and a region that differs from its source
(a hand-edited or stale figure) fails here."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tools import docfigures

REPO = Path(__file__).resolve().parent.parent


def _regions() -> list[tuple[Path, str]]:
    return [(doc, src) for doc in docfigures.DOCS for src in docfigures.sources(doc.read_text())]


def test_every_figure_region_matches_its_source() -> None:
    assert len(_regions()) >= 8, "the docs lost their figure regions"
    assert docfigures.main(["--check"]) == 0


def test_a_hand_edited_figure_is_caught(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    doc = tmp_path / "emulator.md"
    text = (REPO / "docs" / "emulator.md").read_text()
    region = re.search(r"<!-- figures: bench_chain/rtt -->\n\| .*?\n\|---.*?\n\| (\d+) \|", text)
    assert region is not None
    edited = text[: region.start(1)] + "99" + text[region.end(1) :]
    doc.write_text(edited)
    assert docfigures.main(["--check", str(doc)]) == 1
    assert "rerun the benchmark" in capsys.readouterr().out
    assert docfigures.main(["--write", str(doc)]) == 0
    assert doc.read_text() == text


def test_each_measured_region_names_its_command_machine_load_and_conditions() -> None:
    for doc, source in _regions():
        if "/" not in source or not source.startswith("bench_"):
            continue
        bench, _, table = source.partition("/")
        data = json.loads((REPO / "benchmarks" / "results" / f"{bench}.json").read_text())
        # a results file is named after its benchmark, or after a variant run of it
        # (bench_api_normal.json: bench_api.py with other options)
        assert bench == data["bench"] or bench.startswith(data["bench"] + "_"), doc
        assert data["command"].startswith(f".venv/bin/python benchmarks/{data['bench']}.py"), doc
        assert data["machine"]["cores"] and data["machine"]["cpu"], doc
        assert len(data["load_1min"]) == 2, doc
        assert data["tables"][table]["note"], f"{doc}: {source} has no conditions"
        body = docfigures.render(source)
        assert f"Measured by `{data['command']}`" in body and "1-min load" in body


def test_an_unknown_source_is_an_error_not_an_empty_region(tmp_path: Path) -> None:
    doc = tmp_path / "x.md"
    doc.write_text("<!-- figures: bench_chain/nope -->\n<!-- /figures -->\n")
    assert docfigures.main(["--check", str(doc)]) == 1
    doc.write_text("<!-- figures: floors/nope -->\n<!-- /figures -->\n")
    assert docfigures.main(["--check", str(doc)]) == 1


def test_a_benchmark_run_saves_tables_that_render_with_their_provenance(tmp_path: Path) -> None:
    out = tmp_path / "bench_chain.json"
    cmd = [
        sys.executable, "benchmarks/bench_chain.py", "--timing", "off", "--segments", "1",
        "--bauds", "921600", "--repeat", "3", "--duration", "0.3", "--figures", str(out),
    ]  # fmt: skip
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    data = json.loads(out.read_text())
    assert set(data["tables"]) == {"discovery", "rtt"}
    [row] = data["tables"]["rtt"]["rows"]
    assert row[:2] == ["1", "921600"]
    assert "--segments 1" in data["command"]
    body = docfigures.bench_region("bench_chain/rtt", results=tmp_path)
    assert body.startswith("| segments | baud (bit/s) |") and "timing model off" in body
