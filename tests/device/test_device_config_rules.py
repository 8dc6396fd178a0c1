"""One rule for what a segment can be (issue 11, finding 4): what `ucr check` accepts the firmware
runs exactly (short segments included, curvature within 1e-3 1/m up to 100 1/m); what the
firmware cannot run, `ucr check` and `ucr flash` refuse with ``path:line: message``; a segment
never runs defaults in place of a configuration it was given; kappa_max <= 0 or NaN is refused
everywhere."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from protocol import messages as M
from tests.cli_run import run_ucr
from tests.device.conftest import decode
from tools import mpvm

REPO = mpvm.REPO
# a short segment: length * tendon radius = 0.05 * 0.008 = 4e-4 m^2 (the old limit: ~4.2e-4)
SHORT = {"name": "short", "length": 0.05, "tendon_radius": 0.008, "spool_radius": 0.01}
SHORT.update({"kappa_max": 20.0, "kappa_rate_max": 200.0, "watchdog_ms": 60000})


def test_short_segment_runs_its_own_geometry_exactly(vm):
    sync = M.encode_sync(1, 1, [(12.5, 0.7)]).hex()
    disc = M.encode_discover(2).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({SHORT!r})
for _ in range(40):
    hal.up.feed(bytes.fromhex('{sync}'))
    vmkit.run(hal, seg, 10)
    hal.up.discard()
hal.up.feed(bytes.fromhex('{disc}'))
vmkit.run(hal, seg, 10)
R['s'] = [seg.cfg.error, seg.status(), seg.mc.kappa, seg.mc.phi, list(seg.mc.tendon),
          vmkit.hexs(hal.up.take()), seg.mc.cx, seg.mc.cy]
"""
    )
    error, status, kappa, phi, tendons, out, cx, cy = r["s"]
    assert error is None and status & 0x21 == 0  # configured, not holding
    # commanded exactly (1e-3 1/m); measured within the servo angle quantum (1e-4 rad of spool
    # is 1e-4 * 0.01 / 4e-4 = 2.5e-3 1/m on this short segment) and the servos' settling
    assert abs(cx - 125000 * math.cos(0.7)) <= 10 and abs(cy - 125000 * math.sin(0.7)) <= 10
    assert abs(kappa - 125000) <= 40 and abs(phi - 7000) <= 3
    sig = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    want = 0.05 * (1 - 0.008 * 12.5 * np.cos(sig - 0.7))
    assert np.abs(np.array(tendons) * 1e-6 - want).max() <= 3e-6
    desc = [m for m in decode(out) if m["type"] == "DESCRIPTOR"][0]
    assert desc["length"] == 0.05 and desc["name"] == "short" and desc["config_error"] == ""


