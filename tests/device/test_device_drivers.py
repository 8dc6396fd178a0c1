"""ESP32 servo drivers on the VM against test doubles: the Feetech STS/SCS packet format (sync
write, read, checksums, echo, error byte, silence) and the PWM pulse mapping and boot hold."""

from __future__ import annotations

import math

import pytest

from protocol import messages as M

SYNC = M.encode_sync(1, 1, [(2.0, 0.7)]).hex()


def _run_bus(vm, driver, big, centre, steps_per_rev):
    cfg = {
        "servo_driver": driver,
        "watchdog_ms": 60000,
        "servos": [{"id": 11}, {"id": 12}, {"id": 13}],
    }
    return vm(
        f"""
import gc, config
cfg = config.Config({cfg!r})  # as main.build: the board rules come and go before the rest loads
gc.collect()
import servos, vmfakes
from segment import Segment
fake = vmfakes.FakeFeetech([11, 12, 13], big={big}, centre={centre})
hal = vmfakes.BusHal(fake)
bus = servos.make('{driver}', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
vmkit.run(hal, seg, 100)
R['boot'] = [fake.syncs, fake.reads, dict(fake.goal)]
hal.up.feed(bytes.fromhex('{SYNC}'))
for _ in range(40):
    hal.up.feed(bytes.fromhex('{SYNC}'))
    vmkit.run(hal, seg, 25)
    hal.up.discard()
R['moved'] = [fake.syncs, fake.reads, fake.bad, dict(fake.goal), seg.mc.kappa, seg.mc.phi,
              list(seg.mc.servo_target), list(bus.voltage), list(bus.temperature), seg.status(),
              list(bus.load)]
fake.err[12] = 0x20   # overload on the second servo
vmkit.run(hal, seg, 50)
R['overload'] = [seg.status(), list(bus.fault)]
fake.err[12] = 0
fake.silent.add(13)   # third servo stops answering
vmkit.run(hal, seg, 100)
R['silent'] = [seg.status(), list(bus.fault), vmkit.hexs(hal.up.take())]
"""
    )


def _check_bus(r, centre, steps_per_rev):
    syncs, reads, goal = r["boot"]
    assert syncs == 0 and reads >= 15  # boot hold: positions read, nothing written
    assert set(goal.values()) == {centre}
    syncs, reads, bad, goal, kappa, phi, targets, volt, temp, status, load = r["moved"]
    assert bad == 0 and syncs > 100 and reads > 100
    for sid, raw in zip(("11", "12", "13"), targets, strict=True):
        want = centre + raw * 1e-4 * steps_per_rev / (2 * math.pi)
        assert abs(goal[sid] - want) <= 1.0
    # measured from the servos' replies, quantised to one encoder step
    step_rad = 2 * math.pi / steps_per_rev
    tol = 2 * step_rad * 0.02 / (0.316 * 0.05) * 1e4  # two steps of spool -> 1e-4 1/m
    assert abs(kappa - 20000) <= tol and abs(phi - 7000) <= 40
    assert volt == [121] * 3 and temp == [35] * 3 and load == [100] * 3  # 12.1 V, 35 C, 10 %
    assert status & 0x05 == 0
    status, faults = r["overload"]
    assert faults[1] == 3 and status & 0x05 == 0x05
    status, faults, up = r["silent"]
    assert faults[2] == 1


def test_feetech_sts_packets_positions_and_faults(vm):
    r = _run_bus(vm, "feetech_sts", False, 2048, 4096)
    _check_bus(r, 2048, 4096)


def test_feetech_scs_uses_big_endian_and_its_own_resolution(vm):
    r = _run_bus(vm, "feetech_scs", True, 512, 1228.8)
    _check_bus(r, 512, 1228.8)


