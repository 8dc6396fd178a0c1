"""Chain behaviour of one segment on the MicroPython VM, driven through a loopback HAL: forwarding
rules, discovery, parameters, errors, bad frames, neighbour presence, ALIVE, UNCONFIGURED."""

from __future__ import annotations

from protocol import messages as M
from protocol.constants import FLAG_BCAST, FLAG_LOCAL, FLAG_UP
from protocol.frame import encode_frame
from tests.device.conftest import decode, frames

UID = "00aa11bb22cc"  # vmkit.LoopHal's uid


#: kappa 1/m, phi rad per position (wire: 1000/0, 2000/0, 15000/-20000, 4000/0)
_SPS = [(0.1, 0.0), (0.2, 0.0), (1.5, -2.0), (0.4, 0.0)]


def test_broadcast_is_processed_with_its_position_and_forwarded_with_hop_plus_one(vm):
    sync = encode_frame(FLAG_BCAST, 2, 0x02, 77, M.sync_payload(9, _SPS))
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{sync.hex()}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['down'] = vmkit.hexs(hal.down.take())
R['t'] = [seg.position, seg.mc.tx, seg.mc.ty]
"""
    )
    down = frames(r["down"])
    assert len(down) == 1
    assert (down[0].flags, down[0].hop, down[0].mtype, down[0].seq) == (FLAG_BCAST, 3, 0x02, 77)
    assert down[0].payload == frames(sync.hex())[0].payload  # payload untouched
    states = [m for m in decode(r["up"]) if m["type"] == "STATE"]
    assert len(states) == 1 and states[0]["seq"] == 77 and states[0]["cycle"] == 9
    assert states[0]["hop"] == 0 and states[0]["flags"] == FLAG_UP
    position, tx, ty = r["t"]
    assert position == 2  # took entry 2 of the list: (1.5 1/m, -2.0 rad)
    assert abs(tx - round(15000 * -0.4161468)) <= 3 and abs(ty - round(15000 * -0.9092974)) <= 3


def test_addressed_frames_are_answered_at_hop_zero_and_forwarded_otherwise(vm):
    mine = M.encode_param_get(5, 0, 10)
    other = M.encode_param_get(6, 3, 10)
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{mine.hex()}'))
vmkit.run(hal, seg, 5)
R['mine'] = [vmkit.hexs(hal.up.take()), vmkit.hexs(hal.down.take())]
hal.up.feed(bytes.fromhex('{other.hex()}'))
vmkit.run(hal, seg, 5)
R['other'] = [vmkit.hexs(hal.up.take()), vmkit.hexs(hal.down.take())]
"""
    )
    up, down = r["mine"]
    vals = [m for m in decode(up) if m["type"] == "PARAM_VALUE"]
    assert vals == [dict(vals[0], param_id=10, value=UID)] and vals[0]["seq"] == 5
    assert frames(down) == []
    up, down = r["other"]
    assert [m for m in decode(up) if m["type"] != "EVENT"] == []
    fwd = frames(down)
    assert len(fwd) == 1 and fwd[0].hop == 2 and fwd[0].mtype == 0x04 and fwd[0].seq == 6


def test_upstream_frames_are_forwarded_with_hop_plus_one_and_local_ones_consumed(vm):
    state = M.encode_state(
        3,
        cycle=1,
        t_ms=5,
        kappa=0.0,
        phi=0.0,
        servo_angles=[0.0, 0.0, 0.0],
        status=0,
    )
    event = encode_frame(FLAG_UP, 4, 0x85, 0, {0: 1, 1: 0, 2: 7})
    alive = M.encode_alive(0)
    r = vm(
        f"""
hal, seg = vmkit.make()
vmkit.run(hal, seg, 30)
hal.up.take()
hal.down.feed(bytes.fromhex('{state.hex() + event.hex() + alive.hex()}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['st'] = seg.status()
"""
    )
    up = frames(r["up"])
    fwd = [f for f in up if f.mtype in (0x83, 0x85) and f.hop != 0]
    assert [(f.mtype, f.hop) for f in fwd] == [(0x83, 1), (0x85, 5)]
    assert fwd[0].payload == frames(state.hex())[0].payload
    assert not any(f.mtype == 0x07 and f.hop == 1 for f in up)  # neighbour's ALIVE consumed
    assert r["st"] & 0x10  # DOWNSTREAM


