"""The project's CBOR codec: canonical bytes identical to cbor2, strict and safe decoding."""

from __future__ import annotations

import math
import struct

import cbor2
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import cbor
from protocol.errors import MalformedError

ints = st.integers(min_value=-(2**64), max_value=2**64 - 1)
wire_ints = st.integers(min_value=-(2**30) + 1, max_value=2**30 - 1)  # what loads accepts
floats = (
    st.floats(allow_nan=False)
    | st.floats(width=32, allow_nan=False)
    | st.floats(width=16, allow_nan=False)
)
scalars = ints | floats | st.booleans() | st.none() | st.text(max_size=20) | st.binary(max_size=20)
keys = st.integers(min_value=-(2**20), max_value=2**20) | st.text(max_size=8)
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(keys, inner, max_size=6),
    max_leaves=25,
)
wire_scalars = (
    wire_ints | floats | st.booleans() | st.none() | st.text(max_size=20) | st.binary(max_size=20)
)
wire_values = st.recursive(
    wire_scalars,
    lambda inner: st.lists(inner, max_size=6) | st.dictionaries(keys, inner, max_size=6),
    max_leaves=25,
)


@settings(max_examples=400, deadline=None)
@given(values)
def test_dumps_is_byte_identical_to_cbor2_canonical(obj) -> None:
    assert cbor.dumps(obj) == cbor2.dumps(obj, canonical=True)


@settings(max_examples=400, deadline=None)
@given(wire_values)
def test_loads_inverts_dumps_and_reads_cbor2_output(obj) -> None:
    assert cbor.loads(cbor.dumps(obj)) == obj
    assert cbor2.loads(cbor.dumps(obj)) == obj


@settings(max_examples=300, deadline=None)
@given(st.floats(allow_nan=False))
def test_floats_use_the_shortest_exact_width(x: float) -> None:
    b = cbor.dumps(x)
    width = {0xF9: 2, 0xFA: 4, 0xFB: 8}[b[0]]
    fmt = {2: ">e", 4: ">f", 8: ">d"}[width]
    assert struct.unpack(fmt, b[1:])[0] == x or (x == 0 and b[1:] in (b"\x00\x00", b"\x80\x00"))
    if width > 2:  # no narrower width holds x exactly
        try:
            narrower = struct.unpack(">e", struct.pack(">e", x))[0]
        except OverflowError:
            narrower = None
        assert narrower != x
    if width > 4:
        try:
            assert struct.unpack(">f", struct.pack(">f", x))[0] != x
        except OverflowError:
            pass


def test_nan_and_infinities_encode_like_cbor2() -> None:
    for x in (math.nan, math.inf, -math.inf):
        assert cbor.dumps(x) == cbor2.dumps(x, canonical=True)
    assert math.isnan(cbor.loads(b"\xf9\x7e\x00"))


@pytest.mark.parametrize(
    "data, why",
    [
        (b"", "empty"),
        (b"\x18", "truncated argument"),
        (b"\x62a", "truncated text"),
        (b"\x82\x01", "truncated array"),
        (b"\x9f\x01\xff", "indefinite array"),
        (b"\x5f\x41a\xff", "indefinite bytes"),
        (b"\xc1\x01", "tag"),
        (b"\xf7", "undefined"),
        (b"\xf0", "simple value"),
        (b"\xf8\x20", "one-byte simple value"),
        (b"\x01\x02", "trailing bytes"),
        (b"\xa2\x01\x01\x01\x02", "duplicate key"),
        (b"\xa1\x80\x01", "list as key"),
        (b"\x62\xff\xfe", "text not UTF-8"),
        (b"\x1c", "reserved additional info"),
        (b"\x81" * 20 + b"\x01", "nesting too deep"),
        (b"\x9b\xff\xff\xff\xff\xff\xff\xff\xff", "huge array length"),
    ],
)
def test_loads_rejects_malformed_input(data: bytes, why: str) -> None:
    with pytest.raises(MalformedError):
        cbor.loads(data)


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=64))
def test_loads_on_random_bytes_raises_only_malformed(data: bytes) -> None:
    try:
        cbor.loads(data)
    except MalformedError:
        pass


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=64))
def test_reader_skip_never_raises_and_agrees_with_loads(data: bytes) -> None:
    r = cbor.Reader()
    r.reset(data, 0, len(data))
    ok = r.skip() and r.at_end()
    try:
        obj = cbor.loads(data)
    except MalformedError:
        obj = MalformedError
    if obj is not MalformedError and ok is False:
        # the in-place reader is stricter only about map keys (ints and text); the wire's int
        # range it shares with loads
        assert _has_odd_keys(obj)
    if obj is not MalformedError:
        assert not _has_big_ints(obj)
    if ok:  # and never more lenient: what skip() passes, loads() accepts
        assert obj is not MalformedError


