"""Protocol test helpers: vectors, random messages, corrupted streams, the VM batch runner."""

from __future__ import annotations

import json
import math
import random
import struct
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent.parent
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))

VECTORS_FILE = REPO / "protocol" / "vectors" / "vectors.jsonl"


def load_vectors() -> list[dict]:
    """The committed test vectors (protocol/vectors/vectors.jsonl)."""
    with VECTORS_FILE.open() as f:
        return [json.loads(line) for line in f if line.strip()]


def approx_equal(a, b, rel: float = 1e-12) -> bool:
    """Deep equality where floats may differ in the last digits (JSON float printing)."""
    if isinstance(a, float) or isinstance(b, float):
        if not isinstance(a, (int, float)) or not isinstance(b, (int, float)):
            return False
        if math.isnan(a) and math.isnan(b):
            return True
        return math.isclose(a, b, rel_tol=rel, abs_tol=1e-300) and (
            math.copysign(1, a) == math.copysign(1, b) or a == 0
        )
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(approx_equal(a[k], b[k], rel) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(approx_equal(x, y, rel) for x, y in zip(a, b, strict=True))
    return a == b


# --------------------------------------------------------------------------------------------
# random messages and corrupted streams (seeded, so the VM batch is reproducible)
# --------------------------------------------------------------------------------------------
def random_float_vector(rng: random.Random, i: int) -> dict:
    """cbor.dumps of random float16/32/64 bit patterns, passed as exact float64 bits."""
    xs = []
    for _ in range(50):
        width = rng.choice((2, 4, 8))
        x = struct.unpack({2: ">e", 4: ">f", 8: ">d"}[width], rng.randbytes(width))[0]
        if not math.isnan(x):
            xs.append({"$f64": struct.pack(">d", x).hex()})
    return {"name": f"random_{i}_floats", "call": "cbor.dumps", "args": [xs]}


def random_vectors(rng: random.Random, n: int) -> list[dict]:
    """Random message descriptions in the vector format (no expected results)."""
    out = [random_float_vector(rng, n + i) for i in range(20)]
    for i in range(n):
        kind = rng.choice(["sync", "state", "param", "event", "error", "descriptor", "dstate"])
        seq = rng.randrange(256)
        if kind == "sync":
            nseg = rng.randint(1, 8)
            sps = [
                None
                if rng.random() < 0.15
                else [round(rng.uniform(-60, 60), 6), round(rng.uniform(-7, 7), 6)]
                for _ in range(nseg)
            ]
            v = {
                "call": "encode_sync",
                "args": [seq, rng.randrange(2**30), sps],
                "kwargs": {"resume": rng.random() < 0.2},
                "positions": list(range(nseg + 1)),
            }
        elif kind == "state":
            nt = rng.randint(0, 6)
            v = {
                "call": "encode_state",
                "args": [seq],
                "kwargs": {
                    "cycle": rng.randrange(2**30),
                    "t_ms": rng.randrange(2**30),
                    "kappa": rng.uniform(0, 40),
                    "phi": rng.uniform(-10, 10),
                    "servo_angles": [rng.uniform(-3, 3) for _ in range(nt)],
                    "status": rng.randrange(64),
                    "applied_position": rng.randrange(256),
                },
            }
        elif kind == "dstate":
            nt = rng.randint(0, 8)
            lim = 2**30 - 1
            v = {
                "call": "device.state_frame",
                "args": [seq, rng.randrange(2**30), rng.randrange(2**30)]
                + [rng.randint(-0x7FFFFF, 0x7FFFFF), rng.randint(-31416, 31416)]
                + [[rng.randint(-lim, lim) for _ in range(nt)], nt]
                + [rng.randrange(64), rng.randrange(256)],
            }
        elif kind == "param":
            value = rng.choice(
                [rng.randint(-(2**29), 2**29), rng.uniform(-1e6, 1e6), True, "txt", 0.25]
            )
            call = rng.choice(["encode_param_set", "encode_param_value"])
            if call == "encode_param_set":
                v = {"call": call, "args": [seq, rng.randrange(8), rng.randrange(1000), value]}
            else:
                v = {"call": call, "args": [seq, rng.randrange(1000), value]}
        elif kind == "event":
            v = {
                "call": "encode_event",
                "args": [seq, rng.randint(1, 9), rng.randint(-5, 2**20), rng.randrange(2**30)],
            }
        elif kind == "error":
            v = {"call": "encode_error", "args": [seq, rng.randint(1, 6), rng.randrange(256), "é"]}
        else:
            v = {
                "call": "encode_descriptor",
                "args": [
                    {
                        "uid": f"{rng.randrange(2**48):012x}",
                        "fw_version": f"1.{rng.randrange(10)}",
                        "protocol_version": 1,
                        "model": "pcc",
                        "length": rng.uniform(0.01, 0.5),
                        "tendon_angles": [rng.uniform(0, 6.28) for _ in range(rng.randint(3, 4))],
                        "kappa_max": float(rng.randint(1, 40)),
                        "watchdog_ms": rng.randrange(1000),
                        "downstream_present": rng.random() < 0.5,
                    },
                    seq,
                ],
            }
        v["name"] = f"random_{i}_{kind}"
        out.append(v)
    return out


def corrupt(rng: random.Random, wire: bytes) -> tuple[bytes, bool]:
    """Apply one random corruption to a frame's wire bytes.

    Returns (bytes, delimiter_intact): whether the stream still has a 0x00 right after the
    corrupted frame, so the next frame starts cleanly.
    """
    op = rng.choice(["flip", "drop", "dup", "truncate", "insert", "flips"])
    n = len(wire)
    p = rng.randrange(n)
    b = bytearray(wire)
    if op == "flip":
        b[p] ^= 1 << rng.randrange(8)
    elif op == "flips":
        for _ in range(rng.randint(2, 6)):
            b[rng.randrange(n)] ^= 1 << rng.randrange(8)
    elif op == "drop":
        del b[p]
    elif op == "dup":
        b.insert(p, b[p])
    elif op == "truncate":
        return bytes(b[: rng.randrange(n - 1)]), False
    else:  # insert garbage
        b[p:p] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))
    return bytes(b), len(b) > 0 and b[-1] == 0


