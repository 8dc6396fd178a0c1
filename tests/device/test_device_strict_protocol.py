"""Strict protocol on the MicroPython VM (issue 11, finding 7): invalid content anywhere in a
frame, even under keys the segment ignores, is answered with ERROR MALFORMED and nothing is
executed; wire ints stop short of -2**30; LIMIT_CLAMPED events are >= 100 ms apart on the wire;
STATE names the chain position whose setpoint was applied, so a misaddressed SYNC shows."""

from __future__ import annotations

import math

import pytest

from protocol import messages as M
from protocol.frame import decode_frame, encode_frame
from tests.device.conftest import decode

BCAST = 0x02
_HEAD = b"\xa3\x00\x01\x01\x45\x00\x75\x30\x0b\xb8"  # {0: 1, 1: h'007530 0bb8', ...}


def _sync_with(extra_key_value: bytes) -> bytes:
    """SYNC {0: 1, 1: (3 1/m, 0.3 rad), 9: <raw CBOR>} (9 is a key the firmware ignores)."""
    return encode_frame(BCAST, 0, 0x02, 7, _HEAD + b"\x09" + extra_key_value)


CORPUS = {
    "too_deep": b"\x81" * 8 + b"\x80",  # 9 nested lists under the ignored key
    "bad_utf8": b"\x62\xc3\x28",
    "overlong_utf8": b"\x62\xc0\xaf",
    "surrogate_utf8": b"\x63\xed\xa0\x80",
    "dup_nested_keys": b"\xa2\x01\x00\x01\x00",
    "nested_map_float_key": b"\xa1\xf9\x3c\x00\x00",
}


def _frames():
    out = {name: _sync_with(v) for name, v in CORPUS.items()}
    # many duplicate unknown top-level keys
    many = b"\xa8\x00\x01\x01\x45\x00\x75\x30\x0b\xb8" + b"\x14\x00" * 6
    out["dup_top_keys"] = encode_frame(BCAST, 0, 0x02, 7, many)
    # -2**30 (under the ignored key 9): outside the wire range (|n| < 2**30)
    out["int_minus_2_30"] = _sync_with(b"\x3a\x3f\xff\xff\xff")
    out["discover_bad_utf8"] = encode_frame(BCAST, 0, 0x01, 7, b"\xa1\x09\x62\xc3\x28")
    out["hold_too_deep"] = encode_frame(BCAST, 0, 0x06, 7, b"\xa1\x09" + b"\x81" * 8 + b"\x80")
    out["heartbeat_dup_keys"] = encode_frame(BCAST, 0, 0x03, 7, b"\xa3\x00\x01\x14\x00\x14\x00")
    # issue 14 audit: the hold marker is exactly 80 00 00 00 00 in every entry, not only in the
    # segment's own (the host's decoder refuses the whole frame); resume is false/true/0/1 only
    entries = b"\x00\x75\x30\x0b\xb8" + b"\x80\x00\x00\x00\x01"  # ours, then a bad hold
    out["other_entry_bad_hold"] = encode_frame(BCAST, 0, 0x02, 7, b"\xa2\x00\x01\x01\x4a" + entries)
    out["resume_2"] = encode_frame(BCAST, 0, 0x02, 7, _HEAD + b"\x02\x02")  # {..., 2: 2}
    return out


FRAMES = _frames()


@pytest.mark.parametrize("name", sorted(FRAMES))
def test_invalid_content_anywhere_is_malformed_and_nothing_runs(vm, name):
    frame = FRAMES[name].hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
