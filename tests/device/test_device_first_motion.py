"""First motion on the MicroPython VM (issue 11, finding 1), with servos that power up far from
zero: a segment commands no servo before it knows where every one is (bus servos: a present
position read from each; PWM: the configured rest pose inside its range), then moves from there
only under the slew limit and never outside [min, max], whatever the first SYNC asks."""

from __future__ import annotations

import math

import pytest

from protocol import messages as M
from tests.device.conftest import decode

# asks for the far end of everything at once
GREEDY = M.encode_sync(1, 1, [(50.0, 2.5)]).hex()
GREEDY_RESUME = M.encode_sync(2, 2, [(50.0, 2.5)], resume=True).hex()
STRAIGHT = M.encode_sync(1, 1, [(0.0, 0.0)]).hex()
STS_STEPS_PER_RAD = 4096 / (2 * math.pi)
STEP_LIMIT = 6.0 * 0.005  # default servo_speed (rad/s) * tick (s): largest command change


def test_feetech_commands_nothing_until_every_position_is_read_then_slews_from_there(vm):
    """Servo 13 answers only after 300 ms; the servos sit 0.9/-0.6/0.4 rad from their zero."""
    cfg = {
        "servo_driver": "feetech_sts",
        "watchdog_ms": 60000,
        "servos": [{"id": 11}, {"id": 12}, {"id": 13}],
    }
    start = {11: 2048 + 587, 12: 2048 - 391, 13: 2048 + 261}
    r = vm(
        f"""
import config, servos, vmfakes
from segment import Segment
fake = vmfakes.FakeFeetech([11, 12, 13])
for sid, p in {start!r}.items():
    fake.pos[sid] = p
    fake.goal[sid] = p
fake.silent.add(13)
hal = vmfakes.BusHal(fake)
cfg = config.Config({cfg!r})
bus = servos.make('feetech_sts', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
# every goal written: count, first, largest step between consecutive goals, extremes
G = {{'n': 0, 'first': None, 'prev': None, 'step': 0, 'lo': 4096, 'hi': -1}}
class Spy:
    def write(self, buf, n=-1):
        if buf[4] == 0x83:
            g = [buf[8] | (buf[9] << 8), buf[11] | (buf[12] << 8), buf[14] | (buf[15] << 8)]
            G['n'] += 1
            if G['first'] is None:
                G['first'] = g
            if G['prev'] is not None:
                G['step'] = max([G['step']] + [abs(g[i] - G['prev'][i]) for i in range(3)])
            G['prev'] = g
            G['lo'] = min([G['lo']] + g)
            G['hi'] = max([G['hi']] + g)
        return fake.write(buf, n)
    def readinto(self, b):
        return fake.readinto(b)
bus.uart = Spy()
for _ in range(6):                         # the host streams at once, from power-on
    hal.up.feed(bytes.fromhex('{GREEDY}'))
    vmkit.run(hal, seg, 50)
R['early'] = [G['n'], bus.known, seg.status(), vmkit.hexs(hal.up.take())]
fake.silent.discard(13)                    # the last servo answers: its position is known
for _ in range(20):                        # (resume: its silence was a NO_REPLY fault)
    hal.up.feed(bytes.fromhex('{GREEDY_RESUME}'))
    vmkit.run(hal, seg, 50)
    hal.up.discard()
R['goals'] = G
R['known'] = bus.known
"""
    )
    n, known, status, out = r["early"]
    assert n == 0 and not known  # nothing written while servo 13's position is unknown
    assert status & 0x01  # HOLD reported meanwhile
    assert [m for m in decode(out) if m["type"] == "STATE"]  # but it answers
    g = r["goals"]
    assert r["known"] and g["n"] > 50
    # the first goals start at the measured positions and move by at most one slew step
    lim = STEP_LIMIT * STS_STEPS_PER_RAD + 2
    first = g["first"]
    assert all(
        abs(a - b) <= lim for a, b in zip(first, (start[11], start[12], start[13]), strict=True)
    )
    assert g["step"] <= lim
    # and never leave the default range [-pi, pi] around the centre
    assert 0 <= g["lo"] and g["hi"] <= 4095


def test_pwm_first_pulse_goes_to_the_rest_pose_inside_the_range(vm):
    """Zero lies outside [0.2, 1.0]: the first pulse is the rest pose (0.5), not zero."""
    cfg = {
        "servo_driver": "pwm",
        "watchdog_ms": 60000,
        "pwm": {"pins": [25, 26, 27], "min_us": 500, "max_us": 2500, "range": math.pi},
        "servos": [{"min_angle": 0.2, "max_angle": 1.0, "rest_angle": 0.5}] * 3,
    }
    r = vm(
        f"""
import config, servos, vmfakes
from segment import Segment
hal = vmfakes.BusHal()
cfg = config.Config({cfg!r})
bus = servos.make('pwm', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
vmkit.run(hal, seg, 50)
import gc
gc.collect()
pulses = []
for _ in range(40):
    hal.up.feed(bytes.fromhex('{GREEDY}'))
    hal.t += 5
    seg.poll()
    seg.tick(hal.ticks_ms())
    pulses.append([p.ns for p in hal.pwms])
    hal.up.discard()
R['p'] = pulses
"""
    )
    ns_per_rad = 2_000_000 / math.pi
    lo = 1_500_000 + 0.2 * ns_per_rad
    hi = 1_500_000 + 1.0 * ns_per_rad
    pulses = r["p"]
    first = pulses[0]
    assert all(
        abs(p - (1_500_000 + 0.5 * ns_per_rad)) <= STEP_LIMIT * ns_per_rad + 50 for p in first
    )
    for a, b in zip(pulses, pulses[1:], strict=False):
        for x, y in zip(a, b, strict=True):
            assert abs(y - x) <= STEP_LIMIT * ns_per_rad + 50
    assert all(lo - 50 <= p <= hi + 50 for row in pulses for p in row)


