"""Message builders/parsers: SI round trips, cbor2 agreement, validation, device/host agreement."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import calibration as CAL
from protocol import cbor
from protocol import device as D
from protocol import messages as M
from protocol.constants import (
    ERR_BAD_VALUE,
    ERR_MALFORMED,
    ERR_UNKNOWN_TYPE,
    ERR_UNSUPPORTED_VERSION,
    FLAG_BCAST,
    FLAG_LOCAL,
    FLAG_UP,
    HEADER_LEN,
    MAX_ENCODED,
    MAX_FRAME,
    T_STATE,
    T_SYNC,
)
from protocol.errors import (
    BadValueError,
    MalformedError,
    ProtocolError,
    UnknownTypeError,
    UnsupportedVersionError,
)
from protocol.frame import Frame, decode_frame

kappas = st.floats(-100, 100, allow_nan=False)
phis = st.floats(-20, 20, allow_nan=False)
setpoint = st.none() | st.tuples(kappas, phis)
seqs = st.integers(0, 255)
cycles = st.integers(0, 2**30 - 1)

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
    "downstream_present": False,
}


def _msg(wire: bytes) -> dict:
    return M.decode_message(decode_frame(wire))


def _every_message() -> list[bytes]:
    """One frame of every message type (with floats, text and nulls)."""
    return [
        M.encode_discover(1),
        M.encode_sync(2, 3, [(1.0, 0.5), None, (40.0, -3.0)], resume=True),
        M.encode_heartbeat(3, 4),
        M.encode_param_get(4, 2, 7, uid="abc"),
        M.encode_param_set(5, 1, 7, 0.1),
        M.encode_param_set(5, 1, 8, "text"),
        M.encode_hold(6),
        M.encode_hold(6, 2),
        M.encode_clear_fault(6),
        M.encode_alive(7),
        M.encode_descriptor(DESC, 8),
        M.encode_state(9, cycle=1, t_ms=2, kappa=3.0, phi=1.0, servo_angles=[0.1], status=3),
        M.encode_param_value(10, 7, 1e-9),
        M.encode_event(11, 5, 2, 100),
        M.encode_error(12, 1, 0x42, "unknown"),
        M.encode_version_error(13, 2),
        CAL.encode_calibrate(14, 1, CAL.ACTION_PERSIST, [0.1, -0.2, 0.0], [1, -1, 1], "abc"),
        CAL.encode_calibration(15, [0.1, -0.2, 0.0], [1, -1, 1], True, 123456),
    ]


def test_cbor2_and_own_codec_give_identical_frames_for_every_message() -> None:
    M.use_cbor2(False)
    try:
        own = _every_message()
    finally:
        M.use_cbor2(True)
    assert own == _every_message()
    for w in own:  # and cbor2 decodes every payload to what the own decoder reads
        import cbor2

        p = decode_frame(w).payload
        assert cbor2.loads(p) == cbor.loads(p)


def test_every_message_decodes_with_its_type_name() -> None:
    names = [_msg(w)["type"] for w in _every_message()]
    assert set(names) == set(M.TYPE_NAMES.values())


@settings(max_examples=300, deadline=None)
@given(seqs, cycles, st.lists(setpoint, max_size=8), st.booleans())
def test_sync_round_trip_within_quantum(seq, cycle, sps, resume) -> None:
    wire = M.encode_sync(seq, cycle, sps, resume)
    assert len(wire) <= MAX_ENCODED
    m = _msg(wire)
    assert m["cycle"] == cycle and m["seq"] == seq and m["resume"] == resume
    assert m["flags"] == FLAG_BCAST and m["hop"] == 0
    assert len(m["setpoints"]) == len(sps)
    for sent, got in zip(sps, m["setpoints"], strict=True):
        if sent is None:
            assert got is None
            continue
        assert abs(got[0] - sent[0]) <= 0.5e-4 + 1e-9
        assert -math.pi - 1e-4 < got[1] <= math.pi + 1e-4
        d = M.wrap_angle(got[1] - sent[1])  # same direction modulo 2 pi
        assert abs(d) <= 0.5e-4 + 1e-9


@settings(max_examples=300, deadline=None)
@given(cycles, st.lists(setpoint, max_size=8), st.booleans(), st.integers(0, 9))
def test_device_decode_sync_agrees_with_host_decoder(cycle, sps, resume, position) -> None:
    fr = decode_frame(M.encode_sync(0, cycle, sps, resume))
    raw = fr.raw()
    out = [0, 0, 0, 0]
    rc = D.decode_sync(raw, HEADER_LEN, len(raw) - 3, position, out)  # pad + CRC after it
    host = M.decode_sync(fr.payload)["setpoints"]
    if position < len(sps) and sps[position] is not None:
        assert rc == D.OK
        assert out[1] / 1e4 == host[position][0] and out[2] / 1e4 == host[position][1]
    else:
        assert rc == D.HOLD
    assert out[0] == cycle and out[3] == int(resume)


@settings(max_examples=300, deadline=None)
@given(
    st.integers(0, 2**30 - 1),
    st.integers(0, 2**30 - 1),
    st.integers(-0x7FFFFF, 0x7FFFFF),
    st.integers(-31415, 31415),  # a measured phi: inside (-pi, pi] once rounded
    st.lists(st.integers(-327670, 327670), max_size=8),
    st.integers(0, 63),
    st.integers(0, 255),
    seqs,
)
def test_device_state_encoder_matches_generic_encoder(
    cycle, t_ms, kappa, phi, servos, status, pos, seq
) -> None:
    raw = bytearray(MAX_FRAME)
    out = bytearray(MAX_ENCODED)
    n = D.state_frame(raw, out, seq, cycle, t_ms, kappa, phi, servos, len(servos), status, pos)
    # the device sends servo angles in 1e-3 rad, rounded half up from its 1e-4 rad ints
    angles = [((a + 5) // 10) / 1000 for a in servos]
    sent = M.encode_state(
        seq,
        cycle=cycle,
        t_ms=t_ms,
        kappa=kappa / 1e4,
        phi=phi / 1e4,
        servo_angles=angles,
        status=status,
        applied_position=pos,
    )
    assert bytes(out[:n]) == sent


@settings(max_examples=300, deadline=None)
@given(
    seqs,
    cycles,
    cycles,
    st.floats(0, 100),
    phis,
    st.lists(st.floats(-6, 6), max_size=6),
    st.integers(0, 63),
    st.integers(0, 255),
)
def test_state_round_trip_in_si(seq, cycle, t_ms, kappa, phi, angles, status, pos) -> None:
    m = _msg(
        M.encode_state(
            seq,
            cycle=cycle,
            t_ms=t_ms,
            kappa=kappa,
            phi=phi,
            servo_angles=angles,
            status=status,
            applied_position=pos,
        )
    )
    assert m["type"] == "STATE" and m["position"] == 0 and m["cycle"] == cycle
    assert m["t_ms"] == t_ms and m["raw_status"] == status and m["applied_position"] == pos
    assert abs(m["kappa"] - kappa) <= 0.5e-4 + 1e-9
    assert all(abs(a - b) <= 0.5e-3 + 1e-9 for a, b in zip(m["servo_angles"], angles, strict=True))
    assert abs(m["kx"] - kappa * math.cos(phi)) <= 1e-4 * (1 + kappa)
    assert abs(m["ky"] - kappa * math.sin(phi)) <= 1e-4 * (1 + kappa)
    assert M.status_bits(m["status"]) == status


def test_state_names_match_the_contract() -> None:
    m = M.decode_state(
        decode_frame(M.encode_state(0, cycle=1, t_ms=2, kappa=1.0, phi=0.0)).payload, position=3
    )
    assert set(m) == {
        "position",
        "applied_position",
        "cycle",
        "t_ms",
        "kappa",
        "phi",
        "kx",
        "ky",
        "servo_angles",
        "status",
        "raw_status",
    }
    assert m["position"] == 3 and m["status"] == set()


def test_descriptor_round_trip_with_contract_names() -> None:
    m = _msg(M.encode_descriptor(DESC, 4))
    for k, v in DESC.items():
        assert m[k] == v
    assert m["position"] == 0 and m["seq"] == 4


def test_descriptor_optional_fields_decode_as_none() -> None:
    minimal = {k: DESC[k] for k in ("uid", "fw_version", "protocol_version", "model")}
    m = _msg(M.encode_descriptor(minimal))
    assert m["length"] is None and m["downstream_present"] is None and m["uid"] == DESC["uid"]


@pytest.mark.parametrize(
    "desc",
    [
        {**DESC, "mass": math.nan},
        {**DESC, "lenght": 0.1},
        {k: v for k, v in DESC.items() if k != "uid"},
        {**DESC, "watchdog_ms": -1},
        {**DESC, "downstream_present": 1},
    ],
)
def test_descriptor_refuses_bad_fields(desc: dict) -> None:
    with pytest.raises(BadValueError):
        M.encode_descriptor(desc)


@settings(max_examples=200, deadline=None)
@given(
    seqs,
    st.integers(0, 255),
    st.integers(0, 2**30 - 1),
    st.integers(-(2**30) + 1, 2**30 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.booleans()
    | st.text(max_size=30),
    st.none() | st.text(max_size=12),
)
def test_params_round_trip(seq, position, pid, value, uid) -> None:
    m = _msg(M.encode_param_set(seq, position, pid, value, uid=uid))
    assert (m["hop"], m["flags"], m["param_id"], m["value"], m["uid"]) == (
        position,
        0,
        pid,
        value,
        uid,
    )
    m = _msg(M.encode_param_get(seq, position, pid, uid=uid))
    assert (m["param_id"], m["uid"]) == (pid, uid)
    m = _msg(M.encode_param_value(seq, pid, value))
    assert (m["param_id"], m["value"], m["position"]) == (pid, value, 0)


def test_event_and_error_round_trip() -> None:
    m = _msg(M.encode_event(1, 6, 3, 5000))
    assert (m["code"], m["name"], m["detail"], m["t_ms"]) == (6, "LIMIT_CLAMPED", 3, 5000)
    m = _msg(M.encode_error(2, 1, 0x42, "no such type"))
    assert (m["name"], m["offending_type"], m["text"], m["versions"]) == (
        "UNKNOWN_TYPE",
        0x42,
        "no such type",
        None,
    )
    m = _msg(M.encode_version_error(3, T_SYNC))
    assert m["code"] == ERR_UNSUPPORTED_VERSION and m["versions"] == (2, 2) and "2..2" in m["text"]
    assert _msg(M.encode_event(1, 99, 0, 0))["name"] == "UNKNOWN_99"


def test_hold_alive_addressing() -> None:
    assert decode_frame(M.encode_hold(1)).flags == FLAG_BCAST
    f = decode_frame(M.encode_hold(1, 4))
    assert (f.flags, f.hop) == (0, 4)
    f = decode_frame(M.encode_alive(1))
    assert f.flags == FLAG_UP | FLAG_LOCAL


@pytest.mark.parametrize(
    "call",
    [
        lambda: M.encode_sync(0, 0, [(math.nan, 0.0)]),
        lambda: M.encode_sync(0, 0, [(math.inf, 0.0)]),
        lambda: M.encode_sync(0, 0, [(1.0, math.inf)]),
        lambda: M.encode_sync(0, 0, [(2e5, 0.0)]),
        lambda: M.encode_sync(0, 0, [(838.861, 0.0)]),
        lambda: M.encode_sync(0, 0, [(1.0,)]),
        lambda: M.encode_sync(0, -1, []),
        lambda: M.encode_sync(0, 2**30, []),
        lambda: M.encode_sync(256, 0, []),
        lambda: M.encode_sync(0, 0, [("1", 0.0)]),
        lambda: M.encode_param_set(0, 0, 1, math.nan),
        lambda: M.encode_param_set(0, 0, 1, [1, 2]),
        lambda: M.encode_param_set(0, 0, 1, 2**31),
        lambda: M.encode_param_get(0, 256, 1),
        lambda: M.encode_state(0, cycle=0, t_ms=0, kappa=1.0, phi=0.0, status={"NOPE"}),
        lambda: M.encode_state(0, cycle=0, t_ms=0, kappa=1.0, phi=0.0, servo_angles=[33.0]),
        lambda: M.encode_state(0, cycle=0, t_ms=0, kappa=839.0, phi=0.0),
        lambda: M.encode_event(0, 1, 2**30, 0),
    ],
)
def test_builders_refuse_bad_values(call) -> None:
    with pytest.raises(BadValueError) as e:
        call()
    assert e.value.code == ERR_BAD_VALUE


def test_sync_too_long_for_a_frame_is_refused() -> None:
    with pytest.raises(ValueError):
        M.encode_sync(0, 0, [(99.0, 3.0)] * 60)


def test_phi_wraps_to_minus_pi_exclusive() -> None:
    assert M.wrap_angle(math.pi) == pytest.approx(math.pi)
    assert M.wrap_angle(-math.pi) == pytest.approx(math.pi)
    assert M.wrap_angle(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert M.phi_to_wire(-math.pi) == 31416


def test_decode_message_errors_carry_wire_codes() -> None:
    with pytest.raises(UnknownTypeError) as e:
        M.decode_message(Frame(2, 0, 0, 0x42, 0, b"\xa0"))
    assert e.value.code == ERR_UNKNOWN_TYPE
    with pytest.raises(UnsupportedVersionError) as e:
        M.decode_message(Frame(1, 0, 0, T_SYNC, 0, b"\xa0"))
    assert e.value.code == ERR_UNSUPPORTED_VERSION
    with pytest.raises(MalformedError) as e:
        M.decode_message(Frame(2, 0, 0, T_SYNC, 0, b"\xa1\x00\x01"))  # setpoints missing
    assert e.value.code == ERR_MALFORMED
    with pytest.raises(MalformedError):
        M.decode_message(Frame(2, 0, 0, T_SYNC, 0, b"\x80"))  # not a map
    with pytest.raises(MalformedError):  # v1's setpoint list is not v2's byte string
        M.decode_message(Frame(2, 0, 0, T_SYNC, 0, b"\xa2\x00\x01\x01\x82\x01\x02"))
    with pytest.raises(MalformedError):  # a STATE report shorter than its fixed part
        M.decode_message(Frame(2, FLAG_UP, 0, T_STATE, 0, b"\xa1\x00\x44\x00\x00\x00\x01"))


@settings(max_examples=1500, deadline=None)
@given(st.sampled_from(sorted(M.TYPE_NAMES) + [0, 0x42]), st.binary(max_size=60))
def test_random_payloads_raise_only_protocol_errors(mtype: int, payload: bytes) -> None:
    try:
        M.decode_message(Frame(2, FLAG_UP, 0, mtype, 0, payload))
    except ProtocolError:
        pass
    for pos in (0, 3):
        assert D.decode_sync(payload, 0, len(payload), pos, [0, 0, 0, 0]) in (-1, 0, 1)
    assert D.decode_cycle(payload, 0, len(payload)) >= -1
    assert D.decode_empty(payload, 0, len(payload)) in (-1, 1)


@pytest.mark.parametrize(
    "payload, rc",
    [
        (b"\xa2\x00\x01\x01\x45\x00\x00\x01\x00\x02", D.OK),
        (b"\xa2\x00\x01\x01\x45\x80\x00\x00\x00\x00", D.HOLD),  # the hold marker
        (b"\xa2\x00\x01\x01\x40", D.HOLD),  # no entry for position 0
        (b"\xa2\x00\x01\x01\x45\x80\x00\x00\x00\x01", D.MALFORMED),  # marker with phi
        (b"\xa2\x00\x01\x01\x44\x00\x00\x01\x00", D.MALFORMED),  # 4 bytes: no whole entry
        (b"\xa2\x00\x01\x01\x82\x01\x02", D.MALFORMED),  # version 1's list
        (b"\xa1\x00\x01", D.MALFORMED),  # no setpoints
        (b"\xa3\x00\x01\x01\x40\x00\x02", D.MALFORMED),  # duplicate key
        (b"\xa2\x00\x01\x01\x45\x00\x00\x01\x00\x02\x00", D.MALFORMED),  # trailing byte
        (b"\xa2\x00\x01\x01\x46\x00\x00\x01\x00\x02", D.MALFORMED),  # length > rest
        (b"\xa3\x00\x01\x01\x45\x00\x00\x01\x00\x02\x09\x82\x61\x61\xa0", D.OK),
        (b"\xa2\x00\x1a\x40\x00\x00\x00\x01\x40", D.MALFORMED),  # cycle 2**30
    ],
)
def test_device_decode_sync_cases(payload: bytes, rc: int) -> None:
    assert D.decode_sync(payload, 0, len(payload), 0, [0, 0, 0, 0]) == rc


def test_routing_rules() -> None:
    mine = 4
    assert D.route(FLAG_BCAST, 3) == mine | D.FWD_DOWN and D.next_hop(FLAG_BCAST, 3) == 4
    assert D.route(0, 0) == mine  # addressed to me
    assert D.route(0, 2) == D.FWD_DOWN and D.next_hop(0, 2) == 1
    assert D.route(FLAG_UP, 1) == D.FWD_UP and D.next_hop(FLAG_UP, 1) == 2
    assert D.route(FLAG_UP | FLAG_LOCAL, 0) == mine  # ALIVE: consumed, never forwarded
    assert D.version_supported(2) and not D.version_supported(1)
    assert not D.version_supported(3)


def test_device_small_decoders() -> None:
    hb = decode_frame(M.encode_heartbeat(0, 77)).payload
    assert D.decode_cycle(hb, 0, len(hb)) == 77
    assert D.decode_cycle(b"\xa0", 0, 1) == D.MALFORMED
    assert D.decode_empty(b"", 0, 0) == D.OK and D.decode_empty(b"\xa0", 0, 1) == D.OK
    assert D.decode_empty(b"\x80", 0, 1) == D.MALFORMED