vmkit.run(hal, seg, 30)
hal.up.discard()
hal.up.feed(bytes.fromhex('{frame}'))
vmkit.run(hal, seg, 200)
R['s'] = [seg.armed, seg.hold, seg.wd_armed, seg.mc.tx, seg.dropped, vmkit.hexs(hal.up.take())]
"""
    )
    armed, hold, wd_armed, tx, dropped, out = r["s"]
    msgs = decode(out)
    errs = [m for m in msgs if m["type"] == "ERROR"]
    assert len(errs) == 1 and errs[0]["name"] == "MALFORMED", (name, msgs)
    assert not [m for m in msgs if m["type"] in ("STATE", "DESCRIPTOR")], name
    assert not armed and not hold and not wd_armed and tx == 0 and dropped == 1, name


_BIG = {
    "minus_2_30": b"\x3a\x3f\xff\xff\xff",
    "plus_2_30": b"\x1a\x40\x00\x00\x00",
    "uint64": b"\x1b\x00\x00\x00\x01\x00\x00\x00\x00",
    "nint64": b"\x3b\x00\x00\x00\x01\x00\x00\x00\x00",
}
_SLOW = {}
for _n, _b in _BIG.items():
    # CLEAR_FAULT {9: big}; PARAM_SET {0: 2 (kappa_rate_max), 1: 1.0, 9: big};
    # PARAM_GET {0: 2, 9: big}; PARAM_SET {0: 0 (watchdog_ms), 1: big}
    _SLOW["clear_fault_" + _n] = encode_frame(BCAST, 0, 0x08, 7, b"\xa1\x09" + _b)
    _SLOW["param_set_" + _n] = encode_frame(0, 0, 0x05, 7, b"\xa3\x00\x02\x01\xf9\x3c\x00\x09" + _b)
    _SLOW["param_get_" + _n] = encode_frame(0, 0, 0x04, 7, b"\xa2\x00\x02\x09" + _b)
    _SLOW["param_set_value_" + _n] = encode_frame(0, 0, 0x05, 7, b"\xa2\x00\x00\x01" + _b)


@pytest.mark.parametrize("name", sorted(_SLOW))
def test_slow_path_ints_outside_the_wire_range_are_malformed_and_nothing_runs(vm, name):
    """PARAM_GET/SET and CLEAR_FAULT decode with cbor.loads: as strict as the in-place reader
    (|n| < 2**30, no 8-byte ints), even under a key the segment ignores."""
    frame = _SLOW[name].hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
vmkit.run(hal, seg, 30)
hal.up.discard()
seg.fault_code = 1  # CLEAR_FAULT would clear it
before = [seg.rate_max_si, seg.watchdog_ms]
hal.up.feed(bytes.fromhex('{frame}'))
vmkit.run(hal, seg, 50)
R['s'] = [seg.fault_code, seg.dropped, before, [seg.rate_max_si, seg.watchdog_ms],
          vmkit.hexs(hal.up.take())]
"""
    )
    fault, dropped, before, after, out = r["s"]
    msgs = [m for m in decode(out) if m["type"] not in ("STATE", "EVENT")]
    assert [(m["type"], m["name"]) for m in msgs] == [("ERROR", "MALFORMED")], (name, msgs)
    assert fault == 1 and dropped == 1 and after == before, name


def test_valid_unknown_content_is_still_ignored(vm):
    """The same keys with valid content (8 levels, good UTF-8, distinct keys) are accepted."""
    ok = _sync_with(b"\xa2\x01\x81" + b"\x81" * 5 + b"\x80" + b"\x62\xc3\xa9\x00").hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
hal.up.feed(bytes.fromhex('{ok}'))
vmkit.run(hal, seg, 30)
R['s'] = [seg.armed, seg.mc.tx, vmkit.hexs(hal.up.take())]
"""
    )
    armed, tx, out = r["s"]
    assert armed and abs(tx - 30000 * math.cos(0.3)) <= 3
    assert not [m for m in decode(out) if m["type"] == "ERROR"]


def test_micropython_cbor_decoder_rejects_invalid_utf8_like_cbor2(vm):
    cases = ["62c328", "62c0af", "63eda080", "64f4908080", "61ff", "62e282"]
    good = ["62c3a9", "63e282ac", "64f09f9880", "6161"]
    r = vm(
        f"""
from protocol import cbor
def ok(h):
    try:
        cbor.loads(bytes.fromhex(h))
        return True
    except ValueError:
        return False
