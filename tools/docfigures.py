"""Writes (or checks) the figures in docs/*.md from their one source.

A figure region in a doc is::

    <!-- figures: SOURCE -->
    ... generated: never edit by hand ...
    <!-- /figures -->

SOURCE is ``bench_x/table``: the table ``table`` that ``benchmarks/bench_x.py --figures
benchmarks/results/bench_x.json`` saved, rendered as a Markdown table followed by its provenance
(the command, the machine, the load, the table's own conditions, the date); or ``floors/NAME``:
figures computed from ``host/floors.py`` (the floor definitions, docs/protocol.md "Floors");
``flash/payload``: what ``ucr flash`` writes (``tools/flash.py``); or ``protocol/…``: wire sizes
and the rates they imply (``benchmarks/bench_protocol.py``). Computed ones need no measurement.

    .venv/bin/python -m tools.docfigures --check     # exit 1 and a diff if any region is stale
    .venv/bin/python -m tools.docfigures --write     # rewrite the regions from the results

To refresh a figure, rerun its benchmark with the command the region names, then ``--write``.
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

REGION = re.compile(
    r"(?P<open><!-- figures: (?P<source>[\w./-]+) -->\n)(?P<body>.*?)(?P<close><!-- /figures -->)",
    re.S,
)


class FiguresError(Exception):
    """A region names a source that does not exist (results file, table or computation)."""


def _md_table(headers: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out) + "\n"


def _provenance(data: dict, note: str) -> str:
    m = data["machine"]
    load = data["load_1min"]
    cond = [
        f"{m['cores']} × {m['cpu']} ({m['arch']})",
        f"1-min load {load[0]:g} → {load[1]:g}",
        f"Python {m['python']}",
        f"MicroPython {m['micropython']}",
    ]
    if note:
        cond.append(note)
    return f"\nMeasured by `{data['command']}` on {data['date']}: {'; '.join(cond)}.\n"


def bench_region(source: str, results: Path = RESULTS) -> str:
    bench, _, table = source.partition("/")
    path = results / f"{bench}.json"
    if not path.exists():
        raise FiguresError(f"{source}: no results file {path.relative_to(REPO)}")
    data = json.loads(path.read_text())
    if table not in data["tables"]:
        known = ", ".join(data["tables"]) or "none"
        raise FiguresError(f"{source}: {path.name} has no table {table!r} (tables: {known})")
    t = data["tables"][table]
    return _md_table(t["headers"], t["rows"]) + _provenance(data, t.get("note", ""))


def _floors_exchange() -> str:
    """The daemon's rate warning bound (largest frames, store-and-forward) per chain length."""
    from host import floors  # noqa: PLC0415
    from host.chain_report import largest_rate_hz  # noqa: PLC0415

    headers = ["segments", "115200 bd", "921600 bd", "2000000 bd"]
    rows = []
    for n in (1, 3, 8):
        cells = [str(n)]
        for baud in (115200, 921600, 2000000):
            sf = floors.store_and_forward_floor_s(n, baud)
            lr = floors.line_rate_floor_s(n, baud)
            rate = largest_rate_hz(n, baud)
            cells.append(f"{sf * 1e3:.1f} ms (line rate {lr * 1e3:.1f} ms) → rate_hz ≤ {rate}")
        rows.append(cells)
    return _md_table(headers, rows) + (
        "\nComputed by `host/floors.py` and `host/chain_report.py`: the store-and-forward floor, "
        "in brackets the line-rate floor, at the largest frames the encoders produce; then the "
        "largest `rate_hz` the daemon runs without its rate warning (0.8 × period ≥ the floor; "
        "above 20 ms also `watchdog.reply_timeout_s` must be raised).\n"
    )


