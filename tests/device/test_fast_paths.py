"""The cycle's machine-code paths (protocol/_fast.py) give exactly the bytecode paths' results.

``protocol.device`` decodes the usual SYNC (``sync_entry``) and builds a whole STATE frame
(``state_wire``) in one viper call where the VM has the emitter (the ESP32's xtensawin, the C3's
rv32imc, the emulator's x64); elsewhere, and for any SYNC in another encoding, the general
bytecode paths run. These tests compare both on the VM, on random and edge inputs.
"""

from __future__ import annotations

import random

from protocol import messages as M
from protocol.frame import decode_frame

# Corpus for the SYNC decoder: host-encoded SYNCs, the corner cases of the decoder's own tests,
# and mutations of them (bytes changed, truncated, appended), so both accepted and refused inputs
# reach both decoders.
_CASES = [
    "a2000101450000010002",
    "a2000101458000000000",
    "a200010140",
    "a2000101458000000001",
    "a20001014400000100",
    "a2000101820102",
    "a10001",
    "a3000101400002",
    "a200010145000001000200",
    "a2000101460000010002",
    "a3000101450000010002098261 61a0".replace(" ", ""),
    "a2001a400000000140",
    "a2001a3fffffff0140",
    "a200190100015800",
    "a300010145000001000201",  # resume as 1, 0, true, false, 2, null
    "a300010145000001000200",
    "a3000101450000010002f5",
    "a3000101450000010002f4",
    "a300010145000001000202",
    "a3000101450000010002f6",
]


def _sync_corpus(seed: int = 11, n: int = 1500) -> list[str]:
    rnd = random.Random(seed)
    out = list(_CASES)
    for _ in range(n):
        k = rnd.randint(0, 9)
        sps = [
            None if rnd.random() < 0.2 else (rnd.uniform(-100, 100), rnd.uniform(-3.14, 3.14))
            for _ in range(k)
        ]
        cycle = rnd.choice([rnd.randint(0, 23), rnd.randint(0, 70000), rnd.randint(0, 2**30 - 1)])
        p = bytearray(decode_frame(M.encode_sync(0, cycle, sps, rnd.random() < 0.5)).payload)
        r = rnd.random()
        if r < 0.3:
            for _ in range(rnd.randint(1, 3)):
                p[rnd.randrange(len(p))] = rnd.randint(0, 255)
        elif r < 0.4:
            p = p[: rnd.randint(0, len(p))]
        elif r < 0.5:
            p += bytes(rnd.randint(0, 255) for _ in range(rnd.randint(1, 3)))
        out.append(p.hex())
    return out


def test_machine_code_sync_decoder_agrees_with_the_general_one(vm):
    corpus = _sync_corpus()
    r = vm(
        f"""
import protocol.device as pd
C = {corpus!r}
fast = pd._sync_entry
R['fast'] = fast is not None
bad = []
hits = 0
for h in C:
    p = bytes.fromhex(h)
    for pos in (0, 1, 2, 7):
        a = [9, 9, 9, 9]
        b = [9, 9, 9, 9]
        ra = pd.decode_sync(p, 0, len(p), pos, a)
        if fast(p, 0, len(p), pos, [0, 0, 0, 0]) >= 0:
            hits += 1
        pd._sync_entry = None
        rb = pd.decode_sync(p, 0, len(p), pos, b)
        pd._sync_entry = fast
        same = ra == rb
        if same and ra >= 0:
            same = a[0] == b[0] and a[3] == b[3] and (ra == 0 or a[1:3] == b[1:3])
        if not same:
            bad.append([h, pos, ra, rb, a, b])
R['bad'] = bad[:5]
R['hits'] = hits
R['n'] = 4 * len(C)
""",
        heap="8m",
    )
    assert r["fast"], "the VM has a native emitter: decode_sync must use protocol/_fast.py"
    assert r["bad"] == []
    assert r["hits"] > r["n"] // 3  # the usual encoding took the machine-code path