def make_stream(rng: random.Random, wires: list[bytes], p_corrupt: float = 0.4):
    """A stream of frames, some corrupted, plus leading garbage.

    Returns (hex, chunk sizes, indices of frames that must be received: untouched and preceded by
    an intact delimiter).
    """
    out = bytearray(bytes(rng.randrange(256) for _ in range(rng.randint(0, 20))))
    out.append(0)  # the garbage is ended by a delimiter: the first frame is clean if untouched
    clean = []
    prev_ok = True
    for i, w in enumerate(wires):
        if rng.random() < p_corrupt:
            cw, prev_ok = corrupt(rng, w)
            out += cw
        else:
            if prev_ok:
                clean.append(i)
            out += w
            prev_ok = True
    chunks = [rng.randint(1, 64) for _ in range(5)]
    return out.hex(), chunks, clean


def sample_wires(rng: random.Random, n: int) -> list[bytes]:
    """Valid frames of assorted types for stream tests."""
    from protocol import messages as M

    wires = []
    for _ in range(n):
        k = rng.randrange(4)
        seq = rng.randrange(256)
        if k == 0:
            wires.append(M.encode_sync(seq, rng.randrange(2**30), [(1.0, 0.5)] * rng.randint(1, 8)))
        elif k == 1:
            wires.append(
                M.encode_state(
                    seq,
                    cycle=seq,
                    t_ms=rng.randrange(2**30),
                    kappa=rng.uniform(0, 20),
                    phi=rng.uniform(-3, 3),
                    servo_angles=[0.1, 0.2, 0.3],
                    status=rng.randrange(64),
                )
            )
        elif k == 2:
            wires.append(M.encode_event(seq, rng.randint(1, 7), rng.randrange(100), 1000))
        else:
            wires.append(M.encode_heartbeat(seq, rng.randrange(2**30)))
    return wires


def make_streams(seed: int, n: int) -> list[dict]:
    """Seeded corrupted streams with the frames each must deliver."""
    rng = random.Random(seed)
    streams = []
    for _ in range(n):
        wires = sample_wires(rng, rng.randint(1, 8))
        h, chunks, clean = make_stream(rng, wires)
        streams.append(
            {
                "hex": h,
                "chunks": chunks,
                "clean": clean,
                "sent": [_raw_hex(w) for w in wires],
            }
        )
    return streams


def _raw_hex(wire: bytes) -> str:
    from protocol import frame as F

    return F.decode_frame(wire).raw().hex()


def run_mp_job(job: dict, tmp: Path, heap: str = "16m", pure: bool = False) -> dict:
    """Run mp_runner.main on the MicroPython VM with ``job``; return its JSON results.

    ``pure``: switch off the viper loops first (tests the pure-Python loops on the VM).
    """
    from tools.mpvm import run_code

    inp = tmp / "job.json"
    outp = tmp / "result.json"
    inp.write_text(json.dumps(job))
    code = f"import mp_runner\nmp_runner.main({str(inp)!r}, {str(outp)!r}, {pure!r})\n"
    run_code(code, heap=heap, paths=[REPO, HERE], timeout=120)
    return json.loads(outp.read_text())