def test_curvature_resolution_is_within_1e_3_per_m_up_to_100_per_m(vm):
    """A bendy segment (kappa_max 100 1/m): the commanded curvature vector and the curvature
    measured back from (quantised) servo angles both stay within 1e-3 1/m of exact."""
    cfg = {"length": 0.1, "tendon_radius": 0.005, "spool_radius": 0.01, "kappa_max": 100.0}
    cfg["servos"] = [{"min_angle": -6.0, "max_angle": 6.0}] * 3
    rng = np.random.default_rng(11)
    targets = [
        [int(k), int(p)]
        for k, p in zip(rng.integers(1, 1000000, 60), rng.integers(-31415, 31416, 60), strict=True)
    ]
    targets += [[999999, 0], [999999, 31416], [500000, -15708]]
    r = vm(
        f"""
import config, mechanism
cfg = config.Config({cfg!r})
mc = mechanism.Mechanism(cfg, 5)
out = []
for k, p in {targets!r}:
    mc.set_target(k, p)
    mc.cx = mc.tx
    mc.cy = mc.ty
    mc._servo_targets()
    mc.measure(mc.servo_target)
    out.append([mc.tx, mc.ty, list(mc.servo_target), mc.mx, mc.my, mc.kappa])
R['o'] = out
""",
        heap="1m",  # the sample data, not the firmware, needs it
    )
    sig = np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    mat = np.stack([np.cos(sig), np.sin(sig)], axis=1)
    worst_cmd = worst_meas = 0.0
    for (k, p), (tx, ty, servo, mx, my, kappa) in zip(targets, r["o"], strict=True):
        kx, ky = k * math.cos(p * 1e-4), k * math.sin(p * 1e-4)  # 1e-4 1/m
        worst_cmd = max(worst_cmd, abs(tx - kx), abs(ty - ky), abs(math.hypot(tx, ty) - k))
        # exact least squares from the same quantised servo angles (what measure() sees)
        dl = -np.array(servo) * 1e-4 * 0.01
        ex, ey = np.linalg.lstsq(mat, -dl / (0.1 * 0.005), rcond=None)[0] * 1e4
        worst_meas = max(worst_meas, abs(mx - ex), abs(my - ey), abs(kappa - math.hypot(ex, ey)))
    assert worst_cmd <= 10, worst_cmd  # 1e-3 1/m
    assert worst_meas <= 10, worst_meas


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan")])
def test_invalid_kappa_max_is_refused_by_the_config_and_by_param_set(vm, value):
    wire = M.encode_param_set(3, 0, 1, 0.5 if value != value else value)
    if value != value:  # the host encoder refuses NaN: build the frame by hand
        from protocol.frame import encode_frame

        wire = encode_frame(0, 0, 0x05, 3, b"\xa2\x00\x01\x01\xf9\x7e\x00")
    r = vm(
        f"""
import config
try:
    config.Config({{'kappa_max': float('{value}')}})
    R['cfg'] = None
except ValueError as e:
    R['cfg'] = str(e)
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
hal.up.feed(bytes.fromhex('{wire.hex()}'))
vmkit.run(hal, seg, 10)
R['k'] = [seg.kappa_max_si, vmkit.hexs(hal.up.take())]
"""
    )
    assert r["cfg"] and "kappa_max" in r["cfg"]
    kmax, out = r["k"]
    errs = [m for m in decode(out) if m["type"] == "ERROR"]
    assert errs and errs[0]["name"] == "BAD_VALUE" and "kappa_max" in errs[0]["text"]
    assert kmax > 3.0  # unchanged


def test_a_kappa_limit_below_one_fixed_point_unit_is_refused_everywhere(vm):
    """kappa_max 4e-5 1/m (and a PARAM_SET kappa_max / kappa_rate_max of 4e-5) rounded to 0 units
    of 1e-4 1/m on the segment: accepted, then run as 0. The config, PARAM_SET and ``ucr check``
    (tests/ucrdf_format/test_semantic_errors.py) refuse it."""
    set_k = M.encode_param_set(3, 0, 1, 4e-5).hex()
    set_r = M.encode_param_set(4, 0, 2, 4e-5).hex()
    r = vm(
        f"""
import config
try:
    config.Config({{'kappa_max': 4e-5}})
    R['cfg'] = None
except ValueError as e:
    R['cfg'] = str(e)
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
before = [seg.kappa_max_si, seg.rate_max_si, seg.mc.kappa_max, seg.mc.step_whole, seg.mc.step_frac]
hal.up.feed(bytes.fromhex('{set_k}'))
vmkit.run(hal, seg, 10)
hal.up.feed(bytes.fromhex('{set_r}'))
vmkit.run(hal, seg, 10)
after = [seg.kappa_max_si, seg.rate_max_si, seg.mc.kappa_max, seg.mc.step_whole, seg.mc.step_frac]
R['k'] = [before, after, vmkit.hexs(hal.up.take())]
"""
    )
    assert r["cfg"] and "kappa_max" in r["cfg"] and "rounds to 0" in r["cfg"]
    before, after, out = r["k"]
    errs = [m for m in decode(out) if m["type"] == "ERROR"]
    assert [e["name"] for e in errs] == ["BAD_VALUE", "BAD_VALUE"], errs
    assert "kappa_max" in errs[0]["text"] and "kappa_rate_max" in errs[1]["text"]
    assert after == before