R['bad'] = [ok(h) for h in {cases!r}]
R['good'] = [ok(h) for h in {good!r}]
"""
    )
    assert r["bad"] == [False] * len(cases)
    assert r["good"] == [True] * len(good)


def test_limit_clamped_events_are_at_least_100_ms_apart_on_the_wire(vm):
    """Other events queued at the same time delay the first LIMIT_CLAMPED; the spacing must be
    measured where it counts, between the events actually sent."""
    over = M.encode_sync(1, 1, [(50.0, 0.0)]).hex()  # beyond kappa_max: clamped every cycle
    alive_from_down = M.encode_alive(0).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
vmkit.run(hal, seg, 5)
seg.event(3, 0)   # two events already waiting (e.g. a watchdog trip and a servo fault report)
seg.event(5, 1)
hal.down.feed(bytes.fromhex('{alive_from_down}'))   # and a DOWNSTREAM_UP on its way
from protocol.frame import FrameReader
from protocol import cobs
rd = FrameReader()
ev = []
for _ in range(100):
    hal.up.feed(bytes.fromhex('{over}'))
    hal.down.feed(bytes.fromhex('{alive_from_down}'))
    vmkit.run(hal, seg, 10)
    for f in rd.feed(hal.up.take()):
        if f.mtype == 0x85:
            ev.append(vmkit.hexs(cobs.encode(f.raw()) + bytes(1)))
R['out'] = ev
"""
    )
    msgs = decode("".join(r["out"]))
    t = [m["t_ms"] for m in msgs if m["type"] == "EVENT" and m["name"] == "LIMIT_CLAMPED"]
    assert len(t) >= 5
    gaps = [b - a for a, b in zip(t, t[1:], strict=False)]
    assert min(gaps) >= 100, gaps


def test_state_names_the_position_whose_setpoint_was_applied(vm):
    """A broadcast SYNC that reaches the first segment with hop 1 (a corrupted or misrouted
    header) applies entry 1: STATE says so (key 9) while the reply's hop says position 0."""
    f = decode_frame(M.encode_sync(1, 1, [(1.0, 0.0), (3.0, 1.0)]))
    wrong = encode_frame(f.flags, 1, f.mtype, f.seq, bytes(f.payload)).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
hal.up.feed(bytes.fromhex('{wrong}'))
vmkit.run(hal, seg, 10)
R['s'] = [seg.mc.tx, vmkit.hexs(hal.up.take())]
"""
    )
    tx, out = r["s"]
    assert abs(tx - 30000 * math.cos(1.0)) <= 3  # it applied entry 1 (3 1/m), not entry 0
    st = [m for m in decode(out) if m["type"] == "STATE"]
    assert st and st[0]["position"] == 0 and st[0]["applied_position"] == 1


def test_a_counter_past_the_wire_range_is_reported_modulo_2_30(vm):
    """Defect (review): frames_ok is never reset; past 2**30 (~12 days at 1000 frames/s) its
    PARAM_VALUE carried an int the host's decoder (now strict, |n| < 2**30) refuses, so every
    PARAM_GET of it failed. Counters are now reported modulo 2**30; the array counter wraps
    negative at 2**31, which the same mask keeps consistent."""
    get = encode_frame(0, 0, 0x04, 7, b"\xa1\x00\x06").hex()  # PARAM_GET frames_ok
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 60000}})
vmkit.run(hal, seg, 5)
out = []
for ok in (2**30 + 5, -(2**31) + 7):
    seg.rd_up.st[3] = ok  # protocol.frame _OK
    seg.rd_dn.st[3] = 0
    hal.up.discard()
    hal.up.feed(bytes.fromhex('{get}'))
    vmkit.run(hal, seg, 5)
    out.append(vmkit.hexs(hal.up.take()))
R['s'] = out
"""
    )
    values = []
    for out in r["s"]:
        msgs = [m for m in decode(out) if m["type"] == "PARAM_VALUE"]
        assert len(msgs) == 1, decode(out)
        values.append(msgs[0]["value"])
    # (+1 each: the PARAM_GET frame itself was counted before the reply)
    assert values == [6, (-(2**31) + 8) & (2**30 - 1)]


@pytest.mark.parametrize("name", ["other_entry_bad_hold", "resume_2"])
def test_the_general_sync_decoder_is_as_strict_as_the_machine_code_one(name):
    """protocol.device.decode_sync without the viper step (CPython here; a port without the
    emitter, or an encoding the step leaves to it): the same frames are MALFORMED for every
    position, not only for the one whose entry is bad."""
    from protocol import device as D

    payload = bytearray(decode_frame(FRAMES[name]).payload)
    assert D._sync_entry is None  # CPython: the general decoder decides
    for position in (0, 1, 2):
        out = [0, 0, 0, 0]
        assert D.decode_sync(payload, 0, len(payload), position, out) == D.MALFORMED, position
    ok = bytearray(_HEAD[:1].replace(b"\xa3", b"\xa2") + _HEAD[1:])  # {0: 1, 1: (3, 0.3)}
    assert D.decode_sync(ok, 0, len(ok), 0, [0, 0, 0, 0]) == D.OK