def _has_odd_keys(obj) -> bool:
    """Map keys other than int, text or bytes anywhere (the reader refuses them)."""
    if isinstance(obj, (list, tuple)):
        return any(_has_odd_keys(x) for x in obj)
    if isinstance(obj, dict):
        return any(
            isinstance(k, (bool, float)) or k is None or _has_odd_keys(k) or _has_odd_keys(v)
            for k, v in obj.items()
        )
    return False


def _has_big_ints(obj) -> bool:
    if isinstance(obj, bool):
        return False
    if isinstance(obj, int):
        return not -(2**30) < obj < 2**30
    if isinstance(obj, (list, tuple)):
        return any(_has_big_ints(x) for x in obj)
    if isinstance(obj, dict):
        return any(_has_big_ints(k) or _has_big_ints(v) for k, v in obj.items())
    if isinstance(obj, (str, bytes)):
        return len(obj) >= 2**30
    return False


@settings(max_examples=300, deadline=None)
@given(st.integers(min_value=-(2**30) + 1, max_value=2**30 - 1))
def test_put_int_matches_dumps_and_reader_reads_it_back(v: int) -> None:
    buf = bytearray(8)
    end = cbor.put_int(buf, 0, v)
    assert bytes(buf[:end]) == cbor.dumps(v)
    r = cbor.Reader()
    r.reset(buf, 0, end)
    assert r.int() and r.val == v and r.at_end()


def test_reader_refuses_ints_outside_the_wire_range() -> None:
    r = cbor.Reader()
    for big in (2**30, -(2**30), -(2**30) - 1, 2**40):
        data = cbor.dumps(big)
        r.reset(data, 0, len(data))
        assert r.head() == cbor.BAD


@pytest.mark.parametrize(
    "data",
    [
        b"\x1a\x40\x00\x00\x00",  # 2**30
        b"\x3a\x3f\xff\xff\xff",  # -2**30
        b"\x3a\x40\x00\x00\x00",  # -2**30 - 1
        b"\x1b\x00\x00\x00\x01\x00\x00\x00\x00",  # 2**32 in 8 bytes
        b"\x1b\x00\x00\x00\x00\x00\x00\x00\x01",  # 1 in 8 bytes (not canonical either)
        b"\x3b\x00\x00\x00\x01\x00\x00\x00\x00",
        b"\xa1\x09\x1a\x40\x00\x00\x00",  # under an ignored key
        b"\x5a\x40\x00\x00\x00",  # a length >= 2**30
    ],
)
def test_loads_refuses_ints_outside_the_wire_range_like_the_reader(data: bytes) -> None:
    """The slow path (PARAM_GET/SET, CLEAR_FAULT, CALIBRATE on the segment; every reply on the
    host) is as strict as the in-place Reader (docs/protocol.md "Integer range")."""
    r = cbor.Reader()
    r.reset(data, 0, len(data))
    assert not (r.skip() and r.at_end())
    with pytest.raises(MalformedError):
        cbor.loads(data)
    for edge in (2**30 - 1, -(2**30) + 1):
        assert cbor.loads(cbor.dumps(edge)) == edge


def test_dumps_into_writes_at_offset_and_refuses_overflow() -> None:
    buf = bytearray(10)
    assert cbor.dumps_into({0: 1}, buf, 2) == 5
    assert bytes(buf[2:5]) == b"\xa1\x00\x01"
    with pytest.raises(IndexError):
        cbor.dumps_into("x" * 20, buf, 0)


def test_dumps_refuses_unsupported_types() -> None:
    with pytest.raises(TypeError):
        cbor.dumps({1: object()})
    with pytest.raises(ValueError):
        cbor.dumps(2**64)