def test_a_rejected_config_never_runs_defaults_and_says_why(vm, tmp_path):
    bad = dict(SHORT, kappa_max=150.0)  # beyond the firmware's 100 1/m
    sync = M.encode_sync(1, 1, [(1.0, 0.0)], resume=True).hex()
    disc = M.encode_discover(2).hex()
    (tmp_path / "config.json").write_text(json.dumps(bad))
    r = vm(
        f"""
import config, servos
from segment import Segment
cfg = config.load('{tmp_path / "config.json"}')
hal = vmkit.LoopHal()
seg = Segment(hal, cfg, servos.make('emulated', cfg, hal), 5)
pos = list(seg.bus.true_pos)
for _ in range(20):
    hal.up.feed(bytes.fromhex('{sync}'))
    vmkit.run(hal, seg, 10)
    hal.up.discard()
hal.up.feed(bytes.fromhex('{disc}'))
vmkit.run(hal, seg, 10)
R['s'] = [cfg.error, pos, list(seg.bus.true_pos), seg.status(), vmkit.hexs(hal.up.take())]
"""
    )
    error, pos, later, status, out = r["s"]
    assert error and "kappa_max" in error
    assert pos == later and status & 0x21 == 0x21  # HOLD + UNCONFIGURED, nothing moved
    desc = [m for m in decode(out) if m["type"] == "DESCRIPTOR"][0]
    assert desc["config_error"].startswith("config.json rejected: kappa_max")


def _robot(tmp_path: Path, **edits: str) -> Path:
    text = (REPO / "robots" / "softrobot3.ucrdf").read_text()
    for old, new in edits.items():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "robot.ucrdf"
    path.write_text(text)
    return path


def _line_of(path: Path, needle: str) -> int:
    for i, line in enumerate(path.read_text().splitlines(), 1):
        if needle in line:
            return i
    raise AssertionError(needle)


def test_ucr_check_and_flash_refuse_what_the_firmware_cannot_run_with_path_and_line(tmp_path):
    # servo 0 of segment_1 may turn 60 rad: beyond the firmware's +-50 rad integer range
    path = _robot(
        tmp_path,
        **{
            'id="1" zero_offset="0.0" direction="1" min_angle="-3.141592653589793"': (
                'id="1" zero_offset="0.0" direction="1" min_angle="-60.0"'
            )
        },
    )
    line = _line_of(path, 'min_angle="-60.0"')
    res = run_ucr("check", str(path))
    assert res.returncode != 0
    assert f"{path}:{line}: " in res.stdout + res.stderr
    assert "firmware would refuse" in res.stdout + res.stderr and "Traceback" not in res.stderr
    # ucr flash generates the same configuration and refuses it before touching the board
    res = run_ucr(
        "flash", "--port", "/dev/null-no-such-port", "--robot", str(path), "--segment", "segment_1"
    )
    out = res.stdout + res.stderr
    assert res.returncode != 0 and "firmware would refuse" in out and "Traceback" not in out
    assert f"{path}:" in out


def test_rules_the_config_and_param_set_share_and_what_state_can_report(vm):
    """Review 2026-11-26, three holes in "one rule for what a segment can be":
    - PARAM_SET watchdog_ms took 10 ms on a 50 ms tick, which config.json refuses (< two ticks);
    - servo_speed 0.01 rad/s is below one 1e-4 rad step per tick: the SC moved at one step
      anyway (2x the configured speed at 5 ms, 10x at 1 ms);
    - a 15 mm segment with a 1 mm tendon radius and +-pi servos could measure 5000 1/m, which
      STATE's int24 (+-838 1/m) wrapped, sign and all (1111 1/m went out as -566)."""
    pset = M.encode_param_set(3, 0, 0, 10).hex()
    r = vm(
        f"""
import config, mechanism
out = []
for c in ({{'servo_speed': 0.01}}, {{'length': 0.015, 'tendon_radius': 0.001, 'spool_radius': 0.01,
           'kappa_max': 50.0}}):
    try:
        mechanism.Mechanism(config.Config(c), 5)  # what config.load checks
        out.append(None)
    except ValueError as e:
        out.append(str(e))
R['cfg'] = out
hal, seg = vmkit.make({{'tick_ms': 50, 'watchdog_ms': 200}}, tick_ms=50)
hal.up.feed(bytes.fromhex('{pset}'))
seg.poll()
R['wd'] = [seg.watchdog_ms, vmkit.hexs(hal.up.take())]
"""
    )
    speed, geometry = r["cfg"]
    assert speed and "servo_speed" in speed and "one step" in speed, speed
    assert geometry and "beyond what STATE reports" in geometry, geometry
    wd, out = r["wd"]
    errs = [m for m in decode(out) if m["type"] == "ERROR"]
    assert wd == 200 and errs and "two ticks" in errs[0]["text"], errs
