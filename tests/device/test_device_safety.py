"""Segment safety on the MicroPython VM: boot hold, slew from the measured pose, watchdog, HOLD,
servo faults of every kind (stall, no reply, overload), injected at boot or at run time."""

from __future__ import annotations

import math

from protocol import messages as M
from tests.device.conftest import decode, frames

SYNC_BENT = M.encode_sync(1, 1, [(2.0, 0.5)]).hex()


def _states(msgs):
    return [m for m in msgs if m["type"] == "STATE"]


def _events(msgs):
    return [m["name"] for m in msgs if m["type"] == "EVENT"]


def test_boot_holds_until_the_first_sync_then_slews_from_the_measured_pose(vm):
    hb = M.encode_heartbeat(1, 10).hex()
    sync = M.encode_sync(2, 11, [(2.0, math.pi / 2)]).hex()
    r = vm(
        f"""
import config, servos, mechanism
from segment import Segment
hal = vmkit.LoopHal()
cfg = config.Config({{'watchdog_ms': 10000}})
bus = servos.make('emulated', cfg, hal)
# the segment wakes up bent at (2 1/m, phi 0): e.g. it was powered off while bent
pre = mechanism.Mechanism(cfg, 5)
pre.set_target(20000, 0)
pre.cx = pre.tx
pre.cy = pre.ty
pre._servo_targets()
for i in range(3):
    bus.true_pos[i] = pre.servo_target[i]
seg = Segment(hal, cfg, bus, 5)
start = list(bus.true_pos)
hal.up.feed(bytes.fromhex('{hb}'))
vmkit.run(hal, seg, 500)
R['after_boot'] = [list(bus.true_pos), start, bus.enabled]
R['hb'] = vmkit.hexs(hal.up.take())
hal.up.feed(bytes.fromhex('{sync}'))
vmkit.run(hal, seg, 5)
R['first'] = [seg.mc.cx, seg.mc.cy, seg.mc.step]
vmkit.run(hal, seg, 1500)
R['end'] = [seg.mc.mx, seg.mc.my, seg.status()]
"""
    )
    pos, start, enabled = r["after_boot"]
    assert pos == start and not enabled  # no motion, no output in the boot hold
    st = _states(decode(r["hb"]))
    assert st and "HOLD" in st[0]["status"] and st[0]["kappa"] > 1.99
    cx, cy, step = r["first"]
    # first commanded vector: one slew step from the measured (2, 0), not from straight
    assert math.hypot(cx - 20000, cy) <= step + 2
    mx, my, status = r["end"]
    assert math.hypot(mx, my - 20000) <= 30 and status & 1 == 0


def test_watchdog_trips_holds_and_clears_on_the_next_sync(vm):
    hb = M.encode_heartbeat(3, 2).hex()
    sync2 = M.encode_sync(4, 3, [(3.0, -1.0)]).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 100}})
hal.up.feed(bytes.fromhex('{SYNC_BENT}'))
vmkit.run(hal, seg, 40)
for _ in range(4):            # heartbeats every 50 ms keep it alive
    hal.up.feed(bytes.fromhex('{hb}'))
    vmkit.run(hal, seg, 50)
R['alive'] = [seg.wd_tripped, vmkit.hexs(hal.up.take())]
vmkit.run(hal, seg, 105)       # silence > watchdog_ms
R['trip_t'] = hal.t
pos = list(seg.bus.true_pos)
hal.up.feed(bytes.fromhex('{hb}'))   # a heartbeat does not clear a tripped watchdog
vmkit.run(hal, seg, 300)
R['held'] = [pos, list(seg.bus.true_pos), seg.wd_tripped, vmkit.hexs(hal.up.take())]
hal.up.feed(bytes.fromhex('{sync2}'))
vmkit.run(hal, seg, 10)
R['after'] = [seg.wd_tripped, vmkit.hexs(hal.up.take())]
for _ in range(30):
    hal.up.feed(bytes.fromhex('{sync2}'))
    vmkit.run(hal, seg, 50)
    hal.up.discard()
