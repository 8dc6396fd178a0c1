"""Fixed-point maths and the mechanism controller's mapping, checked on the MicroPython VM
against the float formulas evaluated here with numpy.

Stated accuracies (docs/firmware.md): sin/cos within 1e-4; atan2 within 1.2e-4 rad; tendon
lengths within 10 um of l (1 - d (kx cos s + ky sin s)); servo angles within 1e-3 rad;
inverse (least squares) curvature vector within 1e-3 1/m.
"""

from __future__ import annotations

import json
import math

import numpy as np

SKEW = {
    "name": "skew",
    "length": 0.2,
    "tendon_angles": [0.1, 1.7, 3.3, 4.6],
    "tendon_radius": 0.03,
    "spool_radius": 0.012,
    "kappa_max": 8.0,
    "kappa_rate_max": 50.0,
    "servos": [
        {"id": 1, "zero_offset": 0.1, "direction": 1, "min_angle": -20.0, "max_angle": 20.0},
        {"id": 2, "zero_offset": -0.2, "direction": -1, "min_angle": -20.0, "max_angle": 20.0},
        {"id": 3, "zero_offset": 0.3, "direction": 1, "min_angle": -20.0, "max_angle": 20.0},
        {"id": 4, "zero_offset": 0.0, "direction": -1, "min_angle": -20.0, "max_angle": 20.0},
    ],
}


