"""Benchmark figures with their provenance: what `tools/docfigures.py` writes into the docs.

A benchmark run with ``--figures FILE`` saves, next to what it prints, the tables the docs quote
and the conditions they were measured under: the exact command, the machine (CPU model, cores,
architecture), the load (1-minute load average before and after), the Python and MicroPython
versions, the date, and per table its own conditions (e.g. the emulator's timing model). The docs
never carry a hand-typed figure from a benchmark: `tools/docfigures.py --write` renders each
``<!-- figures: bench_x/table -->`` region from ``benchmarks/results/bench_x.json`` and
``--check`` (run by the test suite) fails when a region differs from its results file.

Use::

    figs = Figures.from_argv("bench_chain")          # None unless --figures FILE was given
    figs.table("rtt", ["segments", "RTT ms"], note="timing model off")
    figs.row("rtt", [3, "5.18"])
    figs.save()
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
import time
from pathlib import Path


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _micropython_version() -> str:
    try:
        from tools.mpvm import micropython_binary  # noqa: PLC0415

        code = "import sys; print('%d.%d.%d' % sys.implementation.version[:3])"
        out = subprocess.run(
            [micropython_binary(), "-c", code], capture_output=True, text=True, timeout=10,
            check=False,
        )  # fmt: skip
        return out.stdout.strip() or "unknown"
    except Exception:  # noqa: BLE001 - provenance is best effort, never stops a benchmark
        return "unknown"


def machine() -> dict:
    """The conditions every figure depends on, as of now."""
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "arch": platform.machine(),
        "python": platform.python_version(),
        "micropython": _micropython_version(),
    }


class Figures:
    """Tables a benchmark run produced, saved as JSON with the run's conditions."""

    def __init__(self, bench: str, path: str | os.PathLike, argv: list[str]):
        self.bench = bench
        self.path = Path(path)
        args = " ".join(shlex.quote(a) for a in argv)
        self.command = f".venv/bin/python benchmarks/{bench}.py {args}".strip()
        self.started = time.strftime("%Y-%m-%d", time.gmtime())
        self.load_before = round(os.getloadavg()[0], 2)
        self.tables: dict[str, dict] = {}

    @classmethod
    def from_argv(cls, bench: str, argv: list[str] | None = None) -> Figures | None:
        """``Figures`` if ``--figures FILE`` is among the arguments (which the benchmark's own
        parser must accept), else None."""
        argv = list(sys.argv[1:] if argv is None else argv)
        for i, a in enumerate(argv):
            if a == "--figures" and i + 1 < len(argv):
                return cls(bench, argv[i + 1], argv)
            if a.startswith("--figures="):
                return cls(bench, a.split("=", 1)[1], argv)
        return None

    def table(self, name: str, headers: list[str], note: str = "") -> None:
        """Starts table ``name`` (columns ``headers``; ``note``: its own conditions)."""
        self.tables[name] = {"headers": list(headers), "rows": [], "note": note}

    def row(self, name: str, cells: list) -> None:
        table = self.tables[name]
        if len(cells) != len(table["headers"]):
            raise ValueError(f"{name}: {len(cells)} cells for {len(table['headers'])} columns")
        table["rows"].append([str(c) for c in cells])

    def save(self) -> Path:
        data = {
            "bench": self.bench,
            "command": self.command,
            "date": self.started,
            "machine": machine(),
            "load_1min": [self.load_before, round(os.getloadavg()[0], 2)],
            "tables": self.tables,
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n")
        print(f"figures: {self.path} ({', '.join(self.tables)})", flush=True)
        return self.path