def test_machine_code_state_frame_is_the_bytecode_frame_byte_for_byte(vm):
    r = vm(
        """
import random
from array import array
import protocol.device as pd
from protocol.constants import FLAG_UP, HEADER_LEN, T_STATE
from protocol.frame import frame_into
random.seed(5)
R['fast'] = pd._state_wire is not None
raw = bytearray(250)
out = bytearray(260)
raw2 = bytearray(250)
out2 = bytearray(260)
bad = []
M30 = (1 << 30) - 1
for k in range(3000):
    n = random.randint(0, 12)
    sv = [random.randint(-400000, 400000) for _ in range(n)]
    if k % 2:
        sv = array('i', sv)
    v = [random.randint(0, 255), random.choice([0, M30, random.randint(0, M30)]),
         random.choice([0, M30, random.randint(0, M30)]),
         random.choice([-(1 << 23), (1 << 23) - 1, random.randint(-(1 << 23), (1 << 23) - 1)]),
         random.randint(-32768, 32767), random.randint(0, 255), random.randint(0, 255)]
    seq, cyc, t, ka, ph, st, po = v
    a = pd.state_frame(raw, out, seq, cyc, t, ka, ph, sv, n, st, po)
    e = pd.encode_state(raw2, HEADER_LEN, cyc, t, ka, ph, sv, n, st, po)
    b = frame_into(raw2, e, FLAG_UP, 0, T_STATE, seq, out2, 0)
    if a != b or out[:a] != out2[:b]:
        bad.append([n, v])
R['bad'] = bad[:5]
""",
        heap="4m",
    )
    assert r["fast"], "the VM has a native emitter: state_frame must use protocol/_fast.py"
    assert r["bad"] == []


def _streams(seed: int = 3, n: int = 150) -> list[list]:
    """Wire streams of good, corrupted, truncated, oversized and idle frames, with chunk sizes."""
    from protocol.constants import FLAG_BCAST, FLAG_UP
    from protocol.frame import encode_frame

    rnd = random.Random(seed)
    out = []
    for _ in range(n):
        w = bytearray()
        up = rnd.random() < 0.5
        for _ in range(rnd.randint(1, 5)):
            payload = bytes(rnd.randrange(256) for _ in range(rnd.randint(0, 60)))
            flags = rnd.choice([FLAG_UP if up else FLAG_BCAST, 0, 4, 0x09])
            f = bytearray(encode_frame(flags, rnd.randrange(4), 2, rnd.randrange(256), payload))
            r = rnd.random()
            if r < 0.2:
                f[rnd.randrange(len(f) - 1)] ^= 1 << rnd.randrange(8)
            elif r < 0.3:
                f = f[: rnd.randint(1, len(f))]
            elif r < 0.35:
                f = bytearray(b"\x01" * 300 + b"\x00")  # oversize
            elif r < 0.4:
                f = bytearray(b"\x00\x00")  # idle
            w += f
        out.append([w.hex(), up, [rnd.randint(1, 40) for _ in range(3)]])
    out.append([out[-1][0] * 3, out[-1][1], [4000]])  # one long read: > 512 bytes relayed at once
    return out


def test_machine_code_reader_and_relay_agree_with_their_bytecode_twins(vm):
    """The frame reader's scan and the relay's step (one viper call each, and both in one as the
    segment calls them) against their bytecode twins on the VM: the same frames, counters and
    relayed bytes in any chunking."""
    r = vm(
        f"""
from protocol import frame as F, relay as RL, relay_py as RLP
C = {_streams()!r}
fast = (F._scan, RL._feed)
R['fast'] = F._scan is not F._scan_py and RL._feed is not RLP.feed

from protocol import _fast
from protocol.crc import _TABLE

def run(hexs, up, chunks, fused=False):
    stream = bytes.fromhex(hexs)
    rd = F.FrameReader()
    rl = RL.Relay(up)
    out = bytearray(4100)
    sent = bytearray()
    got = []
    a = 0
    k = 0
    while a < len(stream):
        data = stream[a:a + chunks[k % len(chunks)]]
        a += len(data)
        k += 1
        pos = 0
        while pos < len(data):
            if fused:  # the segment's receive step: both in one call
                r = _fast.scan_relay(rd, rl, data, pos, len(data), out, _TABLE)
                nxt = r & 0xFFF
                m = (r >> 12) & 0xFFF
                assert (r >> 24) == (1 if rd.ready else 0)
            else:
                nxt = rd.scan(data, pos, len(data))
                m = rl.feed(data, pos, nxt, rd.ready, rd, out)
            sent += out[:m]
            if rd.ready:
                got.append([rd.ver, rd.flags, rd.hop, rd.mtype, rd.seq, rd.raw_len,
                            rd.payload_end, bytes(rd.raw[:rd.raw_len]).hex(), rl.relayed != 0])
            pos = nxt
    s = rd.stats()
    r = rl.stats()
    return [sent.hex(), got, s["ok"], s["crc_error"], s["framing_error"], s["oversize"],
            r["frames"], r["poisoned"], rl.busy]

bad = []
for hexs, up, chunks in C:
    F._scan, RL._feed = fast
    a = run(hexs, up, chunks)
    c = run(hexs, up, chunks, True)
    F._scan, RL._feed = F._scan_py, RLP.feed
    b = run(hexs, up, chunks)
    if a != b or c != b:
        bad.append([hexs, up, chunks])
F._scan, RL._feed = fast
R['bad'] = bad[:3]
""",
        heap="8m",
    )
    assert r["fast"], "the VM has a native emitter: the reader and relay must use protocol/_fast.py"
    assert r["bad"] == []


