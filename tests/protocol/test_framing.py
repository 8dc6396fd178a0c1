"""COBS, CRC-16 and frames: round trips, limits, and a reader that survives any byte stream."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from protocol_testkit import corrupt, make_stream, sample_wires

from protocol import cobs
from protocol.constants import MAX_ENCODED, MAX_FRAME, MAX_PAYLOAD
from protocol.crc import crc16
from protocol.errors import MalformedError
from protocol.frame import (
    Frame,
    FrameReader,
    decode_frame,
    encode_frame,
    forward_into,
    frame_into,
    seal,
    wire_into,
)

headers = st.tuples(*(st.integers(0, 255) for _ in range(5)))
payloads = st.binary(max_size=MAX_PAYLOAD)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=700))
def test_cobs_round_trip_removes_zeros_with_minimal_overhead(data: bytes) -> None:
    enc = cobs.encode(data)
    assert 0 not in enc
    assert len(enc) == len(data) + 1 + len(data) // 254
    assert cobs.decode(enc) == data
    buf = bytearray(enc)  # in-place decode
    n = cobs.decode_into(buf, 0, len(buf), buf, 0)
    assert bytes(buf[:n]) == data


@pytest.mark.parametrize("bad", [b"\x00", b"\x05\x01", b"\x02\x00", b"\x03\x11"])
def test_cobs_decode_rejects_invalid(bad: bytes) -> None:
    with pytest.raises(ValueError):
        cobs.decode(bad)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300), st.integers(0, 300))
def test_crc_is_incremental(data: bytes, cut: int) -> None:
    cut = min(cut, len(data))
    assert crc16(data, cut, len(data), crc16(data, 0, cut)) == crc16(data)


def test_crc_detects_every_1_2_3_bit_error_in_a_max_size_frame() -> None:
    """Hamming distance >= 4 at 250 bytes (2000 bits), verified through the CRC's linearity:
    an error pattern is missed iff the XOR of its single-bit syndromes is 0."""
    n_data = MAX_FRAME - 2
    syn = []
    for byte in range(n_data):
        for bit in range(8):
            e = bytearray(n_data)
            e[byte] = 0x80 >> bit
            syn.append(crc16(e, 0, n_data, 0))
    syn += [1 << b for b in range(16)]  # flips inside the transmitted CRC itself
    assert len(syn) == 8 * MAX_FRAME
    assert 0 not in syn  # all single-bit errors
    s = set(syn)
    assert len(s) == len(syn)  # all double-bit errors
    for i in range(len(syn)):  # all triple-bit errors: s_i ^ s_j == s_k never happens
        si = syn[i]
        for j in range(i + 1, len(syn)):
            assert si ^ syn[j] not in s


@settings(max_examples=300, deadline=None)
@given(headers, payloads)
def test_frame_round_trip_and_layout(h, payload: bytes) -> None:
    ver, flags, hop, mtype, seq = h
    wire = encode_frame(flags, hop, mtype, seq, payload, ver)
    assert wire[-1] == 0 and 0 not in wire[:-1]
    assert len(wire) <= MAX_ENCODED
    fr = decode_frame(wire)
    assert (fr.ver, fr.flags, fr.hop, fr.mtype, fr.seq, fr.payload) == (*h, payload)
    raw = cobs.decode(wire[:-1])
    t = 2 if ver == 1 else 3  # version 2+: a 0x00 pad before the CRC; version 1 had none
    assert raw[:5] == bytes(h) and raw[5:-t] == payload
    assert t == 2 or raw[-3] == 0
    assert int.from_bytes(raw[-2:], "big") == crc16(raw[:-2])  # CRC big-endian at the end
    assert fr.raw() == raw
    if ver != 1:  # the CRC's COBS form is always the last three wire bytes (cut-through)
        assert wire[-4:-1] == cobs.encode(b"\x00" + raw[-2:])[1:]


def test_frame_size_limits() -> None:
    wire = encode_frame(0, 0, 1, 0, bytes(range(1, 243)))  # 242-byte payload: 250-byte frame
    assert len(wire) == MAX_ENCODED
    with pytest.raises(ValueError):
        encode_frame(0, 0, 1, 0, bytes(MAX_PAYLOAD + 1))
    with pytest.raises(ValueError):
        encode_frame(256, 0, 1, 0, None)
    with pytest.raises(ValueError):
        seal(bytearray(300), 249, 0, 0, 1, 0)


@pytest.mark.parametrize(
    "wire",
    [b"", b"\x00", b"\x01\x01\x00", b"\x06\x01\x02\x03\x04\x05\x00", b"\x02\x00\x01\x00"],
)
def test_decode_frame_rejects_runts_and_garbage(wire: bytes) -> None:
    with pytest.raises(MalformedError):
        decode_frame(wire)


def test_empty_payload_frame() -> None:
    fr = decode_frame(encode_frame(2, 0, 6, 9, None))
    assert fr.payload == b"" and fr.mtype == 6


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(headers, payloads), min_size=1, max_size=6), st.integers(1, 80))
def test_reader_receives_every_frame_in_any_chunking(frames, chunk: int) -> None:
    sent = [Frame(*h, p) for h, p in frames]
    stream = b"".join(encode_frame(f.flags, f.hop, f.mtype, f.seq, f.payload, f.ver) for f in sent)
    r = FrameReader()
    got = []
    for i in range(0, len(stream), chunk):
        got += r.feed(stream[i : i + chunk])
    assert got == sent
    assert r.stats() == {"ok": len(sent), "crc_error": 0, "framing_error": 0, "oversize": 0}


@settings(max_examples=300, deadline=None, derandomize=True)
@given(st.integers(0, 2**32 - 1))
def test_reader_survives_corruption_and_resynchronises(seed: int) -> None:
    """Flipped bits, dropped, duplicated, inserted and truncated bytes: never raises, hands out
    only frames that were sent, and receives every untouched frame after an intact delimiter."""
    rng = random.Random(seed)
    wires = sample_wires(rng, rng.randint(1, 10))
    h, chunks, clean = make_stream(rng, wires, p_corrupt=0.5)
    data = bytes.fromhex(h)
    sent = [decode_frame(w) for w in wires]
    r = FrameReader()
    got = []
    pos = 0
    i = 0
    while pos < len(data):
        n = chunks[i % len(chunks)]
        got += r.feed(data[pos : pos + n])
        pos += n
        i += 1
    for f in got:
        assert f in sent
    for i in clean:
        assert sent[i] in got


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=600))
def test_reader_on_random_bytes_yields_only_crc_valid_frames(data: bytes) -> None:
    r = FrameReader()
    for f in r.feed(data):
        assert decode_frame(encode_frame(f.flags, f.hop, f.mtype, f.seq, f.payload, f.ver)) == f
    # whatever came before, a delimiter plus a good frame is received
    good = encode_frame(1, 2, 0x83, 4, b"\xa0")
    assert r.feed(b"\x00" + good) == [decode_frame(good)]


def test_corrupt_helper_reports_the_delimiter_state() -> None:
    rng = random.Random(3)
    w = sample_wires(rng, 1)[0]
    for _ in range(200):
        b, intact = corrupt(rng, w)
        assert intact == (len(b) > 0 and b[-1] == 0)


def test_oversize_frame_is_counted_and_followed_by_resync() -> None:
    r = FrameReader()
    good = encode_frame(2, 0, 2, 1, {0: 1, 1: []})
    assert r.feed(b"\x01" * 400 + b"\x00" + good) == [decode_frame(good)]
    assert r.stats()["oversize"] == 1 and r.stats()["ok"] == 1


def test_reader_counts_crc_and_framing_errors() -> None:
    r = FrameReader()
    w = bytearray(encode_frame(2, 0, 1, 1, {}))
    w[6] ^= 0x40  # the payload byte 0xa0 changes, COBS stays valid
    assert r.feed(bytes(w)) == []
    assert r.stats()["crc_error"] == 1
    assert r.feed(b"\x05\x01\x00") == []  # COBS code byte points past the end
    assert r.stats()["framing_error"] == 1
    r.feed(b"\x02\x11")
    r.reset()  # a partial frame discarded after a silence
    assert r.stats()["framing_error"] == 2
    assert r.feed(b"\x00\x00\x00") == []  # idle delimiters are free
    assert r.stats()["framing_error"] == 2


def test_scan_hands_out_one_frame_at_a_time() -> None:
    a = encode_frame(2, 0, 2, 1, {0: 1, 1: []})
    b = encode_frame(1, 3, 0x83, 2, b"")
    data = a + b
    r = FrameReader()
    pos = r.scan(data, 0, len(data))
    assert r.ready and pos == len(a) and r.mtype == 2 and r.seq == 1
    assert bytes(r.payload()) == decode_frame(a).payload
    pos = r.scan(data, pos, len(data))
    assert r.ready and pos == len(data) and r.hop == 3 and r.payload_end == 5
    pos = r.scan(data, pos, len(data))
    assert not r.ready


@settings(max_examples=200, deadline=None)
@given(headers, payloads, st.integers(0, 255))
def test_forward_into_changes_only_the_hop(h, payload: bytes, hop: int) -> None:
    ver, flags, _, mtype, seq = h
    raw = bytearray(decode_frame(encode_frame(flags, h[2], mtype, seq, payload, ver)).raw())
    out = bytearray(MAX_ENCODED)
    n = forward_into(raw, len(raw), hop, out)
    assert bytes(out[:n]) == encode_frame(flags, hop, mtype, seq, payload, ver)


def test_frame_into_equals_seal_plus_wire_into() -> None:
    raw = bytearray(MAX_FRAME)
    raw[5:8] = b"\xa1\x00\x01"
    out1 = bytearray(MAX_ENCODED)
    n1 = frame_into(raw, 8, 1, 0, 0x83, 7, out1)
    out2 = bytearray(MAX_ENCODED)
    n2 = wire_into(raw, seal(raw, 8, 1, 0, 0x83, 7), out2)
    assert out1[:n1] == out2[:n2] == encode_frame(1, 0, 0x83, 7, {0: 1})
