"""Cut-through relay (protocol/relay.py): what it passes on equals the frame re-framed with the next
hop, in any chunking; a corrupted input is never passed on as a frame anyone accepts; the viper
byte loop on MicroPython gives the same bytes as the bytecode one on CPython."""

from __future__ import annotations

import json
import random

from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import messages as M
from protocol import relay as R
from protocol.constants import FLAG_BCAST, FLAG_LOCAL, FLAG_UP, T_STATE, T_SYNC
from protocol.frame import FrameReader, decode_frame, encode_frame
from tools import mpvm


def through(stream: bytes, upward: bool, chunks: list[int]) -> bytes:
    """Feed ``stream`` to a reader + relay pair in the given chunk sizes; return what it sends."""
    rd = FrameReader()
    rl = R.Relay(upward)
    out = bytearray(max(chunks) + 8)
    sent = bytearray()
    a = 0
    k = 0
    while a < len(stream):
        data = stream[a : a + chunks[k % len(chunks)]]
        a += len(data)
        k += 1
        pos = 0
        while pos < len(data):
            nxt = rd.scan(data, pos, len(data))
            m = rl.feed(data, pos, nxt, rd.ready, rd, out)
            sent += out[:m]
            pos = nxt
    return bytes(sent)


payloads = st.binary(max_size=60)
hops = st.integers(0, 20)
chunking = st.lists(st.integers(1, 40), min_size=1, max_size=5)


@settings(max_examples=300, deadline=None)
@given(payloads, hops, st.integers(0, 255), chunking)
def test_a_relayed_broadcast_is_the_frame_with_the_next_hop(payload, hop, seq, chunks) -> None:
    w = encode_frame(FLAG_BCAST, hop, T_SYNC, seq, payload)
    assert through(w, False, chunks) == encode_frame(FLAG_BCAST, hop + 1, T_SYNC, seq, payload)


@settings(max_examples=300, deadline=None)
@given(payloads, hops, st.integers(0, 255), chunking)
def test_a_relayed_upstream_frame_is_the_frame_with_the_next_hop(payload, hop, seq, chunks) -> None:
    w = encode_frame(FLAG_UP, hop, T_STATE, seq, payload)
    assert through(w, True, chunks) == encode_frame(FLAG_UP, hop + 1, T_STATE, seq, payload)


def test_a_long_read_is_relayed_as_in_short_ones() -> None:
    """More than 512 bytes relayed by one call: frames with a broken CRC do not stop the
    reader's scan, so one read of twenty of them is one relay step (its output length once
    shared an int with a flag at bit 9 and wrapped). The same bytes go out however it is read."""
    frames = []
    for k in range(20):
        w = bytearray(encode_frame(FLAG_BCAST, 1, T_SYNC, k, bytes(range(1, 41))))
        w[10] ^= 0x01  # a payload byte: the CRC fails at the receiver, the relay poisons the end
        frames.append(bytes(w))
    stream = b"".join(frames)
    assert len(stream) > 900
    one = through(stream, False, [len(stream)])
    assert len(one) > 900
    assert one == through(stream, False, [7])
    assert FrameReader().feed(one) == []  # nothing the next segment accepts


def test_what_is_not_cut_through_is_not_relayed() -> None:
    for w, up in (
        (encode_frame(0, 2, 0x04, 1, {0: 1}), False),  # addressed: store-and-forward
        (encode_frame(FLAG_UP | FLAG_LOCAL, 0, 0x07, 1, {}), True),  # ALIVE: link-local
        (encode_frame(FLAG_UP, 0, T_STATE, 1, {0: b"x"}), False),  # wrong direction
        (encode_frame(FLAG_BCAST, 0, T_SYNC, 1, {}, ver=1), False),  # another version
    ):
        assert through(w, up, [7]) == b""


@settings(max_examples=400, deadline=None, derandomize=True)
@given(st.integers(0, 2**32 - 1))
def test_a_corrupted_frame_is_never_passed_on_as_an_acceptable_one(seed: int) -> None:
    rng = random.Random(seed)
    sps = [(rng.uniform(-50, 50), rng.uniform(-3, 3)) for _ in range(rng.randint(1, 8))]
    w = bytearray(M.encode_sync(rng.randrange(256), rng.randrange(2**30), sps))
    f = decode_frame(bytes(w))
    w = bytearray(encode_frame(f.flags, rng.randrange(4), f.mtype, f.seq, f.payload))
    for _ in range(rng.randint(1, 3)):  # flip, replace, drop or insert bytes
        j = rng.randrange(len(w) - 1)
        op = rng.randrange(4)
        if op == 0:
            w[j] ^= 1 << rng.randrange(8)
        elif op == 1:
            w[j] = rng.randrange(256)
        elif op == 2:
            del w[j]
        else:
            w.insert(j, rng.randrange(256))
    accepted_in = FrameReader().feed(bytes(w))
    out = through(bytes(w), False, [rng.randint(1, 30)])
    accepted_out = FrameReader().feed(out)
    for fr in accepted_out:  # only what the relay's own reader accepted, with the next hop
        assert any(
            (g.payload, g.seq, g.hop + 1) == (fr.payload, fr.seq, fr.hop) for g in accepted_in
        )


VM_CODE = """
import json
from protocol import relay as R
from protocol.frame import FrameReader
cases = json.loads(%r)
res = []
for hexs, up, chunks in cases:
    stream = bytes.fromhex(hexs)
    rd = FrameReader()
    rl = R.Relay(up)
    out = bytearray(600)
    sent = bytearray()
    a = 0
    k = 0
    while a < len(stream):
        data = stream[a:a + chunks[k %% len(chunks)]]
        a += len(data)
        k += 1
        pos = 0
        while pos < len(data):
            nxt = rd.scan(data, pos, len(data))
            m = rl.feed(data, pos, nxt, rd.ready, rd, out)
            sent += out[:m]
            pos = nxt
    res.append(sent.hex())
from protocol import _fast
print('@@' + json.dumps([res, R._feed is _fast.relay_feed]))
"""


def test_the_viper_relay_on_micropython_sends_the_same_bytes_as_cpython() -> None:
    rng = random.Random(5)
    cases = []
    for _ in range(60):
        up = rng.random() < 0.5
        frames = []
        for _ in range(rng.randint(1, 4)):
            payload = bytes(rng.randrange(256) for _ in range(rng.randint(0, 50)))
            flags = FLAG_UP if up else FLAG_BCAST
            w = bytearray(encode_frame(flags, rng.randrange(3), 0x02, rng.randrange(256), payload))
            if rng.random() < 0.3:
                w[rng.randrange(len(w) - 1)] ^= 1 << rng.randrange(8)
            frames.append(bytes(w))
        cases.append([b"".join(frames).hex(), up, [rng.randint(1, 30) for _ in range(3)]])
    out = mpvm.run_code(VM_CODE % json.dumps(cases), paths=[mpvm.REPO], timeout=60, heap="2m")
    line = [ln for ln in out.splitlines() if ln.startswith("@@")][0]
    got, viper = json.loads(line[2:])
    assert viper  # the machine-code loop ran, not the bytecode twin
    want = [through(bytes.fromhex(h), up, chunks).hex() for h, up, chunks in cases]
    assert got == want