@pytest.mark.parametrize(
    "servo",
    [
        {"min_angle": 0.2, "max_angle": 1.0},  # zero (the default rest pose) outside the range
        {"min_angle": -1.0, "max_angle": 1.0, "rest_angle": 1.5},
    ],
)
def test_pwm_config_without_a_rest_pose_inside_the_range_is_refused(vm, servo):
    cfg = {"servo_driver": "pwm", "servos": [servo] * 3}
    r = vm(
        f"""
import config
try:
    config.Config({cfg!r})
    R['e'] = None
except ValueError as e:
    R['e'] = str(e)
"""
    )
    assert r["e"] and "rest" in r["e"] and "outside its range" in r["e"]


def test_emulated_servos_far_from_zero_start_where_they_are_and_slew(vm):
    """Power-on 1.2/-0.8/0.5 rad from zero, first SYNC asks for straight (0 for every servo)."""
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000, 'emulated_start': [1.2, -0.8, 0.5]}})
R['boot'] = list(seg.bus.true_pos)
prev = list(seg.bus.true_pos)
step = 0
for _ in range(120):
    hal.up.feed(bytes.fromhex('{STRAIGHT}'))
    vmkit.run(hal, seg, 5)
    for i in range(3):
        step = max(step, abs(seg.sc.cmd[i] - prev[i]))
        prev[i] = seg.sc.cmd[i]
    hal.up.discard()
R['step'] = step
R['end'] = [list(seg.bus.true_pos), seg.mc.kappa]
"""
    )
    assert r["boot"] == [12000, -8000, 5000]
    assert 0 < r["step"] <= STEP_LIMIT * 1e4 + 1  # the first command starts at the power-on pose
    pos, kappa = r["end"]
    assert max(abs(p) for p in pos) <= 40 and kappa <= 20  # arrived at straight, slowly


def test_a_servo_powered_up_outside_its_range_is_never_driven(vm):
    """Servo 0 starts at 4 rad, beyond its [-pi, pi] range: SERVO_FAULT out_of_range, no motion
    (the old firmware dragged it to the end of its range at full speed)."""
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000, 'emulated_start': [4.0, 0.0, 0.0]}})
for _ in range(5):
    hal.up.feed(bytes.fromhex('{STRAIGHT}'))
    vmkit.run(hal, seg, 10)
out = vmkit.hexs(hal.up.take())
for _ in range(20):
    hal.up.feed(bytes.fromhex('{STRAIGHT}'))
    vmkit.run(hal, seg, 10)
    hal.up.discard()
R['s'] = [list(seg.bus.true_pos), seg.bus.enabled, seg.status(), list(seg.prev_fault), out]
"""
    )
    pos, enabled, status, faults, out = r["s"]
    assert pos == [40000, 0, 0] and not enabled
    assert status & 0x05 == 0x05 and faults[0] == 5  # SERVO_FAULT + HOLD, out_of_range
    ev = [m for m in decode(out) if m["type"] == "EVENT" and m["name"] == "SERVO_FAULT"]
    assert [e["detail"] for e in ev] == [0]


def test_a_resume_is_refused_while_a_servo_is_still_out_of_range(vm):
    """Review 2026-11-26: a SYNC with resume was "accepted" while servo 0 still sat outside its
    range: hold and the fault bits cleared, the STATE answering it said all was well, and the
    next tick raised a fresh SERVO_FAULT, on every resume. Now it stays in hold and says so."""
    cfg = {"watchdog_ms": 60000, "emulated_start": [1.0, 0.0, 0.0],
           "servos": [{"min_angle": -0.5, "max_angle": 0.5}] * 3}  # fmt: skip
    resume = M.encode_sync(1, 1, [(1.0, 0.0)], resume=True).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({cfg!r})
vmkit.run(hal, seg, 100)
hal.up.discard()
hal.up.feed(bytes.fromhex('{resume}'))
seg.poll()
R['reply'] = vmkit.hexs(hal.up.take())
vmkit.run(hal, seg, 200)
R['later'] = vmkit.hexs(hal.up.take())
R['s'] = [seg.hold, seg.fault_bits, seg.moving, seg.bus.enabled]
"""
    )
    (state,) = [m for m in decode(r["reply"]) if m["type"] == "STATE"]
    assert {"HOLD", "SERVO_FAULT"} <= set(state["status"]), state
    assert r["s"] == [True, 1, False, False]
    assert not [m for m in decode(r["later"]) if m["type"] == "EVENT"]  # no fault re-raised