def test_downstream_presence_events_descriptor_flag_and_alive_timing(vm):
    alive = M.encode_alive(0).hex()
    disc = M.encode_discover(9).hex()
    r = vm(
        f"""
hal, seg = vmkit.make()
vmkit.run(hal, seg, 300)
R['idle'] = vmkit.hexs(hal.up.take())
for _ in range(6):            # neighbour's ALIVE every 50 ms keeps it present
    hal.down.feed(bytes.fromhex('{alive}'))
    vmkit.run(hal, seg, 50)
hal.up.feed(bytes.fromhex('{disc}'))
vmkit.run(hal, seg, 5)
R['present'] = vmkit.hexs(hal.up.take())
vmkit.run(hal, seg, 200)       # neighbour unplugged
hal.up.feed(bytes.fromhex('{disc}'))
vmkit.run(hal, seg, 30)
R['gone'] = vmkit.hexs(hal.up.take())
"""
    )
    idle = frames(r["idle"])
    alives = [f for f in idle if f.mtype == 0x07]
    assert all(f.flags == FLAG_UP | FLAG_LOCAL and f.hop == 0 for f in alives)
    assert 4 <= len(alives) <= 6  # one per 50 ms of upstream silence in 300 ms
    msgs = decode(r["present"])
    assert [m["name"] for m in msgs if m["type"] == "EVENT"] == ["DOWNSTREAM_UP"]
    desc = [m for m in msgs if m["type"] == "DESCRIPTOR"]
    assert desc[0]["downstream_present"] is True and desc[0]["uid"] == UID
    msgs = decode(r["gone"])
    assert [m["name"] for m in msgs if m["type"] == "EVENT"] == ["DOWNSTREAM_DOWN"]
    assert [m for m in msgs if m["type"] == "DESCRIPTOR"][0]["downstream_present"] is False


def test_parameters_identity_and_errors(vm):
    reqs = [
        M.encode_param_get(1, 0, 0, uid=UID),  # ok
        M.encode_param_get(2, 0, 0, uid="ffffffffffff"),  # identity mismatch
        M.encode_param_get(3, 0, 99),  # unknown param
        M.encode_param_set(4, 0, 0, 50),  # watchdog_ms := 50
        M.encode_param_set(5, 0, 1, 99.0),  # kappa_max above the flashed limit
        M.encode_param_set(6, 0, 1, 1.5),  # kappa_max := 1.5
        M.encode_param_set(7, 0, 6, 3),  # frames_ok is read-only
        M.encode_param_set(8, 0, 3, "p_slew"),  # sc strategy
        M.encode_param_set(9, 0, 5, "7:stuck"),  # servo index out of range
        M.encode_param_set(10, 0, 3, "bogus"),
        encode_frame(0, 0, 0x42, 11, {}),  # unknown type
        encode_frame(0, 0, 0x04, 12, {0: 0}, ver=1),  # unsupported version (the old one)
        encode_frame(FLAG_BCAST, 0, 0x02, 13, {0: "x"}),  # malformed SYNC
        encode_frame(0, 0, 0x04, 14, [1, 2]),  # malformed PARAM_GET
        M.encode_param_get(15, 0, 9),  # dropped counter
    ]
    blob = b"".join(reqs).hex()
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{blob}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['p'] = [seg.watchdog_ms, seg.mc.kappa_max, seg.sc.name]
"""
    )
    by_seq = {m["seq"]: m for m in decode(r["up"]) if m["type"] in ("PARAM_VALUE", "ERROR")}
    assert by_seq[1]["value"] == 200
    assert by_seq[2]["type"] == "ERROR" and by_seq[2]["code"] == 6
    assert by_seq[3]["code"] == 4
    assert by_seq[4]["value"] == 50
    assert by_seq[5]["code"] == 2 and "flashed" in by_seq[5]["text"]
    assert abs(by_seq[6]["value"] - 1.5) < 1e-9
    assert by_seq[7]["code"] == 2 and "read-only" in by_seq[7]["text"]
    assert by_seq[8]["value"] == "p_slew"
    assert by_seq[9]["code"] == 2 and by_seq[10]["code"] == 2
    assert by_seq[11]["code"] == 1 and by_seq[11]["offending_type"] == 0x42
    assert by_seq[12]["code"] == 3 and "2..2" in by_seq[12]["text"]
    assert by_seq[13]["code"] == 5 and by_seq[14]["code"] == 5
    assert by_seq[15]["value"] == 4  # unknown type, bad version, 2 malformed
    assert r["p"] == [50, 15000, "p_slew"]


def test_corrupt_frames_are_counted_dropped_and_never_forwarded(vm):
    good = M.encode_discover(1)
    bad_crc = bytearray(M.encode_heartbeat(2, 5))
    bad_crc[4] ^= 0x10
    garbage = bytes([0x55] * 40) + b"\x00" + bytes([0x03, 0x01, 0x02]) + b"\x00"
    oversize = bytes([0x11] * 300) + b"\x00"
    blob = (bytes(bad_crc) + garbage + oversize + good).hex()
    counters = b"".join(M.encode_param_get(10 + i, 0, p) for i, p in enumerate((6, 7, 8)))
    r = vm(
        f"""