def test_trig_tables_and_atan2_meet_the_stated_accuracy(vm):
    rng = np.random.default_rng(1)
    angles = [int(a) for a in rng.integers(-200000, 200000, 3000)] + list(range(-31420, 31420, 97))
    pts = [[int(x), int(y)] for x, y in rng.integers(-(2**22), 2**22, (2000, 2))]
    pts += [[int(x), int(y)] for x, y in rng.integers(-50, 50, (500, 2)) if x or y]
    r = vm(
        f"""
import fxp
A = json.loads('{json.dumps(angles)}')
P = json.loads('{json.dumps(pts)}')
R['s'] = [fxp.sin_q14(a) for a in A]
R['c'] = [fxp.cos_q14(a) for a in A]
R['t'] = [fxp.atan2_e4(y, x) for x, y in P]
R['w'] = [fxp.wrap_angle(a) for a in (0, 31416, 31417, -31416, 62832 * 3 + 5)]
""",
        heap="4m",
    )
    a = np.array(angles) * 1e-4
    assert np.abs(np.array(r["s"]) / 16384 - np.sin(a)).max() <= 1e-4
    assert np.abs(np.array(r["c"]) / 16384 - np.cos(a)).max() <= 1e-4
    p = np.array(pts, dtype=float)
    err = np.array(r["t"]) * 1e-4 - np.arctan2(p[:, 1], p[:, 0])
    err = (err + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(err).max() <= 1.2e-4
    assert all(-31416 < v <= 31416 for v in r["t"])
    assert r["w"] == [0, 31416, -31415, 31416, 5]


def test_machine_code_fixed_point_gives_the_plain_versions_integers(vm):
    """device/fxp_fast.py (viper) replaces fxp's mulq/sin/cos/atan2 where the VM compiles it: the
    same integers as the plain code for every input in the documented ranges, edges included
    (random inputs drawn on the VM, seeded)."""
    r = vm(
        """
import fxp, random
random.seed(7)
pm, ps, pc, pa = fxp._plain
R['fast'] = fxp.mulq is not pm and fxp.atan2_e4 is not pa
M24 = (1 << 24) - 1
M21 = (1 << 21) - 1
M29 = (1 << 29) - 1
mul = [[random.randint(-M24, M24), random.randint(-M21, M21), random.randint(12, 29)]
       for _ in range(3000)]
mul += [[a, c, q] for a in (-M24, -1, 0, 1, M24) for c in (-M21, -1, 1, M21)
        for q in (12, 16, 20, 29)]
ang = [random.randint(-M29 - 1, M29 + 1) for _ in range(2000)]
ang += [k * 15708 + d for k in range(-5, 6) for d in (-1, 0, 1)] + [62832, -62832]
pts = [[random.randint(-M29, M29) >> random.randint(0, 28),
        random.randint(-M29, M29) >> random.randint(0, 28)] for _ in range(2000)]
pts += [[x, y] for x in (-M29, -1, 0, 1, M29) for y in (-M29, -1, 0, 1, M29)]
bad = []
for a, c, q in mul:
    if fxp.mulq(a, c, q) != pm(a, c, q):
        bad.append(['mulq', a, c, q])
for a in ang:
    if fxp.sin_q20(a) != ps(a) or fxp.cos_q20(a) != pc(a):
        bad.append(['sin/cos', a])
for x, y in pts:
    if fxp.atan2_e4(y, x) != pa(y, x):
        bad.append(['atan2', y, x])
R['n'] = len(mul) + len(ang) + len(pts)
R['bad'] = bad[:10]
""",
        heap="4m",
    )
    assert r["fast"], "the VM has a native emitter: fxp must use device/fxp_fast.py"
    assert r["n"] > 7000
    assert r["bad"] == []


def _forward_vm(vm, cfg, setpoints):
    return vm(
        f"""
import config, mechanism
cfg = config.Config(json.loads('{json.dumps(cfg)}'))
m = mechanism.Mechanism(cfg, 5)
S = json.loads('{json.dumps(setpoints)}')
R['tendon'] = []
R['servo'] = []
R['flags'] = []
R['k'] = []
for k, p in S:
    f = m.set_target(k, p)
    m.cx = m.tx
    m.cy = m.ty
    f |= m._servo_targets()
    R['flags'].append(f)
    R['tendon'].append(list(m.tendon_cmd))
    R['servo'].append(list(m.servo_target))
    m.measure(m.servo_target)
    R['k'].append([m.mx, m.my, m.kappa, m.phi])
""",
        heap="4m",
    )


def _expected(cfg, kappa, phi):
    sig = np.array(cfg["tendon_angles"])
    kx, ky = kappa * math.cos(phi), kappa * math.sin(phi)
    lengths = cfg["length"] * (1 - cfg["tendon_radius"] * (kx * np.cos(sig) + ky * np.sin(sig)))
    spool = -(lengths - cfg["length"]) / cfg["spool_radius"]  # + = tendon wound in
    servos = cfg["servos"]
    raw = np.array(
        [s["zero_offset"] + s["direction"] * a for s, a in zip(servos, spool, strict=True)]
    )
    return lengths, raw, kx, ky


def test_forward_mapping_matches_the_float_formula_for_skewed_tendons(vm):
    rng = np.random.default_rng(2)
    sps = [(float(rng.uniform(0, 8.0)), float(rng.uniform(-math.pi, math.pi))) for _ in range(300)]
    wire = [[round(k * 1e4), round(p * 1e4)] for k, p in sps]
    r = _forward_vm(vm, SKEW, wire)
    for (kw, pw), lt, st, fl, meas in zip(
        wire, r["tendon"], r["servo"], r["flags"], r["k"], strict=True
    ):
        lengths, raw, kx, ky = _expected(SKEW, kw * 1e-4, pw * 1e-4)
        assert np.abs(np.array(lt) * 1e-6 - lengths).max() <= 10e-6
        assert np.abs(np.array(st) * 1e-4 - raw).max() <= 1e-3
        assert fl == 0
        # back through the least-squares inverse: the same curvature vector
        assert math.hypot(meas[0] * 1e-4 - kx, meas[1] * 1e-4 - ky) <= 1e-3
        assert abs(meas[2] * 1e-4 - kw * 1e-4) <= 1e-3


def test_inverse_is_the_least_squares_solution_for_inconsistent_tendons(vm):
    """Servo positions that no curvature explains exactly -> numpy's lstsq curvature."""
    rng = np.random.default_rng(3)
    sig = np.array(SKEW["tendon_angles"])
    ld = SKEW["length"] * SKEW["tendon_radius"]
    cases, want = [], []
    for _ in range(200):
        k, p = rng.uniform(0.05, 8.0), rng.uniform(-math.pi, math.pi)
        _, raw, _, _ = _expected(SKEW, k, p)
        raw = raw + rng.normal(0, 0.02, raw.shape)  # 0.02 rad of disagreement
        pos = [round(v * 1e4) for v in raw]
        cases.append(pos)
        spool = np.array(
            [
                s["direction"] * (v * 1e-4 - s["zero_offset"])
                for s, v in zip(SKEW["servos"], pos, strict=True)
            ]
        )
        dl = -spool * SKEW["spool_radius"]
        amat = np.stack([np.cos(sig), np.sin(sig)], axis=1)
        sol, *_ = np.linalg.lstsq(amat, -dl / ld, rcond=None)
        want.append(sol)
    r = vm(
        f"""
import config, mechanism
from array import array
m = mechanism.Mechanism(config.Config(json.loads('{json.dumps(SKEW)}')), 5)
R['m'] = []
for pos in json.loads('{json.dumps(cases)}'):
    m.measure(array('i', pos))
    R['m'].append([m.mx, m.my, m.kappa, m.phi, list(m.tendon)])
""",
        heap="4m",
    )
    for (mx, my, kappa, phi, _), (kx, ky) in zip(r["m"], want, strict=True):
        assert math.hypot(mx * 1e-4 - kx, my * 1e-4 - ky) <= 1e-3
        assert abs(kappa * 1e-4 - math.hypot(kx, ky)) <= 1e-3
        if math.hypot(kx, ky) > 0.1:
            d = (phi * 1e-4 - math.atan2(ky, kx) + math.pi) % (2 * math.pi) - math.pi
            assert abs(d) <= 1e-3 / math.hypot(kx, ky) + 2e-4


def test_phi_is_held_when_the_measured_curvature_is_about_zero(vm):
    r = vm(
        """
import config, mechanism
from array import array
m = mechanism.Mechanism(config.Config({}), 5)
m.set_target(20000, 12000)   # 2 1/m at 1.2 rad
m.cx = m.tx
m.cy = m.ty
m._servo_targets()
m.measure(m.servo_target)
R['bent'] = [m.kappa, m.phi]
m.set_target(0, -25000)      # straight: phi of the setpoint is meaningless
m.cx = m.tx
m.cy = m.ty
m._servo_targets()
m.measure(m.servo_target)
R['straight'] = [m.kappa, m.phi, m.mx, m.my]
"""
    )
    assert abs(r["bent"][0] - 20000) <= 10 and abs(r["bent"][1] - 12000) <= 10
    kappa, phi, mx, my = r["straight"]
    assert kappa == 0 and mx == 0 and my == 0
    assert phi == r["bent"][1]  # held, not jumped to 0 or to the setpoint's phi


def test_kappa_and_servo_range_clamps_raise_their_flags(vm):
    r = _forward_vm(vm, SKEW, [[90000, 5000], [-30000, 0], [79000, 0]])
    assert r["flags"] == [1, 0, 0]  # 9 1/m > kappa_max 8: bit0; the others are within limits
    assert abs(r["k"][0][2] - 80000) <= 10  # clamped to exactly kappa_max, plane kept
    assert abs(r["k"][0][3] - 5000) <= 10
    # negative kappa is kappa > 0 in the opposite plane
    assert abs(r["k"][1][2] - 30000) <= 10 and abs(abs(r["k"][1][3]) - 31416) <= 10
    narrow = dict(SKEW)
    narrow["servos"] = [dict(s, min_angle=-0.5, max_angle=0.5) for s in SKEW["servos"]]
    r = _forward_vm(vm, narrow, [[30000, 0], [2000, 0]])
    assert r["flags"] == [4, 0]  # 3 1/m needs more than 0.5 rad of servo travel: bit2
    for servo in r["servo"]:
        for s, v in zip(narrow["servos"], servo, strict=True):
            rel = v * 1e-4 - s["zero_offset"]
            assert -0.5 - 1e-4 <= rel <= 0.5 + 1e-4


def test_slew_limit_moves_the_curvature_vector_by_at_most_rate_times_dt(vm):
    """A 180-degree flip of phi goes through straight (vector slew), never around the circle."""
    r = vm(
        """
import config, mechanism
m = mechanism.Mechanism(config.Config({'kappa_rate_max': 10.0}), 5)
m.set_target(30000, 0)
m.cx = m.tx
m.cy = m.ty
m.set_target(30000, 31416)   # same kappa, opposite plane
R['path'] = []
R['flags'] = []
for _ in range(160):
    R['flags'].append(m.update())
    R['path'].append([m.cx, m.cy])
R['step'] = m.step
""",
        heap="1m",  # 160 recorded points (test data) beside the compiled firmware
    )
    assert r["step"] == 500  # 10 1/m/s * 5 ms = 0.05 1/m = 500 units
    path = np.array([[30000, 0]] + r["path"], dtype=float)
    steps = np.hypot(*np.diff(path, axis=0).T)
    assert steps.max() <= 500 + 2
    assert np.abs(path[:, 1]).max() <= 2  # straight line through kappa = 0, no whirl
    assert tuple(path[-1]) == (-30000, 0)  # arrives exactly
    assert r["flags"][0] == 2 and r["flags"][-1] == 0  # bit1 while rate-limited only
    n_limited = sum(1 for f in r["flags"] if f == 2)
    assert 119 <= n_limited <= 120  # 6 1/m at 0.05 1/m per cycle


def _stream(vm, fraction):
    """Setpoints every 10 ms moving kx at ``fraction`` of kappa_rate_max (10 1/m/s), with the
    200 Hz limiter ticking twice per setpoint; returns the flags of set_target and update."""
    return vm(
        """
import config, mechanism
m = mechanism.Mechanism(config.Config({'kappa_rate_max': 10.0}), 5)
m.set_target(0, 0, 10)
R['sp'] = []
R['up'] = []
R['lag'] = 0
k = 0
for i in range(15):   # 15 * 2000 units stays below kappa_max (33100)
    k += STEP   # 10 1/m/s * 10 ms = 0.1 1/m = 1000 units per setpoint at 100 %
    R['sp'].append(m.set_target(k, 0, 10))
    R['up'].append(m.update())
    R['up'].append(m.update())
    R['lag'] = max(R['lag'], m.tx - m.cx)
R['final'] = [m.cx, m.tx]
""".replace("STEP", str(round(fraction * 1000)))
    )


def test_setpoints_streamed_within_the_rate_are_never_reported_as_rate_clamped(vm):
    """A host stepping at 100 Hz at 90 % of kappa_rate_max: each step needs two 200 Hz ticks of
    the limiter, but the request is within the rate, so nothing is flagged and nothing lags."""
    r = _stream(vm, 0.9)
    assert not any(f & 2 for f in r["sp"] + r["up"])
    assert r["lag"] == 0 and r["final"][0] == r["final"][1]


def test_setpoints_streamed_faster_than_the_rate_are_flagged_while_the_limiter_catches_up(vm):
    """At 200 % of the rate every setpoint is flagged and the motion is held to the rate."""
    r = _stream(vm, 2.0)
    assert all(f & 2 for f in r["sp"])
    assert all(f & 2 for f in r["up"])
    assert r["final"][0] == 15 * 1000  # 30 ticks * 500 units: exactly the rate, not more