def _flash_payload() -> str:
    """What `ucr flash` writes for segment_2 of softrobot3 to a classic ESP32, as files and bytes
    (the payload; the REPL's own framing comes on top, and the command counts that per run)."""
    from tools import mpy as mpy_tools  # noqa: PLC0415
    from tools.flash import BoardInfo, build_files  # noqa: PLC0415
    from tools.segment_config import config_for  # noqa: PLC0415
    from ucrdf.parser import load  # noqa: PLC0415

    robot = load(REPO / "robots" / "softrobot3.ucrdf")
    config = config_for(robot, "segment_2")
    esp32 = 6 | (3 << 8) | (mpy_tools.MPY_ARCHES.index("xtensawin") << 10)  # mpy v6.3 xtensawin
    info = BoardInfo("micropython", "esp32", esp32, "v1.24.1")
    rows = []
    for label, mpy in (("precompiled (default): .mpy v6.3 xtensawin", True),
                       ("`--source`: source files", False)):  # fmt: skip
        files = build_files(config, mpy=mpy, info=info, log=lambda _line: None)
        payload = sum(len(data) for _path, data in files)
        rows.append([label, str(len(files)), str(payload), f"{payload * 10 / 115200:.1f} s"])
    return _md_table(
        ["deployed as", "files", "payload bytes", "payload alone at 115200 bd"], rows
    ) + (
        "\nComputed by `tools/flash.py` (`build_files`, the files `ucr flash` writes) for "
        "segment_2 of robots/softrobot3.ucrdf and a classic ESP32.\n"
    )


def _protocol(table: str) -> Callable[[], str]:
    def render_table() -> str:
        sys.path.insert(0, str(REPO / "benchmarks"))
        try:
            import bench_protocol  # noqa: PLC0415
        finally:
            sys.path.remove(str(REPO / "benchmarks"))
        headers, rows = bench_protocol.wire_tables()[table]
        return _md_table(headers, rows) + (
            "\nComputed by `benchmarks/bench_protocol.py` (`wire_tables`) from the encoders in "
            "`protocol/` and the floors of `host/floors.py`; no processing time included.\n"
        )

    return render_table


COMPUTED: dict[str, Callable[[], str]] = {
    "protocol/sizes": _protocol("sizes"),
    "protocol/rates": _protocol("rates"),
    "protocol/others": _protocol("others"),
    "floors/exchange": _floors_exchange,
    "flash/payload": _flash_payload,
}


def render(source: str, results: Path = RESULTS) -> str:
    if source in COMPUTED:
        return COMPUTED[source]()
    if source.startswith(("floors/", "flash/", "protocol/")):
        raise FiguresError(f"{source}: unknown computation (known: {', '.join(COMPUTED)})")
    return bench_region(source, results)


def regenerate(text: str, results: Path = RESULTS) -> str:
    """``text`` with every figure region rendered anew."""

    def sub(m: re.Match) -> str:
        return m.group("open") + render(m.group("source"), results) + m.group("close")

    return REGION.sub(sub, text)


def sources(text: str) -> list[str]:
    return [m.group("source") for m in REGION.finditer(text)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    mode = ap.add_mutually_exclusive_group(required=True)
    mode.add_argument("--check", action="store_true", help="exit 1 if any region is stale")
    mode.add_argument("--write", action="store_true", help="rewrite the regions in place")
    ap.add_argument("files", nargs="*", type=Path, help="docs to process (default: all)")
    args = ap.parse_args(argv)
    stale = 0
    for path in args.files or DOCS:
        text = path.read_text()
        try:
            new = regenerate(text)
        except FiguresError as e:
            print(f"{path}: {e}", file=sys.stderr)
            return 1
        if new == text:
            continue
        if args.write:
            path.write_text(new)
            print(f"{path}: figures rewritten")
        else:
            stale += 1
            diff = difflib.unified_diff(
                text.splitlines(True), new.splitlines(True), str(path), f"{path} (regenerated)"
            )
            sys.stdout.writelines(diff)
    if stale:
        print(
            f"{stale} doc(s) have figures that differ from benchmarks/results/: rerun the "
            "benchmark the region names, then `python -m tools.docfigures --write`"
        )
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
