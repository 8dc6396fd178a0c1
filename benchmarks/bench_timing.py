"""The emulator's CPU factor, re-derived: pystone 1.2 and the calibration kernel on this host's
MicroPython VM, their ratio against the constant the emulator uses, and the factor per board.

    .venv/bin/python benchmarks/bench_timing.py --pystone PATH [--pairs 6] [--figures FILE]

(``$UCR_PYSTONE`` instead of ``--pystone``; without either it says what it needs and exits 0,
so that ``./run.sh bench`` goes on.)

PATH is MicroPython's own ``tests/perf_bench/misc_pystone.py`` from a checkout of
github.com/micropython/micropython (not part of this project; any version with pystone 1.2). Each
pair runs pystone (20000 loops) and ``tools.emulator.timing.KERNEL`` back to
back on the same VM (best of 15 each: on a shared machine single runs can be half as fast); the
kernel-loops-per-pystone ratio is what ``KERNEL_PER_PYSTONE`` in
tools/emulator/timing.py holds (docs/emulator.md "Timing model"). Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.figures import Figures  # noqa: E402
from protocol import boards  # noqa: E402
from tools import mpvm  # noqa: E402
from tools.emulator import timing  # noqa: E402

LOOPS = 20000

# Appended to pystone's source: its Setup()/Proc0(loops) (the perf_bench interface), timed here.
DRIVER = """
import time
best = None
for _ in range(15):
    Setup()
    t0 = time.ticks_us()
    Proc0({loops})
    dt = time.ticks_diff(time.ticks_us(), t0)
    best = dt if best is None or dt < best else best
print('@@', {loops} * 1000000 // best)
"""


def pystones(source: str) -> int:
    """Pystones/s of this host's VM (best of 15 runs of ``LOOPS``)."""
    out = mpvm.run_code(source + DRIVER.format(loops=LOOPS), timeout=300)
    m = re.search(r"@@ (\d+)", out)
    if not m:
        raise RuntimeError(f"pystone printed no result: {out[-300:]!r}")
    return int(m.group(1))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pystone", metavar="PATH", default=os.environ.get("UCR_PYSTONE"),
                    help="MicroPython's tests/perf_bench/misc_pystone.py (default: "
                    "$UCR_PYSTONE)")  # fmt: skip
    ap.add_argument("--pairs", type=int, default=6, help="pystone + kernel pairs (6)")
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = ap.parse_args(argv)
    figs = Figures.from_argv("bench_timing", argv)
    if not args.pystone:  # not ours to ship: say what it needs and step aside (./run.sh bench)
        print("bench_timing: skipped: it needs MicroPython's pystone, tests/perf_bench/"
              "misc_pystone.py of a micropython checkout (not part of this project): "
              "--pystone PATH or UCR_PYSTONE=PATH")  # fmt: skip
        return 0
    path = Path(args.pystone)
    try:
        source = path.read_text()
    except OSError as exc:
        print(f"bench_timing: cannot read {path}: {exc.strerror}", file=sys.stderr)
        return 2
    if "def Proc0" not in source or "def Setup" not in source:
        print(f"bench_timing: {path} is not MicroPython's pystone (no Setup/Proc0)",
              file=sys.stderr)  # fmt: skip
        return 2
    rows = []
    for k in range(args.pairs):
        p = pystones(source)
        kr = timing.kernel_rate(runs=1)
        rows.append((p, kr, kr / p))
        print(f"pair {k + 1}: pystone {p} /s, kernel {kr} loops/s, {kr / p:.2f} loops per pystone")
    ratios = [r for *_, r in rows]
    host = statistics.median(p for p, *_ in rows)
    ratio = statistics.median(ratios)
    print(f"median: {host:.0f} pystones/s, {ratio:.2f} kernel loops per pystone "
          f"(KERNEL_PER_PYSTONE = {timing.KERNEL_PER_PYSTONE})")  # fmt: skip
    factors = []
    for name in ("esp32", "esp32s3", "esp32c3"):
        prof = boards.profile(name)
        f = timing.cpu_factor(name, host)
        factors.append((name, prof, f))
        print(f"  {name:8s} {prof['pystones']} pystones/s at {prof['mhz']} MHz: CPU factor {f:.0f}")
    if figs is not None:
        figs.table(
            "calibration",
            ["pair", "pystone 1.2 on this VM", "calibration kernel", "kernel loops per pystone"],
            note=f"pystone {LOOPS} loops, best of 15, then KERNEL best of 15, on the same VM; "
            f"the emulator's constant KERNEL_PER_PYSTONE = {timing.KERNEL_PER_PYSTONE}",
        )
        for k, (p, kr, r) in enumerate(rows):
            figs.row("calibration", [str(k + 1), f"{p:,} /s", f"{kr:,} loops/s", f"{r:.2f}"])
        figs.row("calibration", ["median", f"{host:,.0f} /s", "", f"{ratio:.2f}"])
        figs.table(
            "factors",
            ["board", "pystones/s (protocol/boards.py)", "clock", "CPU factor on this host"],
            note="host pystones (the median above) / the board's; the emulator itself estimates "
            "the host's through the kernel on every start",
        )
        for name, prof, f in factors:
            figs.row("factors", [name, str(prof["pystones"]), f"{prof['mhz']} MHz", f"{f:.0f}"])
        figs.save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