R['moved'] = [seg.wd_tripped, seg.mc.kappa, seg.mc.phi]
"""
    )
    tripped, out = r["alive"]
    assert not tripped and "WATCHDOG_TRIPPED" not in _events(decode(out))
    pos_then, pos_later, tripped, out = r["held"]
    msgs = decode(out)
    assert tripped and _events(msgs).count("WATCHDOG_TRIPPED") == 1
    # held: at most the settling of the servos' first-order lag after the trip
    assert max(abs(a - b) for a, b in zip(pos_then, pos_later, strict=True)) <= 2
    assert "WATCHDOG" in _states(msgs)[-1]["status"]
    still, out = r["after"]
    msgs = decode(out)
    assert not still and "WATCHDOG_CLEARED" in _events(msgs)
    assert "WATCHDOG" not in _states(msgs)[0]["status"]
    still, kappa, phi = r["moved"]
    assert not still and abs(kappa - 30000) <= 30 and abs(phi + 10000) <= 30


def test_hold_message_stops_motion_until_a_sync_with_resume(vm):
    hold = M.encode_hold(5).hex()
    go = M.encode_sync(6, 5, [(3.0, 1.0)]).hex()
    go_resume = M.encode_sync(7, 6, [(3.0, 1.0)], resume=True).hex()
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{SYNC_BENT}'))
vmkit.run(hal, seg, 100)
hal.up.feed(bytes.fromhex('{hold}'))
vmkit.run(hal, seg, 10)
pos = list(seg.bus.true_pos)
hal.up.feed(bytes.fromhex('{go}'))
vmkit.run(hal, seg, 300)
R['held'] = [pos, list(seg.bus.true_pos), seg.status(), vmkit.hexs(hal.down.take())]
for _ in range(30):
    hal.up.feed(bytes.fromhex('{go_resume}'))
    vmkit.run(hal, seg, 50)
    hal.up.discard()
R['resumed'] = [seg.status(), seg.mc.kappa, seg.mc.phi]
"""
    )
    pos, later, status, down = r["held"]
    assert pos == later and status & 1
    assert any(f.mtype == 0x06 and f.hop == 1 for f in frames(down))  # HOLD forwarded
    status, kappa, phi = r["resumed"]
    assert status & 1 == 0 and abs(kappa - 30000) <= 30 and abs(phi - 10000) <= 30


FAULT_RUN = """
hal, seg = vmkit.make({{'watchdog_ms': 10000}}, faults={boot!r})
hal.up.feed(bytes.fromhex('{sync}'))
vmkit.run(hal, seg, 60)
hal.up.feed(bytes.fromhex('{inject}'))
vmkit.run(hal, seg, 20)
vmkit.run(hal, seg, 400)
pos = list(seg.bus.pos)
tgt = list(seg.mc.servo_target)
vmkit.run(hal, seg, 100)
R['fault'] = [seg.status(), list(seg.bus.fault), pos, list(seg.bus.pos), tgt,
              list(seg.mc.servo_target), vmkit.hexs(hal.up.take())]
hal.up.feed(bytes.fromhex('{resume}'))
vmkit.run(hal, seg, 50)
R['refused'] = seg.status()
hal.up.feed(bytes.fromhex('{clear}'))
vmkit.run(hal, seg, 20)
R['up'] = vmkit.hexs(hal.up.take())
for _ in range(30):
    hal.up.feed(bytes.fromhex('{resume}'))
    vmkit.run(hal, seg, 50)
    hal.up.discard()
R['cleared'] = [seg.status(), seg.mc.kappa]
"""


def _fault_case(vm, kind, at_boot):
    sync = M.encode_sync(1, 1, [(3.0, 0.3)]).hex()
    inject = (
        M.encode_heartbeat(2, 2).hex()
        if at_boot
        else M.encode_param_set(2, 0, 5, "1:" + kind).hex()
    )
    resume = M.encode_sync(3, 3, [(3.0, 0.3)], resume=True).hex()
    clear = M.encode_param_set(4, 0, 5, "none").hex()
    code = FAULT_RUN.format(
        boot=("1:" + kind) if at_boot else None,
        sync=sync,
        inject=inject,
        resume=resume,
        clear=clear,
    )
    return vm(code)


def _check_fault(r, kind, expected_code):
    status, faults, pos, later, tgt, tgt_later, out = r["fault"]
    msgs = decode(out)
    ev = [m for m in msgs if m["type"] == "EVENT" and m["name"] == "SERVO_FAULT"]
    assert [e["detail"] for e in ev] == [1], kind
    assert status & 0x04 and status & 0x01, kind  # SERVO_FAULT + HOLD
    assert faults[1] == expected_code, kind
    assert tgt == tgt_later, kind  # targets frozen while held
    if kind != "disconnected":
        assert max(abs(a - b) for a, b in zip(pos, later, strict=True)) <= 5, kind
    if kind == "stuck":
        assert r["refused"] & 0x01 == 0  # a stall is retried on resume (not a persistent flag)
    else:
        assert r["refused"] & 0x05 == 0x05, kind  # persistent fault: resume refused
    status, kappa = r["cleared"]
    assert status & 0x05 == 0, kind
    assert abs(kappa - 30000) <= 40, kind


