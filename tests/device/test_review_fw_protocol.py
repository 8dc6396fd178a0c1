"""Firmware review (protocol defects), on the MicroPython VM against the precompiled firmware:

1. CALIBRATE apply/persist must list exactly one zero offset and one direction per servo of the
   segment (empty lists ran into an IndexError that became FAULT FRAME_EXCEPTION and lost the
   frames behind it); any exception of the calibration slow path is answered with ERROR, never a
   FAULT.
2. A name too long for the DESCRIPTOR frame is refused by the firmware's configuration rules, so
   by ``ucr check`` and ``ucr flash`` too (path:line: message); every accepted configuration's
   DESCRIPTOR fits a frame, even with a config_error.
3. PARAM_GET/SET (and CBOR ``loads`` on both runtimes) refuse map keys that are not ints / not
   int, text or bytes: ERROR MALFORMED, nothing executed.
"""

from __future__ import annotations

import math

import cbor2
import pytest

from protocol import cbor
from protocol import messages as M
from protocol.errors import MalformedError
from protocol.frame import encode_frame
from tests.device.conftest import decode

RUNNER = """
from main import Runner
def loop(hal, r, ms):
    end = hal.t + ms
    while hal.t < end:
        hal.t += 5
        r.once()
"""


def _calibrate(action: int, zeros, dirs) -> str:
    return encode_frame(0, 0, 0x09, 3, {0: 1, 1: action, 2: zeros, 3: dirs}).hex()


def _not_state(out: str) -> list[dict]:
    return [m for m in decode(out) if m["type"] not in ("STATE", "ALIVE", "EVENT")]


# -- 1. CALIBRATE list lengths --------------------------------------------------------------------
@pytest.mark.parametrize(
    "action, zeros, dirs",
    [
        (1, [], []),  # apply, empty lists
        (2, [], []),  # persist, empty lists
        (1, [0.0, 0.0], [1, 1]),  # two of three servos
        (2, [0.0] * 4, [1] * 4),  # four of three
    ],
)
def test_calibrate_needs_one_value_per_servo_and_never_faults(vm, action, zeros, dirs):
    cal = _calibrate(action, zeros, dirs)
    get = M.encode_param_get(4, 0, 10).hex()  # in the same read, right behind it
    r = vm(
        RUNNER
        + f"""
import os
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
r = Runner(hal, seg, 5)
hal.up.feed(bytes.fromhex('{M.encode_hold(2).hex()}'))
loop(hal, r, 20)
hal.up.take()
zero0 = list(seg.cfg.zero)
hal.up.feed(bytes.fromhex('{cal}' + '{get}'))
loop(hal, r, 100)
R['out'] = vmkit.hexs(hal.up.take())
R['fault'] = [seg.fault_code, seg.fault_count]
R['same'] = list(seg.cfg.zero) == zero0
R['stored'] = 'calibration.json' in os.listdir()
"""
    )
    assert r["fault"] == [0, 0], r["fault"]
    msgs = _not_state(r["out"])
    assert [m["type"] for m in msgs] == ["ERROR", "PARAM_VALUE"], msgs
    assert msgs[0]["name"] == "BAD_VALUE" and "3 servos" in msgs[0]["text"], msgs[0]
    assert msgs[1]["value"] == "00aa11bb22cc"
    assert r["same"] and not r["stored"]


