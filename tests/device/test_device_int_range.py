"""Small-int discipline of the hot path, checked on CPython with a tracer.

On a 32-bit ESP32, an int outside +-2**30 is a heap object (an allocation the unix port's
heap_lock test cannot see: its small ints have 62 bits). This test runs the MC, the SCs, the
emulated servos and the segment tick under CPython for the extreme configurations config.py
accepts, and fails if any int local of a firmware function, any ``mulq`` partial product, or any
array element reaches 2**30.
"""

from __future__ import annotations

import math
import sys
from array import array
from pathlib import Path

import numpy as np
import pytest

DEVICE = Path(__file__).resolve().parents[2] / "device"
LIMIT = 1 << 30


@pytest.fixture(scope="module")
def dev():
    sys.path.insert(0, str(DEVICE))
    try:
        import config
        import fxp
        import mechanism
        import sc
        import servos
        import servos.emulated  # noqa: F401

        yield {"config": config, "fxp": fxp, "mechanism": mechanism, "sc": sc, "servos": servos}
    finally:
        sys.path.remove(str(DEVICE))


class _Tracer:
    """sys.settrace hook: every int local of a frame in device/ must stay below 2**30."""

    def __init__(self) -> None:
        self.worst = 0
        self.where = ""

    def __call__(self, frame, event, arg):
        if not frame.f_code.co_filename.startswith(str(DEVICE)):
            return None
        return self._local

    def _local(self, frame, event, arg):
        for name, v in frame.f_locals.items():
            if type(v) is int and abs(v) > self.worst:
                self.worst = abs(v)
                self.where = f"{frame.f_code.co_name}:{frame.f_lineno} {name}"
        if event == "return" and type(arg) is int and abs(arg) > self.worst:
            self.worst = abs(arg)
            self.where = f"{frame.f_code.co_name} returns"
        return self._local


def _checked_mulq(orig):
    worst = {"v": 0}

    def mulq(a, c, q):
        assert abs(a) < 1 << 24 and abs(c) < 1 << 21 and 12 <= q <= 29, (a, c, q)
        hi, mid, lo = a >> 16, (a >> 8) & 255, a & 255
        top = abs(hi * c) << max(0, 16 - q)  # the top partial is shifted left when q < 16
        worst["v"] = max(worst["v"], top, abs(mid * c), abs(lo * c) + (1 << (q - 1)))
        return orig(a, c, q)

    return mulq, worst


EXTREMES = [
    {},  # defaults: the paper's segment
    {  # small, very bendy segment with a tiny spool
        "length": 0.05,
        "tendon_radius": 0.01,
        "spool_radius": 0.002,
        "kappa_max": 100.0,
        "kappa_rate_max": 1000.0,
        "servos": [{"min_angle": -50.0, "max_angle": 50.0, "zero_offset": 50.0}] * 3,
    },
    {  # long segment, wide tendons, many tendons, big spool
        "length": 2.0,
        "tendon_radius": 0.04,
        "spool_radius": 0.15,
        "kappa_max": 100.0,
        "kappa_rate_max": 1000.0,
        "tendon_angles": [i * 2 * math.pi / 8 for i in range(8)],
        "servos": [{"min_angle": -50.0, "max_angle": 50.0, "direction": -1}] * 8,
    },
]


@pytest.mark.parametrize("extra", EXTREMES, ids=["default", "tiny-spool", "long-8-tendons"])
def test_hot_path_ints_stay_below_2_pow_30(dev, extra):
    config, fxp, mechanism, scmod, servos = (
        dev["config"],
        dev["fxp"],
        dev["mechanism"],
        dev["sc"],
        dev["servos"],
    )
    cfg = config.Config(dict(extra))
    mc = mechanism.Mechanism(cfg, 5)
    checked, worst = _checked_mulq(fxp.mulq)
    orig = mechanism.mulq
    mechanism.mulq = checked
    tracer = _Tracer()
    rng = np.random.default_rng(5)
    scs = scmod.SimpleControllers(cfg.n, "p_slew", 1.0, 100.0, 5)

    class _Hal:
        pass

    bus = servos.make("emulated", cfg, _Hal())
    sys.settrace(tracer)
    try:
        for _ in range(200):
            k = int(rng.choice([rng.integers(-(2**29), 2**29), rng.integers(-(10**6), 10**6)]))
            p = int(rng.integers(-(2**29), 2**29))
            mc.set_target(k, p)
            for _ in range(3):
                mc.update()
            scs.step(mc.servo_target)
            bus.command(scs.cmd, 0)
            bus.poll(int(rng.integers(0, 2000)))
            mc.measure(bus.pos)
            # servo positions anywhere in the allowed travel
            pos = [
                int(rng.integers(cfg.zero[i] - 500000, cfg.zero[i] + 500000)) for i in range(cfg.n)
            ]
            mc.measure(array("i", pos))
        # the wire's extremes (a CBOR int within +-2**30), with and without the rate check
        for k, p in ((-(2**30 - 1), 2**30 - 1), (2**30 - 1, -(2**30 - 1)), (-(2**30 - 1), 0)):
            mc.set_target(k, p)
            mc.set_target(k, p, 10)
            mc.update()
    finally:
        sys.settrace(None)
        mechanism.mulq = orig
    assert worst["v"] < LIMIT, worst
    assert tracer.worst < LIMIT, (tracer.worst, tracer.where)
    assert tracer.worst > 1 << 20  # the tracer did see the big wire inputs
    assert worst["v"] > 1 << 20
    for arr in (mc.servo_target, mc.tendon, mc.tendon_cmd, mc.joint, scs.cmd):
        assert max(abs(v) for v in arr) < LIMIT