def test_servo_faults_injected_at_run_time_are_detected_reported_and_held(vm):
    for kind, code in (("disconnected", 1), ("overload", 3)):
        _check_fault(_fault_case(vm, kind, at_boot=False), kind, code)


def test_stuck_servo_is_detected_as_a_stall_while_moving(vm):
    r = _fault_case(vm, "stuck", at_boot=True)
    status, faults, pos, later, tgt, tgt_later, out = r["fault"]
    ev = [m for m in decode(out) if m["type"] == "EVENT" and m["name"] == "SERVO_FAULT"]
    assert [e["detail"] for e in ev] == [1]
    assert status & 0x05 == 0x05
    assert r["cleared"][0] & 0x05 == 0 and abs(r["cleared"][1] - 30000) <= 40


def test_fault_injected_at_boot_holds_from_the_start(vm):
    r = _fault_case(vm, "overload", at_boot=True)
    _check_fault(r, "overload", 3)


def test_clamping_sets_the_status_bit_and_limit_events_are_rate_limited(vm):
    far = M.encode_sync(1, 1, [(9.0, 0.0)]).hex()  # beyond kappa_max 3.31 1/m
    near = M.encode_sync(2, 2, [(0.5, 0.0)]).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
out = []
for _ in range(50):            # 500 ms of SYNCs asking for too much curvature
    hal.up.feed(bytes.fromhex('{far}'))
    vmkit.run(hal, seg, 10)
    out.append(vmkit.hexs(hal.up.take()))
R['far'] = out
R['far_status'] = seg.status()
for _ in range(100):
    hal.up.feed(bytes.fromhex('{near}'))
    vmkit.run(hal, seg, 10)
    hal.up.discard()
hal.up.feed(bytes.fromhex('{near}'))
vmkit.run(hal, seg, 10)
R['near_status'] = seg.status()
""",
        heap="512k",  # room for the collected wire output (test data, not the firmware)
    )
    msgs = [m for h in r["far"] for m in decode(h)]
    ev = [m for m in msgs if m["type"] == "EVENT" and m["name"] == "LIMIT_CLAMPED"]
    assert 4 <= len(ev) <= 6  # about one per 100 ms over 500 ms, not one per cycle
    gaps = [b["t_ms"] - a["t_ms"] for a, b in zip(ev, ev[1:], strict=False)]
    assert min(gaps) >= 100 - 20, gaps  # queued every 100 ms; sending may wait 20 ms (spacing)
    assert ev[0]["detail"] & 0b011 == 0b011  # kappa clamped and rate limited
    st = [sorted(m["status"]) for m in msgs if m["type"] == "STATE"]
    assert all("CLAMPED" in s for s in st), st
    assert r["far_status"] & 0x08 and not r["near_status"] & 0x08


def test_motion_starts_from_uneven_servo_angles_at_servo_speed_not_in_one_jump(vm):
    """Servos powered up at uneven angles the curvature model cannot represent (all three wound
    in by different amounts): the first SYNC must not snap them to the model's pose in one tick;
    every command moves at most servo_speed * tick per cycle, for any SC strategy."""
    sync = M.encode_sync(2, 11, [(0.0, 0.0)]).hex()
    r = vm(
        f"""
import gc, config, servos
from array import array
from segment import Segment
R['runs'] = []
for sc in ('direct', 'p_slew'):
    hal = vmkit.LoopHal()
    cfg = config.Config({{'watchdog_ms': 10000, 'sc': sc}})
    bus = servos.make('emulated', cfg, hal)
    for i, p in enumerate((3000, 3500, 4000)):
        bus.true_pos[i] = p
    seg = Segment(hal, cfg, bus, 5)
    hal.up.feed(bytes.fromhex('{sync}'))
    cmds = array('i')  # flat (60 x 3): the test's data stays small beside the firmware
    for _ in range(60):
        vmkit.run(hal, seg, 1)
        cmds.extend(seg.sc.cmd)
    R['runs'].append([sc, seg.sc.step_limit, [3000, 3500, 4000], cmds])
    del seg, bus, hal, cfg  # one segment at a time fits the ESP32-sized heap
    gc.collect()
for run in R['runs']:
    c = run[3]
    run[3] = [list(c[k:k + 3]) for k in range(0, len(c), 3)]
