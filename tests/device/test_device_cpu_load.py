"""CPU load (PARAM 23, docs/firmware.md "CPU load"): the share of each second a segment does not
spend waiting in ``hal.wait``, so a board that cannot keep its tick and the host's rate says so
(`ucr doctor`) instead of forwarding and ticking late in silence."""

from __future__ import annotations

import cbor2

from protocol import messages as M
from protocol.constants import T_PARAM_VALUE
from tests.device.conftest import frames

_CLOCK_HAL = """
class ClockHal(vmkit.LoopHal):
    # the loopback HAL on a clock the test drives: compute and waiting are what the test says
    def __init__(self):
        vmkit.LoopHal.__init__(self)
        self.us = 0
    def ticks_us(self):
        return self.us
    def ticks_diff(self, a, b):
        return a - b
    def wait(self, ms):
        self.us += ms * 1000
        self.idle_us += ms * 1000

def make_clocked():
    import config, servos
    from segment import Segment
    hal = ClockHal()
    cfg = config.Config({}, 'emulated')
    return hal, Segment(hal, cfg, servos.make(cfg.driver, cfg, hal), 5)

def run(hal, seg, ms, busy_us):
    # ticks every 5 ms: busy_us of compute, the rest of the period waited
    for _ in range(ms // 5):
        hal.t += 5
        seg.poll()
        seg.tick(hal.ticks_ms())
        hal.us += busy_us
        hal.wait(5 - busy_us // 1000)

def cpu_load(hal, seg):
    hal.up.take()
    hal.up.feed(bytes.fromhex(GET))
    seg.poll()
    return vmkit.hexs(hal.up.take())
"""


def test_cpu_load_is_the_share_of_each_second_not_spent_waiting(vm):
    get = M.encode_param_get(7, 0, 23).hex()
    r = vm(
        f"""
GET = '{get}'
{_CLOCK_HAL}
hal, seg = make_clocked()
R['first'] = cpu_load(hal, seg)          # no whole window yet
run(hal, seg, 2100, 2000)               # 2 ms of 5 busy: 40 %
R['light'] = cpu_load(hal, seg)
run(hal, seg, 2100, 5000)               # never waits: 100 %
R['saturated'] = cpu_load(hal, seg)
run(hal, seg, 2100, 1000)               # 20 %, the peak stays
R['after'] = cpu_load(hal, seg)
"""
    )

    def value(hexs):
        # (a list value: protocol.messages decodes scalar values only; the host's link reads
        # key 1 as it comes, host/doctor_checks.py validates it)
        (f,) = [f for f in frames(hexs) if f.mtype == T_PARAM_VALUE]
        payload = cbor2.loads(f.payload)
        assert payload[0] == 23 and f.seq == 7
        return payload[1]

    assert value(r["first"]) == [0, 0]
    now, peak = value(r["light"])
    assert 38 <= now <= 42 and peak >= now
    assert value(r["saturated"]) == [100, 100]
    now, peak = value(r["after"])
    assert 18 <= now <= 22 and peak == 100
