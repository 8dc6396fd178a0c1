"""Requests and situations that must not upset a segment: refused values answered (never an
exception out of poll()), replies too large for a frame, identity with a configured uid, a
lowered kappa_max applied to the current target, and event pacing after days without events."""

from __future__ import annotations

import math

from protocol import messages as M
from protocol.frame import encode_frame
from tests.device.conftest import decode


def test_refused_parameter_values_are_answered_and_the_rest_of_the_read_still_runs(vm):
    """watchdog_ms = inf (int(inf) raises OverflowError) and a fault text whose reply cannot fit
    a frame: each gets an ERROR reply, and the SYNC behind them in the same read is processed."""
    blob = b"".join(
        [
            encode_frame(0, 0, 0x05, 1, {0: 0, 1: math.inf}),  # PARAM_SET watchdog_ms := inf
            M.encode_param_set(2, 0, 5, "0:stuck," * 24 + "1:st"),  # reply would not fit
            M.encode_sync(3, 7, [(1.0, 0.0)]),
        ]
    ).hex()
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{blob}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['armed'] = seg.armed
R['wd'] = seg.watchdog_ms
"""
    )
    msgs = {m["seq"]: m for m in decode(r["up"]) if m["type"] in ("ERROR", "STATE")}
    assert msgs[1]["type"] == "ERROR" and msgs[1]["code"] == 2 and r["wd"] == 200
    assert msgs[2]["type"] == "ERROR" and msgs[2]["code"] == 2
    assert msgs[3]["type"] == "STATE" and r["armed"]


def test_identity_check_accepts_a_configured_uid_whatever_its_case(vm):
    req = M.encode_param_get(1, 0, 0, uid="Seg-A").hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'uid_override': 'Seg-A'}})
hal.up.feed(bytes.fromhex('{req}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
"""
    )
    (reply,) = [m for m in decode(r["up"]) if m["seq"] == 1]
    assert reply["type"] == "PARAM_VALUE"


def test_a_lowered_kappa_max_applies_to_the_current_target_at_the_rate_limit(vm):
    """Bent to 3 1/m, then kappa_max := 1.0 with only HEARTBEATs afterwards: the segment moves
    down to 1.0 (slew-limited) instead of staying beyond the new limit."""
    bend = M.encode_sync(1, 1, [(3.0, 0.5)]).hex()
    lower = M.encode_param_set(2, 0, 1, 1.0).hex()
    hb = M.encode_heartbeat(3, 2).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
for _ in range(150):                       # 1.5 s of SYNCs at 100 Hz: reach 3 1/m
    hal.up.feed(bytes.fromhex('{bend}'))
    vmkit.run(hal, seg, 10)
R['bent'] = seg.mc.kappa
hal.up.feed(bytes.fromhex('{lower}'))
vmkit.run(hal, seg, 5)
prev = [seg.mc.cx, seg.mc.cy]
R['max_move'] = 0
R['grew'] = 0
for _ in range(150):
    hal.up.feed(bytes.fromhex('{hb}'))
    vmkit.run(hal, seg, 10)
    cur = [seg.mc.cx, seg.mc.cy]
    R['max_move'] = max(R['max_move'], abs(cur[0] - prev[0]) + abs(cur[1] - prev[1]))
    if cur[0] * cur[0] + cur[1] * cur[1] > prev[0] * prev[0] + prev[1] * prev[1] + 100:
        R['grew'] += 1
    prev = cur