"""
    )
    for sc, limit, start, cmds in r["runs"]:
        prev = start
        for cmd in cmds:
            assert all(abs(c - p) <= limit for c, p in zip(cmd, prev, strict=True)), (sc, prev, cmd)
            prev = cmd
        assert limit == 300  # 6 rad/s * 5 ms = 0.03 rad = 300 units
        assert cmds[-1] != start  # and it does move on towards the commanded pose


def test_a_bad_position_reply_never_becomes_a_hold_target(vm):
    """Review 2026-11-26: one checksummed Feetech reply of 4000 steps (~ +2.98 rad; the range is
    +-0.5 rad, goals <= 2374) made the segment hold and then write goal 4000 to that servo every
    tick: hold_here copied the reading into the targets. Now a reading that far out keeps the
    servo's last target, inside the range."""
    servo = {"min_angle": -0.5, "max_angle": 0.5}
    cfg = {"servo_driver": "feetech_sts", "watchdog_ms": 60000,
           "servos": [dict(servo, id=i) for i in (11, 12, 13)]}  # fmt: skip
    sync = M.encode_sync(1, 1, [(2.0, 0.3)]).hex()
    r = vm(
        f"""
import config, servos, vmfakes
from segment import Segment
fake = vmfakes.FakeFeetech([11, 12, 13])
hal = vmfakes.BusHal(fake)
cfg = config.Config({cfg!r})
bus = servos.make('feetech_sts', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
goals = []
glitch = [False]
class Spy:
    def write(self, buf, n=-1):
        if buf[4] == 0x02 and buf[2] == 11 and glitch[0]:  # the read of servo 11
            glitch[0] = False
            keep = fake.pos[11]
            fake.pos[11] = 4000
            r = fake.write(buf, n)
            fake.pos[11] = keep
            return r
        if buf[4] == 0x83:  # SYNC WRITE of the goals
            goals.append(buf[8] | (buf[9] << 8))
        return fake.write(buf, n)
    def readinto(self, b):
        return fake.readinto(b)
bus.uart = Spy()
for _ in range(10):
    hal.up.feed(bytes.fromhex('{sync}'))
    vmkit.run(hal, seg, 20)
hal.up.discard()
R['moving'] = seg.moving
n = len(goals)
glitch[0] = True
vmkit.run(hal, seg, 40)
R['after'] = goals[n:]
R['hold'] = seg.hold
R['events'] = vmkit.hexs(hal.up.take())
"""
    )
    assert r["moving"] and r["hold"]
    assert "SERVO_FAULT" in _events(decode(r["events"]))
    limit = 2048 + 0.5 * 4096 / (2 * math.pi)
    assert r["after"] and max(r["after"]) <= limit + 1, r["after"]


def test_the_curvature_slews_no_faster_than_a_rate_below_one_unit_per_tick(vm):
    """Review 2026-11-26: the slew step was rate * tick rounded to whole 1e-4 1/m units, at least
    one: 0.03 1/m/s slewed at 0.04, a PARAM_SET of 0.01 at 0.02, the config's minimum 0.001 at
    0.02. The fraction is now carried from tick to tick."""
    cases = ((1.0, 0.03, 5), (1.0, 0.01, 5), (0.001, None, 5), (1.0, 0.075, 2))
    for cfg_rate, set_rate, tick in cases:
        cfg = {"watchdog_ms": 60000, "kappa_rate_max": cfg_rate, "tick_ms": tick}
        pset = M.encode_param_set(3, 0, 2, set_rate).hex() if set_rate else ""
        sync = M.encode_sync(1, 1, [(3.0, 0.0)]).hex()
        hb = M.encode_heartbeat(2, 2).hex()
        r = vm(
            f"""
hal, seg = vmkit.make({cfg!r}, tick_ms={tick})
if '{pset}':
    hal.up.feed(bytes.fromhex('{pset}'))
vmkit.run(hal, seg, 20)
hal.up.feed(bytes.fromhex('{sync}'))
vmkit.run(hal, seg, {tick})
c0 = seg.mc.cx
t0 = hal.t
for _ in range(20):
    hal.up.feed(bytes.fromhex('{hb}'))
    vmkit.run(hal, seg, 100)
    hal.up.discard()
R['d'] = seg.mc.cx - c0
R['ms'] = hal.t - t0
R['rate'] = seg.rate_max_si
"""
        )
        actual = r["d"] * 1e-4 / (r["ms"] / 1000.0)
        assert actual <= r["rate"] * 1.001, (cfg_rate, set_rate, tick, actual)
        assert actual >= r["rate"] * 0.95, (cfg_rate, set_rate, tick, actual)  # not stuck