_MECH_CONFIGS = [
    {},  # the paper's segment
    {  # four tendons, mixed directions, offsets and narrow ranges: clamps on both sides
        "length": 0.12,
        "tendon_radius": 0.012,
        "spool_radius": 0.008,
        "kappa_max": 20.0,
        "tendon_angles": [0.3, 1.9, 3.4, 5.0],
        "servos": [
            {"zero_offset": 0.4, "direction": -1, "min_angle": -1.0, "max_angle": 0.8},
            {"zero_offset": -0.7, "direction": 1, "min_angle": -0.5, "max_angle": 1.2},
            {"zero_offset": 0.0, "direction": -1, "min_angle": -2.0, "max_angle": 2.0},
            {"zero_offset": 1.1, "direction": 1, "min_angle": -0.3, "max_angle": 0.3},
        ],
    },
    # fixed-point shifts on every side of 16 (the written-out products' three branches):
    # q_i = 12, q_t = 16, q_t = 15
    {
        "length": 0.02,
        "tendon_radius": 0.001,
        "spool_radius": 0.005,
        "kappa_max": 5.0,
        "servos": [{"min_angle": -0.3, "max_angle": 0.3}] * 3,
    },
    {
        "length": 2.0,
        "tendon_radius": 0.08,
        "spool_radius": 0.15,
        "kappa_max": 1.0,
        "servos": [{"min_angle": -0.5, "max_angle": 0.5}] * 3,
    },
    {
        "length": 2.0,
        "tendon_radius": 0.2,
        "spool_radius": 0.15,
        "kappa_max": 1.0,
        "servos": [{"min_angle": -0.5, "max_angle": 0.5}] * 3,
    },
]


def test_machine_code_mechanism_loops_give_the_bytecode_loops_integers(vm):
    """device/mech_fast.py (Mechanism.measure, _servo_targets, update) against the bytecode
    paths: the same joint angles, tendon lengths, curvature, servo targets, slew state and
    clamp bits, for positions inside and far outside the ranges, curvature vectors up to beyond
    kappa_max, and slew steps from below one unit per tick to beyond the distance left."""
    import json

    r = vm(
        f"""
import random, config, mechanism
from array import array
random.seed(9)
R['fast'] = mechanism._fast is not None
fast = mechanism._fast
bad = []
for c in json.loads({json.dumps(json.dumps(_MECH_CONFIGS))}):
    cfg = config.Config(c)
    assert not cfg.error, cfg.error
    m = mechanism.Mechanism(cfg, 5)
    n = cfg.n
    for k in range(400):
        pos = array('i', [cfg.zero[i] + random.randint(-40000, 40000) for i in range(n)])
        res = []
        for use in (fast, None):
            mechanism._fast = use
            m.measure(pos)
            res.append([list(m.joint), list(m.tendon), m.mx, m.my, m.kappa, m.phi])
        if res[0] != res[1]:
            len(bad) < 3 and bad.append(['measure', list(pos), res])
        km = 2 * cfg.kappa_max
        m.cx = random.randint(-km, km)
        m.cy = random.randint(-km, km)
        res = []
        for use in (fast, None):
            mechanism._fast = use
            f = m._servo_targets()
            res.append([f, list(m.tendon_cmd), list(m.servo_target)])
        if res[0] != res[1]:
            len(bad) < 3 and bad.append(['targets', m.cx, m.cy, res])
        # the slew (update): from the same state, near and far targets, rate flag on and off
        m.set_rate_max(random.choice([1, 7, 333, 10000, 2000000]))
        s0 = [random.randint(-km, km) for _ in range(4)]
        if k % 3 == 0:
            s0[2] = s0[0] + random.randint(-5, 5)
            s0[3] = s0[1] + random.randint(-5, 5)
        acc0 = random.randint(0, 999)
        ex0 = random.random() < 0.5
        res = []
        for use in (fast, None):
            mechanism._fast = use
            m.tx, m.ty, m.cx, m.cy = s0
            m.step_acc = acc0
            m.rate_excess = ex0
            f = m.update()
            res.append([f, m.cx, m.cy, m.step_acc, m.rate_excess, list(m.tendon_cmd),
                        list(m.servo_target)])
        if res[0] != res[1]:
            len(bad) < 3 and bad.append(['update', s0, acc0, ex0, res])
    mechanism._fast = fast
R['bad'] = bad[:3]
""",
        heap="1m",
    )
    assert r["fast"], "the VM has a native emitter: mechanism must use device/mech_fast.py"
    assert r["bad"] == []