R['after'] = [seg.mc.kappa, seg.mc.kappa_max, seg.mc.step]
"""
    )
    assert r["bent"] > 29000
    kappa, kappa_max, step = r["after"]
    assert kappa_max == 10000 and abs(kappa - 10000) <= 50
    assert r["grew"] == 0  # straight down towards the new limit, never out again
    # at most 2 ticks of slew per 10 ms (L1 norm of a step <= sqrt(2) * its length)
    assert r["max_move"] <= 1.5 * 2 * step


def test_events_are_sent_promptly_after_days_without_any_event(vm):
    """Stamps of the last event are only refreshed when one is sent; 2**29 ms (6.2 days) later a
    signed difference turned negative and held new events back. The watchdog event must go out
    within a few ticks of the trip however long the segment ran quietly before."""
    sync = M.encode_sync(1, 1, [(0.0, 0.0)]).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 100}})
vmkit.run(hal, seg, 300)                   # BOOT event goes out, stamps set
hal.up.take()
hal.t += (1 << 29) + 10000                 # 6.2 days and 10 s of quiet operation
hal.up.feed(bytes.fromhex('{sync}'))
vmkit.run(hal, seg, 10)                    # arms the watchdog (a SYNC clears nothing yet)
hal.up.take()
vmkit.run(hal, seg, 300)                   # host silent: the watchdog trips after 100 ms
R['up'] = vmkit.hexs(hal.up.take())
R['tripped'] = seg.wd_tripped
"""
    )
    names = [m["name"] for m in decode(r["up"]) if m["type"] == "EVENT"]
    assert r["tripped"] and "WATCHDOG_TRIPPED" in names


def test_a_rejected_config_file_keeps_the_segment_in_hold_while_it_still_answers(vm):
    """config.json present but invalid: the calibration is unknown, so the segment holds (HOLD and
    UNCONFIGURED bits, reason readable as parameter config_error) and ignores setpoints, yet it
    answers discovery and keeps forwarding, so the host can see and fix it."""
    sync = M.encode_sync(1, 1, [(2.0, 0.0)]).hex()
    discover = M.encode_discover(2).hex()
    r = vm(
        f"""
import config, servos
from segment import Segment
with open('/tmp/ucr_rejected_config.json', 'w') as f:
    f.write('{{"length": -1}}')
hal = vmkit.LoopHal()
cfg = config.load('/tmp/ucr_rejected_config.json')
bus = servos.make('emulated', cfg, hal)
seg = Segment(hal, cfg, bus, 5)
start = list(bus.true_pos)
for _ in range(50):
    hal.up.feed(bytes.fromhex('{sync}'))
    vmkit.run(hal, seg, 10)
    hal.up.take()
hal.up.feed(bytes.fromhex('{discover}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['moved'] = list(bus.true_pos) != start
R['status'] = seg.status()
R['error'] = seg.get_param(16)
"""
    )
    assert not r["moved"]
    assert r["status"] & 0x01 and r["status"] & 0x20  # HOLD and UNCONFIGURED
    assert "length" in r["error"]
    assert any(m["type"] == "DESCRIPTOR" for m in decode(r["up"]))


def test_the_boot_event_goes_out_before_any_reply_of_the_segments_life(vm):
    """A DISCOVER waiting in the port's buffer when the segment starts (a host that was up first,
    retrying) was answered at the first poll, and the BOOT went out at the first tick, after the
    DESCRIPTOR: the host then took the BOOT for a restart after its discovery (a topology change
    that aborted the first goal). The BOOT now leaves while the segment is built, so on the wire
    it precedes every reply of this life (relays keep each position's order)."""
    discover = M.encode_discover(1).hex()
    r = vm(
        f"""
import config, servos
from segment import Segment
hal = vmkit.LoopHal()
hal.up.feed(bytes.fromhex('{discover}'))   # waiting before the segment is built
cfg = config.Config({{}}, "emulated")
seg = Segment(hal, cfg, servos.make(cfg.driver, cfg, hal), 5)
seg.poll()
R['up'] = vmkit.hexs(hal.up.take())
"""
    )
    kinds = [m["type"] + (":" + m["name"] if m["type"] == "EVENT" else "") for m in decode(r["up"])]
    assert kinds[:2] == ["EVENT:BOOT", "DESCRIPTOR"], kinds