def test_pwm_outputs_nothing_in_the_boot_hold_then_maps_angles_to_pulses(vm):
    cfg = {
        "servo_driver": "pwm",
        "watchdog_ms": 60000,
        # GPIO4-6 are free on an ESP32-S3 (GPIO6 is the SPI flash's on a classic ESP32)
        "board": "esp32s3",
        "pwm": {"pins": [4, 5, 6], "min_us": 1000, "max_us": 2000, "range": 1.5},
        "servos": [{"zero_offset": 0.2}, {"direction": -1}, {"min_angle": -0.3, "max_angle": 0.3}],
    }
    r = vm(
        f"""
import gc, config
cfg = config.Config({cfg!r})  # as main.build: the board rules come and go before the rest loads
gc.collect()
import servos, vmfakes
from segment import Segment
hal = vmfakes.BusHal()
bus = servos.make('pwm', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
vmkit.run(hal, seg, 100)
R['boot'] = len(hal.pwms)
for _ in range(40):
    hal.up.feed(bytes.fromhex('{SYNC}'))
    vmkit.run(hal, seg, 25)
    hal.up.discard()
R['run'] = [[p.pin for p in hal.pwms], [p.freq for p in hal.pwms], [p.ns for p in hal.pwms],
            list(seg.mc.servo_target), seg.status()]
"""
    )
    assert r["boot"] == 0  # no PWM output exists before the first SYNC
    pins, freqs, ns, targets, status = r["run"]
    assert pins == [4, 5, 6] and freqs == [50, 50, 50]
    for pulse, raw in zip(ns, targets, strict=True):
        want = 1_500_000 + raw * 1e-4 * (1_000_000 / 1.5)
        want = min(max(want, 1_000_000), 2_000_000)
        assert abs(pulse - want) <= 20  # slope in 1/256 ns; LEDC resolution is ~300 ns
    assert status & 0x04 == 0  # open loop: no faults observable


def test_pwm_runs_the_pulse_range_the_robot_file_declares(vm):
    """robots/hybrid_arm.ucrdf's wrist needs ±2.945 rad of 360° servos (<pwm_pulse range=2π>):
    the generated config.json carries the pulse range and the firmware reaches the full bend
    instead of saturating at the default ±π/2."""
    from tools.mpvm import REPO
    from tools.segment_config import config_for
    from ucrdf.parser import load

    cfg = config_for(load(REPO / "robots" / "hybrid_arm.ucrdf"), "wrist")
    assert cfg["pwm"]["range"] == math.tau and cfg["pwm"]["min_us"] == 500.0
    cfg["watchdog_ms"] = 60000
    sync = M.encode_sync(1, 1, [(cfg["kappa_max"], 0.0)]).hex()
    r = vm(
        f"""
import gc, config
cfg = config.Config({cfg!r})
gc.collect()
import servos, vmfakes
from segment import Segment
hal = vmfakes.BusHal()
bus = servos.make('pwm', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
vmkit.run(hal, seg, 20)
for _ in range(60):
    hal.up.feed(bytes.fromhex('{sync}'))
    vmkit.run(hal, seg, 25)
    hal.up.discard()
R['run'] = [[p.ns for p in hal.pwms], list(seg.mc.servo_target), bus.saturated, seg.mc.kappa]
"""
    )
    ns, targets, saturated, kappa = r["run"]
    need = cfg["length"] * cfg["tendon_radius"] * cfg["kappa_max"] / cfg["spool_radius"]
    assert abs(targets[0] * 1e-4 - need) < 2e-3  # tendon 0 winds in the full 2.945 rad
    assert not saturated
    assert abs(kappa * 1e-4 - cfg["kappa_max"]) < 0.05  # the whole bend, not a clamped one
    want = 1_500_000 + targets[0] * 1e-4 * (2_000_000 / math.tau)
    assert abs(ns[0] - want) <= 100 and ns[0] < 2_490_000  # inside the pulse range (1/256 ns slope)


def test_the_firmware_pwm_defaults_are_the_u_c_rdf_defaults():
    """device/servos/pwm.py's defaults = ucrdf.model's (what `ucr check` judges against)."""
    import ast

    from tools.mpvm import REPO
    from ucrdf.model import PwmPulse

    tree = ast.parse((REPO / "device" / "servos" / "pwm.py").read_text())
    default = next(
        ast.literal_eval(n.value)
        for n in tree.body
        if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "_DEFAULT"
    )
    p = PwmPulse()
    assert (default["min_us"], default["max_us"]) == (p.min_us, p.max_us)
    assert default["range"] == pytest.approx(p.range, abs=1e-8)
