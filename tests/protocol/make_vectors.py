"""Regenerate protocol/vectors/vectors.jsonl from the current implementation (CPython).

Run ``.venv/bin/python tests/protocol/make_vectors.py`` after a deliberate wire change only: the
vectors pin the exact bytes, and tests/protocol/test_vectors.py checks them on both interpreters.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
sys.path[:0] = [str(REPO), str(HERE)]

import mp_runner  # noqa: E402

OUT = REPO / "protocol" / "vectors" / "vectors.jsonl"

DESC = {
    "uid": "24a1600c3b5e",
    "fw_version": "0.1.0",
    "protocol_version": 2,
    "model": "pcc",
    "length": 0.12,
    "tendon_angles": [0.0, 2.0943951023931953, 4.1887902047863905],
    "tendon_radius": 0.012,
    "spool_radius": 0.01,
    "kappa_max": 20.0,
    "kappa_rate_max": 40.0,
    "mass": 0.085,
    "backbone_radius": 0.0015,
    "name": "seg_0",
    "servo_driver": "pwm",
    "watchdog_ms": 200,
    "downstream_present": True,
}

# (name, description, call, args, kwargs, extra)
SPECS = [
    (
        "crc_check",
        "CRC-16/CCITT-FALSE check value over ASCII 123456789",
        "crc16",
        ["313233343536373839"],
        {},
        {},
    ),
    ("cobs_basic", "COBS of 11 22 00 33", "cobs.encode", ["11220033"], {}, {}),
    ("cobs_zeros", "COBS of 00 00", "cobs.encode", ["0000"], {}, {}),
    (
        "cbor_small",
        "canonical CBOR of a mixed map",
        "cbor.dumps",
        [{"a": [1, -1, 23, 24, 255, 256, 65535, 65536], "b": True}],
        {},
        {},
    ),
    (
        "cbor_floats",
        "shortest exact floats: half, single, double",
        "cbor.dumps",
        [[1.5, 0.1, 1e-7, 65504.0, -0.0, 3.4028234663852886e38, 0.5]],
        {},
        {},
    ),
    ("discover", "DISCOVER broadcast, seq 1", "encode_discover", [1], {}, {}),
    (
        "sync_1",
        "SYNC cycle 1000, one segment kappa 2.5 1/m phi 0.7854 rad",
        "encode_sync",
        [10, 1000, [[2.5, 0.7854]]],
        {},
        {"positions": [0, 1]},
    ),
    (
        "sync_3",
        "SYNC for 3 segments, middle one holds",
        "encode_sync",
        [11, 1001, [[1.0, 0.0], None, [12.5, -1.5708]]],
        {},
        {"positions": [0, 1, 2, 3]},
    ),
    (
        "sync_8",
        "SYNC for 8 segments",
        "encode_sync",
        [12, 123456, [[0.5 * i, round(-3.0 + 0.8 * i, 4)] for i in range(8)]],
        {},
        {"positions": [0, 3, 7, 8]},
    ),
    (
        "sync_resume",
        "SYNC with resume (ends HOLD), phi 3.5 rad wrapped to (-pi, pi]",
        "encode_sync",
        [13, 7, [[4.0, 3.5]]],
        {"resume": True},
        {"positions": [0]},
    ),
    ("heartbeat", "HEARTBEAT cycle 1002", "encode_heartbeat", [14, 1002], {}, {}),
    (
        "param_get",
        "PARAM_GET param 3 at position 2 with uid check",
        "encode_param_get",
        [15, 2, 3],
        {"uid": "24a1600c3b5e"},
        {},
    ),
    (
        "param_set_float",
        "PARAM_SET param 4 = 18.5 (SI float) at position 0",
        "encode_param_set",
        [16, 0, 4, 18.5],
        {},
        {},
    ),
    (
        "param_set_int",
        "PARAM_SET param 5 = 250 at position 1",
        "encode_param_set",
        [17, 1, 5, 250],
        {},
        {},
    ),
    ("hold_all", "HOLD broadcast", "encode_hold", [18], {}, {}),
    ("hold_one", "HOLD addressed to position 1", "encode_hold", [19, 1], {}, {}),
    ("alive", "ALIVE (LOCAL, to the upstream neighbour)", "encode_alive", [20], {}, {}),
    ("clear_fault_all", "CLEAR_FAULT broadcast", "encode_clear_fault", [22], {}, {}),
    (
        "clear_fault_one",
        "CLEAR_FAULT addressed to position 2, identity checked",
        "encode_clear_fault",
        [23, 2, "24a1600c3b5e"],
        {},
        {},
    ),
    ("descriptor", "DESCRIPTOR of a 3-tendon PCC segment", "encode_descriptor", [DESC, 1], {}, {}),
    (
        "calibrate_persist",
        "CALIBRATE persist at position 1: zero offsets 0.12, -0.08, 0.05 rad, servo 1 reversed",
        "encode_calibrate",
        [24, 1, 2, [0.12, -0.08, 0.05], [1, -1, 1], "24a1600c3b5e"],
        {},
        {},
    ),
    ("calibrate_read", "CALIBRATE read at position 0", "encode_calibrate", [25, 0, 0], {}, {}),
    (
        "calibration",
        "CALIBRATION answer: the stored calibration and the configuration hash",
        "encode_calibration",
        [24, [0.12, -0.08, 0.05], [1, -1, 1], True, 0x1234567],
        {},
        {},
    ),
    (
        "config_hash",
        "configuration hash of a 3-tendon segment (FNV-1a 30 bit over the canonical text)",
        "config_hash",
        [
            {
                "length": 0.316,
                "tendon_angles": [0.0, 2.0943951023931953, 4.1887902047863905],
                "tendon_radius": 0.06,
                "spool_radius": 0.025,
                "kappa_max": 3.313916301255056,
                "kappa_rate_max": 5.0,
                "servo_driver": "feetech_sts",
                "servos": [
                    {"id": 1, "zero_offset": 0.12, "direction": 1},
                    {"id": 2, "zero_offset": -0.08, "direction": -1},
                    {"id": 3, "zero_offset": 0.05, "direction": 1},
                ],
            }
        ],
        {},
        {},
    ),
    (
        "config_hash_safety",
        "configuration hash with the safety keys off their defaults (hashed after the servos)",
        "config_hash",
        [
            {
                "length": 0.316,
                "tendon_angles": [0.0, 2.0943951023931953, 4.1887902047863905],
                "tendon_radius": 0.06,
                "spool_radius": 0.025,
                "kappa_max": 3.313916301255056,
                "servo_driver": "pwm",
                "watchdog_ms": 150,
                "tick_ms": 10,
                "hw_watchdog_ms": 2000,
                "fault_action": "release",
            }
        ],
        {},
        {},
    ),
    (
        "state_3t",
        "STATE of a segment with 3 servos",
        "encode_state",
        [10],
        {
            "cycle": 1000,
            "t_ms": 123456,
            "kappa": 2.5,
            "phi": 0.7854,
            "servo_angles": [-0.35, 0.21, 0.14],
            "status": ["DOWNSTREAM"],
            "applied_position": 0,
        },
        {},
    ),
    (
        "state_device",
        "STATE built by the zero-allocation device encoder (wire ints)",
        "device.state_frame",
        [
            10,
            1000,
            123456,
            25000,
            7854,
            [-3500, 2100, 1400],
            3,
            16,
            2,
        ],
        {},
        {},
    ),
    ("param_value", "PARAM_VALUE param 4 = 18.5", "encode_param_value", [16, 4, 18.5], {}, {}),
    (
        "event_clamped",
        "EVENT LIMIT_CLAMPED detail kappa|rate at t 5000 ms",
        "encode_event",
        [0, 6, 3, 5000],
        {},
        {},
    ),
    (
        "event_fault",
        "EVENT FAULT (tick exception) with its reason in key 3",
        "encode_event",
        [0, 8, 1, 5000],
        {"text": "tick: ZeroDivisionError"},
        {},
    ),
    (
        "event_device",
        "EVENT DOWNSTREAM_DOWN by the device encoder",
        "device.event_frame",
        [1, 2, 0, 777],
        {},
        {},
    ),
    ("alive_device", "ALIVE by the device encoder", "device.alive_frame", [21], {}, {}),
    (
        "error_unknown_type",
        "ERROR UNKNOWN_TYPE answering type 0x42",
        "encode_error",
        [9, 1, 0x42, "unknown type"],
        {},
        {},
    ),
    (
        "error_version",
        "ERROR UNSUPPORTED_VERSION with the supported range",
        "encode_version_error",
        [9, 0x02],
        {},
        {},
    ),
    (
        "forward_up",
        "STATE forwarded one hop upstream (hop 0 -> 1, CRC recomputed)",
        "forward",
        [None, 1],
        {},
        {},
    ),
    (
        "bad_nan",
        "SYNC with a NaN kappa is refused",
        "encode_sync",
        [1, 1, [[{"$float": "nan"}, 0.0]]],
        {},
        {},
    ),
    (
        "bad_range",
        "SYNC with kappa beyond the int24 wire range (838.8607 1/m) is refused",
        "encode_sync",
        [1, 1, [[839.0, 0.0]]],
        {},
        {},
    ),
    (
        "dec_unknown_type",
        "frame of unknown type 0x42",
        "decode",
        [None],
        {},
        {"frame": (0, 0, 0x42, 1, b"\xa0")},
    ),
    (
        "dec_bad_version",
        "frame of protocol version 1 (the version before the packed SYNC and STATE)",
        "decode",
        [None],
        {},
        {"frame": (0x02, 0, 0x02, 1, b"\xa0"), "ver": 1},
    ),
    (
        "dec_malformed",
        "SYNC whose payload is truncated CBOR",
        "decode",
        [None],
        {},
        {"frame": (0x02, 0, 0x02, 1, b"\xa2\x00\x01\x01\x45\x00\x00")},
    ),
    ("dec_bad_crc", "DISCOVER with a corrupted CRC byte", "decode", [None], {}, {"badcrc": True}),
    (
        "dec_unknown_key_too_deep",
        "SYNC whose unknown key 9 nests 9 lists (deeper than the limit of 8): malformed",
        "decode",
        [None],
        {},
        {
            "frame": (
                0x02,
                0,
                0x02,
                1,
                b"\xa3\x00\x01\x01\x45\x00\x00\x01\x00\x02\x09" + b"\x81" * 8 + b"\x80",
            )
        },
    ),
    (
        "dec_unknown_key_bad_utf8",
        "SYNC whose unknown key 9 carries text that is not UTF-8: malformed",
        "decode",
        [None],
        {},
        {"frame": (0x02, 0, 0x02, 1, b"\xa3\x00\x01\x01\x45\x00\x00\x01\x00\x02\x09\x62\xc3\x28")},
    ),
    (
        "dec_duplicate_unknown_keys",
        "SYNC with unknown key 20 twice: malformed",
        "decode",
        [None],
        {},
        {
            "frame": (
                0x02,
                0,
                0x02,
                1,
                b"\xa4\x00\x01\x01\x45\x00\x00\x01\x00\x02\x14\x00\x14\x01",
            )
        },
    ),
    (
        "dec_int_below_range",
        "SYNC whose cycle is -2**30 (outside the wire range): malformed",
        "decode",
        [None],
        {},
        {"frame": (0x02, 0, 0x02, 1, b"\xa2\x00\x3a\x3f\xff\xff\xff\x01\x40")},
    ),
]


def build() -> list[dict]:
    """Vector descriptions with the bytes and decoded forms produced by this implementation."""
    from protocol import frame as F

    out = []
    by_name: dict[str, dict] = {}
    for name, desc, call, args, kwargs, extra in SPECS:
        args = list(args)
        if call == "forward":
            args[0] = by_name["state_device"]["hex"]
        if call == "decode":
            if extra.get("badcrc"):
                w = bytearray(F.encode_frame(2, 0, 1, 1, {}))
                raw = bytearray(F.decode_frame(bytes(w)).raw())
                raw[-1] ^= 0x01
                from protocol import cobs

                args[0] = (cobs.encode(bytes(raw)) + b"\x00").hex()
            else:
                flags, hop, mtype, seq, payload = extra["frame"]
                args[0] = F.encode_frame(
                    flags, hop, mtype, seq, bytes(payload), extra.get("ver", 2)
                ).hex()
        v = {"name": name, "description": desc, "call": call, "args": args, "kwargs": kwargs}
        if "positions" in extra:
            v["positions"] = extra["positions"]
        res = mp_runner.run_vector(v)
        for k in ("hex", "decoded", "device", "error"):
            if k in res:
                v[k] = res[k]
        by_name[name] = v
        out.append(v)
    return out


def main() -> None:
    vectors = build()
    with OUT.open("w") as f:
        for v in vectors:
            f.write(json.dumps(v, sort_keys=True) + "\n")
    print(f"wrote {len(vectors)} vectors to {OUT.relative_to(REPO)}")


if __name__ == "__main__":
    main()
