"""The steady-state control cycle allocates nothing: proved with micropython.heap_lock() on the VM
with an ESP32-sized heap (any allocation inside the lock raises MemoryError).

One locked cycle = receive a SYNC from upstream (decode, forward downstream with hop+1, answer
STATE), receive a neighbour's STATE from downstream (forward upstream with hop+1), then the
control tick (servo poll, fault/stall checks, measurement, watchdog, MC slew + mapping, SC,
servo command, queued EVENT / ALIVE frames).
"""

from __future__ import annotations

import math

import pytest

from protocol import messages as M
from tests.device.conftest import decode, frames

CYCLES = 20


@pytest.mark.parametrize("driver", ["emulated", "pwm"])
def test_a_full_cycle_allocates_nothing_under_heap_lock(vm, driver):
    """With the emulator's servo driver and with the PWM driver (an ESP32 segment's default,
    machine.PWM replaced by the kit's LoopPwm): a PwmBus once allocated 32 bytes per command."""
    syncs = [
        M.encode_sync(i, 100 + i, [(2.0 + 0.02 * i, math.sin(i) * 3.0), (1.0, 0.0)])
        for i in range(CYCLES)
    ]
    states = [
        M.encode_state(
            i,
            cycle=100 + i,
            t_ms=5 * i,
            kappa=0.5,
            phi=0.1,
            servo_angles=[0.1, -0.2, 0.3],
            status=0,
        )
        for i in range(CYCLES)
    ]
    sizes_up = [len(s) for s in syncs]
    sizes_dn = [len(s) for s in states]
    r = vm(
        f"""
import micropython, gc
gc.collect()  # the script's own parse (its hex data) leaves garbage: free it before the boot
hal, seg = vmkit.make({{'sc': 'p_slew', 'servo_driver': '{driver}'}})
hal.up.feed(bytes.fromhex('{b"".join(syncs).hex()}'))
gc.collect()
hal.down.feed(bytes.fromhex('{b"".join(states).hex()}'))
SU = {sizes_up}
SD = {sizes_dn}
hal.up.gate = 0
hal.down.gate = 0

def cycle(i):
    hal.up.discard()
    hal.down.discard()
    hal.up.allow(SU[i])
    hal.down.allow(SD[i])
    hal.t += 5
    seg.poll()
    seg.tick(hal.t)

for i in range(4):       # warm-up: first use of every path
    cycle(i)
gc.collect()
t0 = hal.up.total
micropython.heap_lock()
try:
    for i in range(4, {CYCLES}):
        cycle(i)
finally:
    micropython.heap_unlock()
R['bytes_up'] = hal.up.total - t0
R['up'] = vmkit.hexs(hal.up.take())
R['down'] = vmkit.hexs(hal.down.take())
R['moving'] = [seg.moving, seg.mc.cx, seg.mc.cy]
""",
        # 16 KB over the ESP32 budget for the script's 40 frames of hex data (the boot's heap is
        # bench_firmware's figure); heap_lock proves the cycle allocates nothing at any size
        heap="176k",
    )
    up = decode(r["up"])  # the last locked cycle's output
    own = [m for m in up if m["type"] == "STATE" and m["hop"] == 0]
    fwd = [m for m in up if m["type"] == "STATE" and m["hop"] == 1]
    assert [m["seq"] for m in own] == [CYCLES - 1] and [m["seq"] for m in fwd] == [CYCLES - 1]
    down = frames(r["down"])
    assert [(f.mtype, f.hop, f.seq) for f in down] == [(0x02, 1, CYCLES - 1)]
    # two STATE frames per locked cycle went up (protocol v2: every STATE has the same size)
    assert r["bytes_up"] >= (CYCLES - 4) * 2 * min(sizes_dn)
    moving, cx, cy = r["moving"]
    assert moving and (cx, cy) != (0, 0)