hal, seg = vmkit.make()
hal.up.feed(bytes.fromhex('{blob}'))
vmkit.run(hal, seg, 5)
R['up'] = vmkit.hexs(hal.up.take())
R['down'] = vmkit.hexs(hal.down.take())
hal.up.feed(bytes.fromhex('{counters.hex()}'))
vmkit.run(hal, seg, 5)
R['c'] = vmkit.hexs(hal.up.take())
"""
    )
    msgs = decode(r["up"])
    assert [m["type"] for m in msgs if m["type"] not in ("EVENT", "ALIVE")] == ["DESCRIPTOR"]
    assert [(f.mtype, f.hop) for f in frames(r["down"])] == [(0x01, 1)]  # only the good one
    vals = {m["param_id"]: m["value"] for m in decode(r["c"]) if m["type"] == "PARAM_VALUE"}
    assert vals[7] == 1  # crc errors
    assert vals[8] >= 2  # garbage (bad COBS / runt) + oversize
    assert vals[6] == 2  # good frames when read: the DISCOVER and this PARAM_GET


def test_unconfigured_status_and_a_rejected_config_file(vm):
    r = vm(
        """
import config, gc
hal, seg = vmkit.make(unconfigured=True)
R['default'] = seg.status() & 0x20
del hal, seg
gc.collect()
hal, seg = vmkit.make({'name': 'x'})
R['configured'] = seg.status() & 0x20
with open('/tmp/ucr_bad_config.json', 'w') as f:
    f.write('{"length": -1}')
c = config.load('/tmp/ucr_bad_config.json')
R['bad'] = [c.unconfigured, c.error, c.si['length']]
c = config.load('/nonexistent/config.json')
R['absent'] = [c.unconfigured, c.error]
for bad in ({'servos': [{}]}, {'tendon_angles': [0, 0]}, {'sc': 'x'}, {'servo_driver': 'y'}):
    try:
        c = config.Config(bad)
        import mechanism
        mechanism.Mechanism(c, 5)
        R.setdefault('accepted', []).append(bad)
    except ValueError as e:
        R.setdefault('errors', []).append(str(e))
""",
        # eight configurations in one VM, each compiling protocol/boards.py anew (the firmware
        # frees it after its one boot): more than a boot needs. A boot's fit in the ESP32 heap
        # is proven by test_device_unix_port (the real main.py) and benchmarks/bench_firmware.py.
        heap="200k",
    )
    assert r["default"] == 0x20 and r["configured"] == 0
    assert r["bad"][0] is True and "length" in r["bad"][1] and r["bad"][2] == 0.316
    assert r["absent"] == [True, None]
    assert "accepted" not in r and len(r["errors"]) == 4
