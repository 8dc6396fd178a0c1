"""Honest state on the MicroPython VM (issue 11, finding 2): a PWM servo driven past its pulse
range saturates; the segment flags CLAMPED (and LIMIT_CLAMPED, servo bit) and STATE reports the
curvature actually achieved by the clipped pulses, not the target."""

from __future__ import annotations

import math

import numpy as np

from protocol import messages as M
from tests.device.conftest import decode

# default geometry: 3 tendons at 50 mm, spool 20 mm, 316 mm; kappa 3 1/m needs a spool angle of
# 3 * 0.316 * 0.05 / 0.02 = 2.37 rad, but the pulses cover only +-0.5 rad (range 1.0 rad)
SYNC = M.encode_sync(1, 1, [(3.0, 0.0)]).hex()


def test_pwm_saturation_is_flagged_and_state_reports_the_achieved_curvature(vm):
    cfg = {
        "servo_driver": "pwm",
        "watchdog_ms": 60000,
        "kappa_rate_max": 100.0,
        "pwm": {"pins": [25, 26, 27], "min_us": 1000, "max_us": 2000, "range": 1.0},
    }
    r = vm(
        f"""
import config, gc, vmfakes
hal = vmfakes.BusHal()
cfg = config.Config({cfg!r})  # before the segment's modules, in main.build's order
gc.collect()
import servos
gc.collect()
from segment import Segment
bus = servos.make('pwm', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
for _ in range(40):
    hal.up.feed(bytes.fromhex('{SYNC}'))
    vmkit.run(hal, seg, 25)
    hal.up.discard()
hal.up.feed(bytes.fromhex('{SYNC}'))
vmkit.run(hal, seg, 120)
R['s'] = [[p.ns for p in hal.pwms], list(bus.pos), seg.status(), vmkit.hexs(hal.up.take())]
"""
    )
    ns, pos, status, out = r["s"]
    assert status & 0x08  # CLAMPED
    assert min(ns) == 1_000_000 or max(ns) == 2_000_000  # a pulse is at its end
    assert all(-5000 <= p <= 5000 for p in pos)  # pos = the angle the pulse asks for
    msgs = decode(out)
    st = [m for m in msgs if m["type"] == "STATE"][-1]
    assert "CLAMPED" in st["status"]
    ev = [m for m in msgs if m["type"] == "EVENT" and m["name"] == "LIMIT_CLAMPED"]
    assert ev and ev[-1]["detail"] & 0x04
    # the achieved curvature, from the output angles (least squares over the three tendons)
    sig = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    a = np.array(st["servo_angles"])  # spool angles (rad), + = wound in
    dl = -a * 0.02
    mat = np.stack([np.cos(sig), np.sin(sig)], axis=1)
    kx, ky = np.linalg.lstsq(mat, -dl / (0.316 * 0.05), rcond=None)[0]
    achieved = math.hypot(kx, ky)
    assert achieved < 2.0  # far from the 3 1/m asked for
    assert abs(st["kappa"] - achieved) <= 2e-3