def test_calibrate_with_one_value_per_servo_still_applies(vm):
    cal = _calibrate(1, [0.01, -0.02, 0.03], [1, -1, 1])
    r = vm(
        f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
hal.up.feed(bytes.fromhex('{M.encode_hold(2).hex()}'))
vmkit.run(hal, seg, 20)
hal.up.take()
hal.up.feed(bytes.fromhex('{cal}'))
vmkit.run(hal, seg, 50)
R['out'] = vmkit.hexs(hal.up.take())
R['zero'] = list(seg.cfg.zero)
R['fault'] = seg.fault_code
"""
    )
    msgs = _not_state(r["out"])
    assert [m["type"] for m in msgs] == ["CALIBRATION"], msgs
    assert r["zero"] == [100, -200, 300] and r["fault"] == 0


def test_calibrate_any_exception_is_an_error_reply_not_a_fault(vm):
    """Whatever the slow path raises (here an IndexError planted in its action) is answered
    ERROR BAD_VALUE; the segment stays out of FAULT and the next frame is answered."""
    cal = _calibrate(1, [0.0] * 3, [1] * 3)
    read = encode_frame(0, 0, 0x09, 2, {0: 1, 1: 0}).hex()
    get = M.encode_param_get(4, 0, 10).hex()
    r = vm(
        RUNNER
        + f"""
hal, seg = vmkit.make({{'watchdog_ms': 10000}})
r = Runner(hal, seg, 5)
hal.up.feed(bytes.fromhex('{M.encode_hold(2).hex()}' + '{read}'))
loop(hal, r, 20)
import calib  # loaded by the segment for the read
def boom(*a):
    return [][1]
calib._act = boom
hal.up.take()
hal.up.feed(bytes.fromhex('{cal}' + '{get}'))
loop(hal, r, 100)
R['out'] = vmkit.hexs(hal.up.take())
R['fault'] = [seg.fault_code, seg.fault_count]
"""
    )
    assert r["fault"] == [0, 0], r["fault"]
    msgs = _not_state(r["out"])
    assert [(m["type"], m.get("name")) for m in msgs] == [
        ("ERROR", "BAD_VALUE"),
        ("PARAM_VALUE", None),
    ], msgs


# -- 2. names the DESCRIPTOR cannot carry ---------------------------------------------------------
def _angles(n: int) -> list[float]:
    return [2 * math.pi * i / n + 0.1 for i in range(n)]  # float64 on the wire: the worst case


def _name_limit(n: int, driver: str) -> int:
    """The longest name the firmware accepts (host run of device/config.py's rule)."""
    from ucrdf.checks import firmware_refusal

    lo, hi = 1, 300
    while lo < hi:
        mid = (lo + hi + 1) // 2
        cfg = {"name": "s" * mid, "tendon_angles": _angles(n), "servo_driver": driver}
        if firmware_refusal(cfg) is None:
            lo = mid
        else:
            hi = mid - 1
    return lo


def test_firmware_refuses_a_name_whose_descriptor_does_not_fit(vm):
    long = "segment_" + "x" * 150
    r = vm(
        f"""
import config
try:
    config.Config({{'name': {long!r}}}, 'emulated')
    R['why'] = None
except ValueError as e:
    R['why'] = str(e)
import sys
R['loaded'] = [m for m in sys.modules if 'desc_room' in m]
"""
    )
    assert r["why"] == (
        "name of 158 bytes too long for the DESCRIPTOR frame: at most 70 with 3 tendons and "
        "servo_driver emulated"
    ), r
    assert not r["loaded"], r  # the rule's module is dropped after use (boot heap)


@pytest.mark.parametrize("n, driver", [(3, "emulated"), (3, "feetech_sts"), (8, "feetech_sts")])
def test_every_accepted_name_gets_a_descriptor_that_fits_even_with_a_config_error(vm, n, driver):
    """At the limit (the longest name accepted), with every float needing float64 and a
    config_error set (a servo driver that failed at boot), DISCOVER is answered with a DESCRIPTOR
    that decodes; one byte more and the configuration is refused."""
    limit = _name_limit(n, driver)
    assert limit >= (20 if n == 8 else 60), limit
    name = "é" + "s" * (limit - 2)  # 2 bytes of UTF-8 first: the rule counts bytes
    cfg = {
        "name": name,
        "tendon_angles": _angles(n),
        "servo_driver": driver,
        "length": 0.3161,
        "tendon_radius": 0.0501,
        "spool_radius": 0.0201,
        "mass": 0.3001,
        "backbone_radius": 0.0031,
        "kappa_max": 3.3139,
        "kappa_rate_max": 4.9991,
        "watchdog_ms": 60000,
    }
    disc = M.encode_discover(1).hex()
    r = vm(
        f"""
import gc, config
cfg = {cfg!r}
longer = dict(cfg, name=cfg['name'] + 's')
try:
    config.Config(longer, 'emulated')
    R['longer'] = None
except ValueError as e:
    R['longer'] = str(e)
del longer
gc.collect()
# main.build's order and its answer to a servo driver that fails (no servo UART here)
hal = vmkit.LoopHal()
c = config.Config(cfg, 'emulated')
gc.collect()
import servos
from segment import Segment
gc.collect()
try:
    bus = servos.make(c.driver, c, hal)
except Exception as e:
    bus = servos.OfflineBus(c.n, str(e))
c.error = 'servo driver %s failed: ' % c.driver + 'e' * 100
seg = Segment(hal, c, bus, 5)
hal.up.take()
hal.up.feed(bytes.fromhex('{disc}'))
vmkit.run(hal, seg, 10)
R['out'] = vmkit.hexs(hal.up.take())
"""
    )
    msgs = [m for m in decode(r["out"]) if m["type"] != "STATE"]
    descs = [m for m in msgs if m["type"] == "DESCRIPTOR"]
    assert len(descs) == 1, msgs
    assert descs[0]["name"] == name
    sent = descs[0]["config_error"]  # cut to the room the name leaves: 16 bytes at least
    assert 16 <= len(sent) <= 40 and f"servo driver {driver} failed: {'e' * 100}".startswith(sent)
    assert r["longer"] is not None and "DESCRIPTOR" in r["longer"]
    # the host's worst case (float64 everywhere, the longest config_error sent) fits too
    from protocol.constants import MAX_PAYLOAD

    worst = {k: descs[0][k] for k in M.DESCRIPTOR_KEYS}
    worst["config_hash"] = 2**30 - 1
    for k in ("length", "tendon_radius", "spool_radius", "kappa_max", "kappa_rate_max", "mass"):
        worst[k] = 0.1 + 1e-9
    worst["backbone_radius"] = 0.1 + 1e-9
    worst["tendon_angles"] = [0.1 + 1e-9] * n
    worst["uid"] = "0123456789ab"
    assert len(M.dumps(M.descriptor_payload(worst))) <= MAX_PAYLOAD


def test_the_descriptor_rule_uses_the_frame_limit():
    from protocol import constants, desc_room

    assert desc_room._MAX_PAYLOAD == constants.MAX_PAYLOAD


def _long_name_robot(tmp_path, length: int):
    from tests.ucrdf_format.conftest import ROBOTS

    name = "segment_" + "x" * (length - 8)
    text = (ROBOTS / "softrobot3.ucrdf").read_text().replace("segment_1", name)
    path = tmp_path / "longname.ucrdf"
    path.write_text(text)
    line = next(i for i, t in enumerate(text.splitlines(), 1) if f'<bendable name="{name}"' in t)
    return path, name, line


def test_ucr_check_and_flash_refuse_the_long_name_with_path_line(tmp_path):
    from tests.cli_run import run_ucr
    from tools.segment_config import SegmentConfigError, config_for
    from ucrdf.parser import load

    path, name, line = _long_name_robot(tmp_path, 108)
    res = run_ucr("check", str(path))
    assert res.returncode != 0
    want = f"{path}:{line}: bendable {name!r}: the segment firmware would refuse"
    assert want in res.stderr + res.stdout, res.stderr + res.stdout
    assert "too long for the DESCRIPTOR frame" in res.stderr + res.stdout
    assert "at most 70 with 3 tendons" in res.stderr + res.stdout
    res = run_ucr("flash", "--port", "/dev/null", "--robot", str(path), "--segment", name)
    assert res.returncode != 0 and "too long for the DESCRIPTOR frame" in res.stderr, res.stderr
    # the configuration generator refuses it on its own too (what `ucr flash` writes)
    with pytest.raises(
        SegmentConfigError, match=f"^{path}:{line}: .*too long for the DESCRIPTOR frame"
    ):
        config_for(load(path, check=False), name)
    ok, _, _ = _long_name_robot(tmp_path, 70)
    assert run_ucr("check", str(ok)).returncode == 0


# -- 3. map keys ----------------------------------------------------------------------------------
NON_INT_KEYS = {
    "bool": cbor2.dumps({False: 0, True: 5000}),
    "float": bytes.fromhex("a2f9000000f93c00191b58"),  # {0.0: 0, 1.0: 7000}
    "null": bytes.fromhex("a3 00 00 01 191b58 f6 191b58"),  # {0: 0, 1: 7000, null: 7000}
    "text": cbor2.dumps({0: 0, "1": 7000, 1: 7000}),
}


@pytest.mark.parametrize("name", sorted(NON_INT_KEYS))
@pytest.mark.parametrize("mtype", [0x04, 0x05])
def test_param_request_with_non_int_keys_is_malformed_and_not_executed(vm, name, mtype):
    frame = encode_frame(0, 0, mtype, 9, NON_INT_KEYS[name]).hex()
    r = vm(
        f"""
hal, seg = vmkit.make({{}})
hal.up.take()
before = [seg.watchdog_ms, seg.dropped]
hal.up.feed(bytes.fromhex('{frame}'))
vmkit.run(hal, seg, 10)
R['out'] = vmkit.hexs(hal.up.take())
R['s'] = before + [seg.watchdog_ms, seg.dropped]
"""
    )
    msgs = [m for m in decode(r["out"]) if m["type"] != "STATE"]
    assert [(m["type"], m.get("name")) for m in msgs] == [("ERROR", "MALFORMED")], msgs
    assert r["s"] == [200, 0, 200, 1], r["s"]


@pytest.mark.parametrize(
    "data",
    [
        b"\xa1\xf4\x00",  # {false: 0}
        b"\xa1\xf6\x00",  # {null: 0}
        b"\xa1\xf9\x3c\x00\x00",  # {1.0: 0}
        b"\xa1\x00\xa1\xf5\x00",  # {0: {true: 0}} (nested)
    ],
)
def test_loads_accepts_only_int_text_or_bytes_keys(data):
    with pytest.raises(MalformedError):
        cbor.loads(data)
    assert cbor.loads(b"\xa3\x00\x00\x61\x61\x00\x41\x62\x00") == {0: 0, "a": 0, b"b": 0}
