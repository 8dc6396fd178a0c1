"""The emulator's timing model: how much slower a board computes than the host running the VM.

CPU factor = host speed / board speed, both in pystones/s (pystone 1.2, the benchmark published
for MicroPython boards). The board's score is in its profile (``protocol/boards.py``: ESP32 at
the 240 MHz the firmware sets at boot, 1661, derived in docs/emulator.md "Timing model"). The
host's score is estimated by running :data:`KERNEL` (our own mix of calls, attribute and
bytearray access and small-int arithmetic, like the firmware's cycle) on the MicroPython VM and
scaling by
:data:`KERNEL_PER_PYSTONE`, the ratio measured once beside pystone on the same VM.
"""

from __future__ import annotations

import functools
import re

from protocol import boards
from tools import mpvm

#: Kernel loops per pystone, measured by benchmarks/bench_timing.py (docs/emulator.md "Timing
#: model"): pystone 1.2 (MicroPython's tests/perf_bench/misc_pystone.py, 20000 loops) and KERNEL,
#: best of 15 each, back to back on the same VM, median of 6 pairs: 12.16 on the 2-core x86_64
#: development machine with MicroPython 1.29.0 (13.4 earlier, best of 5, with 1.28.0.2).
KERNEL_PER_PYSTONE = 12.2

#: The calibration kernel as a function: ``kernel_loops_per_s()`` (best of 15 timed runs), for
#: code that measures the host's speed in the same VM process as what it scales (bench_firmware).
KERNEL_FUNC = """
import time
class _KC:
    def __init__(self):
        self.a = 0
        self.buf = bytearray(64)
    def step(self, i):
        b = self.buf
        b[i & 63] = (b[(i + 1) & 63] + i) & 0xFF
        self.a = (self.a * 31 + b[i & 63]) & 0x3FFFFFF
        return self.a
def _krun(n):
    c = _KC()
    s = 0
    lst = [0] * 8
    for i in range(n):
        s += c.step(i)
        lst[i & 7] = s & 0xFFFF
    return s
def kernel_loops_per_s():
    best = None
    for _ in range(15):
        t0 = time.ticks_us()
        _krun(20000)
        dt = time.ticks_diff(time.ticks_us(), t0)
        best = dt if best is None or dt < best else best
    return 20000 * 1000000 // best
"""

KERNEL = (
    KERNEL_FUNC
    + """
print('@@', kernel_loops_per_s())
"""
)


def kernel_rate(runs: int = 3) -> int:
    """KERNEL loops per second on this host's MicroPython VM: the best of ``runs`` VM runs of
    15 timed loops each (about 0.2 s per run). On a shared machine a whole run can land in a
    window where the VM goes at half speed, so one run alone could halve the CPU factor."""
    best = 0
    for _ in range(runs):
        out = mpvm.run_code(KERNEL, timeout=60)
        m = re.search(r"@@ (\d+)", out)
        if not m:
            raise RuntimeError(f"calibration kernel printed no result: {out!r}")
        best = max(best, int(m.group(1)))
    return best


@functools.lru_cache(maxsize=1)
def host_pystones() -> float:
    """This host's MicroPython VM speed in pystones/s (estimated through KERNEL)."""
    return kernel_rate() / KERNEL_PER_PYSTONE


def cpu_factor(board: str, host: float | None = None) -> float:
    """How many times longer ``board`` takes than this host's VM for the same code (>= 1);
    ``host``: the host's pystones/s when the caller measured them (default: estimated here)."""
    p = boards.profile(board)
    if not p["pystones"]:
        return 1.0
    return max(1.0, (host_pystones() if host is None else host) / p["pystones"])
