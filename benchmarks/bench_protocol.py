"""Link protocol benchmark: bytes on the wire, implied cycle rates, encode/decode times.

Prints:
1. wire bytes per SYNC (host -> all) and per STATE (one segment -> host) for N = 1, 3, 8,
   typical and worst-case values (CBOR ints grow with magnitude);
2. implied max cycle rate at 115200 / 921600 / 2000000 baud (10 bits per byte), a cycle being one
   SYNC down + N STATEs up, for the chain's full-duplex links;
3. the same for micro-ROS / Micro XRCE-DDS and Dynamixel Protocol 2.0 sync write + sync read,
   byte counts computed from their published frame formats (see REFERENCES below);
4. encode/decode time per message on CPython and on the MicroPython unix VM.

Run: ``.venv/bin/python benchmarks/bench_protocol.py`` (``--quick`` for fewer timing loops).
"""

from __future__ import annotations

import argparse
import sys
import timeit
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from host import floors  # noqa: E402
from protocol import device as D  # noqa: E402
from protocol import frame as F  # noqa: E402
from protocol import messages as M  # noqa: E402
from protocol.constants import HEADER_LEN, MAX_ENCODED, MAX_FRAME  # noqa: E402

BAUDS = (115200, 921600, 2000000)
NS = (1, 3, 8)
BITS_PER_BYTE = floors.BITS_PER_BYTE

REFERENCES = """\
Reference byte counts (computed here from the published frame formats, not measured):
- Micro XRCE-DDS / micro-ROS serial transport (eProsima Micro-XRCE-DDS docs, "Custom Serial
  Transport"): HDLC-like frame FLAG(1) SADD(1) RADD(1) LEN(2) payload CRC(2) = 7 bytes, plus the
  XRCE message header (4) + submessage header (4) + WRITE_DATA request/object ids (4) = 12 bytes
  ("only 19 bytes" best case, byte stuffing of 0x7E/0x7D neglected, best-effort stream: no
  ACKNACK/HEARTBEAT traffic counted). Topic data in XCDR: SYNC equivalent = uint32 cycle +
  sequence<int32> (4-byte length + 2N x 4); STATE equivalent = uint32 cycle, uint32 t_ms,
  int32 kappa, phi, sequence<int32> tendons(3), sequence<int32> servos(3), uint8 status (+3 pad),
  int32 kx, ky = 60 bytes.
- Dynamixel Protocol 2.0 (ROBOTIS e-Manual, "Protocol 2.0"): instruction packet = header
  FF FF FD 00 (4) + ID (1) + LEN (2) + INST (1) + params + CRC16 (2) = 10 + params; status packet
  = 11 + data (INST 0x55 + ERR). Sync Write of 8 bytes (two int32 setpoints) to N devices:
  params = addr(2) + len(2) + N x (ID + 8). Sync Read of the 49-byte STATE content (same fields as
  fixed-width ints): instruction params = addr(2) + len(2) + N IDs, then N status packets of
  11 + 49. One half-duplex bus, so every byte is serialised; Return Delay Time (default 250 x
  2 us per reply on X-series) and byte stuffing are not counted (best case).
"""


# --------------------------------------------------------------------------------------------
# wire sizes
# --------------------------------------------------------------------------------------------
def _sync_bytes(n: int, worst: bool) -> int:
    if worst:  # the cycle near 2**30 needs a 4-byte argument (setpoints are fixed-width), and
        # the resume key comes once when a HOLD ends
        sps = [(99.0, -3.0)] * n
        return len(M.encode_sync(255, 2**30 - 1, sps, resume=True))
    sps = [(12.3456, 1.2345)] * n  # kappa 123456 (5 bytes), phi 12345 (3 bytes)
    return len(M.encode_sync(17, 123456, sps))


def _state_bytes(worst: bool) -> int:
    if worst:
        big = 2**30 - 1
        raw = bytearray(MAX_FRAME)
        out = bytearray(MAX_ENCODED)
        return D.state_frame(raw, out, 255, big, big, 0x7FFFFF, -31415, [-big] * 3, 3, 63, 255)
    return len(
        M.encode_state(
            17,
            cycle=123456,
            t_ms=7_654_321,
            kappa=12.3456,
            phi=1.2345,
            servo_angles=[-0.52, 0.31, 0.21],
            status=16,
        )
    )


def xrce_sync(n: int) -> int:
    return 19 + 4 + 4 + 8 * n


def xrce_state() -> int:
    return 19 + 60


def dxl_sync_write(n: int) -> int:
    return 10 + 4 + n * (1 + 8)


def dxl_sync_read_instruction(n: int) -> int:
    return 10 + 4 + n


def dxl_status() -> int:
    """One servo's status packet answering the sync read."""
    return 11 + 49


# --------------------------------------------------------------------------------------------
# cycle model
# --------------------------------------------------------------------------------------------
def chain_cycle_time(n: int, b_sync: int, b_state: int, baud: int) -> float:
    """Time from the host starting a SYNC until it holds all N STATEs on a cut-through chain
    (protocol v2) with zero processing: the cut-through floor (host/floors.py, the one place)."""
    return floors.cut_through_floor_s(n, baud, b_sync, b_state)


def pipelined_rate(n: int, b_sync: int, b_state: int, baud: int) -> float:
    """Throughput bound when the host pipelines cycles: the busiest link direction decides."""
    return floors.pipelined_rate_hz(n, baud, b_sync, b_state)


def print_measured(seconds: float) -> None:
    """Measured back-to-back cycle rates on the emulated chain beside the zero-processing model."""
    from bench_chain import boot, run_cycles, settle  # noqa: PLC0415 - starts emulated chains

    from host.link import ChainLink  # noqa: PLC0415
    from tools.emulator import EmulatedChain  # noqa: PLC0415

    print("== measured (emulated chain, real firmware, timing model off, back to back for")
    print(f"   {seconds:.0f} s; incomplete cycles counted as misses) beside modelled 'seq' [Hz]")
    print(f"{'N':>3}{'baud':>9}{'measured':>10}{'misses':>8}{'modelled':>10}{'ratio':>7}")
    for n in NS:
        with EmulatedChain(n) as chain, ChainLink(chain.host_port) as link:
            boot(link, n)
            for b in BAUDS:
                chain.set_all_links(baud=b)
                settle(link, n)
                run = run_cycles(link, n, duration_s=seconds)
                sy = run.tx_bytes / max(1, run.cycles)
                st = run.rx_bytes / max(1, run.cycles) / n
                model = 1 / chain_cycle_time(n, sy, st, b)
                print(
                    f"{n:>3}{b:>9}{run.rate_hz:>10.0f}{run.misses:>8}{model:>10.0f}"
                    f"{run.rate_hz / model:>7.2f}"
                )
    print()


def wire_tables() -> dict[str, tuple[list[str], list[list[str]]]]:
    """The wire-size and implied-rate tables docs/protocol.md quotes (computed, not measured:
    `tools/docfigures.py` renders them from here)."""
    st_t, st_w = _state_bytes(False), _state_bytes(True)
    sizes = []
    for n in NS:
        sy_t, sy_w = _sync_bytes(n, False), _sync_bytes(n, True)
        sizes.append([str(n), f"{sy_t} / {sy_w}", f"{st_t} / {st_w}",
                      f"{sy_t + n * st_t} / {sy_w + n * st_w}"])  # fmt: skip
    rates = []
    for n in NS:
        sy = _sync_bytes(n, False)
        cells = [str(n)]
        for b in BAUDS:
            seq = 1 / chain_cycle_time(n, sy, st_t, b)
            cells.append(f"{seq:.0f} / {pipelined_rate(n, sy, st_t, b):.0f}")
        rates.append(cells)
    others = []
    b, n8 = 921600, NS[-1]
    sy8 = _sync_bytes(n8, False)
    others.append([
        "this protocol (CBOR, COBS, cut-through)",
        " / ".join(str(_sync_bytes(n, False)) for n in NS), str(st_t),
        (f"{1 / chain_cycle_time(n8, sy8, st_t, b):.0f} Hz seq, "
        f"{pipelined_rate(n8, sy8, st_t, b):.0f} Hz pipelined"),
    ])  # fmt: skip
    xs = xrce_sync(n8)
    others.append([
        "micro-ROS / Micro XRCE-DDS serial, best-effort (on the same chain)",
        " / ".join(str(xrce_sync(n)) for n in NS), str(xrce_state()),
        (f"{1 / chain_cycle_time(n8, xs, xrce_state(), b):.0f} Hz seq, "
        f"{pipelined_rate(n8, xs, xrce_state(), b):.0f} Hz pipelined"),
    ])  # fmt: skip
    down, up = dxl_sync_write(n8) + dxl_sync_read_instruction(n8), n8 * dxl_status()
    others.append([
        "Dynamixel 2.0 sync write + sync read (one half-duplex bus)",
        " / ".join(str(dxl_sync_write(n) + dxl_sync_read_instruction(n)) for n in NS),
        str(dxl_status()),
        f"{b / BITS_PER_BYTE / (down + up):.0f} Hz",
    ])  # fmt: skip
    return {
        "sizes": (["N", "SYNC bytes (typical / worst)", "STATE bytes per segment, 3 servos",
                   "cycle bytes (SYNC + N × STATE)"], sizes),
        "rates": (["N"] + [f"{b} bd: seq / pipe (Hz)" for b in BAUDS], rates),
        "others": (["protocol", "down bytes, N = 1 / 3 / 8", "up bytes per segment",
                    "921600 bd, N = 8"], others),
    }  # fmt: skip


def print_wire_tables() -> None:
    print("== bytes on the wire (COBS + CRC + delimiter included)")
    print(
        f"{'N':>3} {'SYNC typ':>9} {'SYNC worst':>11} {'STATE typ':>10} {'STATE worst':>12}"
        f" {'cycle typ':>10} {'cycle worst':>12}"
    )
    st_t, st_w = _state_bytes(False), _state_bytes(True)
    for n in NS:
        sy_t, sy_w = _sync_bytes(n, False), _sync_bytes(n, True)
        print(
            f"{n:>3} {sy_t:>9} {sy_w:>11} {st_t:>10} {st_w:>12} {sy_t + n * st_t:>10}"
            f" {sy_w + n * st_w:>12}"
        )
    print()
    print("== implied max cycle rate [Hz], typical values; chain links are full duplex")
    print("   'seq' = host waits for all N STATEs before the next SYNC (cut-through,")
    print("   processing time 0); 'pipe' = host pipelines cycles, busiest link direction decides")
    hdr = f"{'protocol':<26}{'N':>3}{'down B':>8}{'up B':>7}"
    for b in BAUDS:
        hdr += f"{b:>10} seq{'':>1}{'pipe':>8}"
    print(hdr)
    for n in NS:
        sy, st = _sync_bytes(n, False), st_t
        row = f"{'ucr CBOR (this)':<26}{n:>3}{sy:>8}{n * st:>7}"
        for b in BAUDS:
            row += (
                f"{1 / chain_cycle_time(n, sy, st, b):>14.0f}{pipelined_rate(n, sy, st, b):>8.0f}"
            )
        print(row)
    for n in NS:
        sy, st = xrce_sync(n), xrce_state()
        row = f"{'micro-ROS/XRCE-DDS serial':<26}{n:>3}{sy:>8}{n * st:>7}"
        for b in BAUDS:
            row += (
                f"{1 / chain_cycle_time(n, sy, st, b):>14.0f}{pipelined_rate(n, sy, st, b):>8.0f}"
            )
        print(row)
    for n in NS:
        down, up = dxl_sync_write(n) + dxl_sync_read_instruction(n), n * dxl_status()
        row = f"{'Dynamixel 2.0 sync w+r':<26}{n:>3}{down:>8}{up:>7}"
        for b in BAUDS:
            rate = b / BITS_PER_BYTE / (down + up)  # half-duplex bus: everything serialised
            row += f"{rate:>14.0f}{rate:>8.0f}"
        print(row)
    print("   (Dynamixel is one half-duplex bus: seq == pipe; its 'down' = sync write +")
    print("    sync read instruction)")
    print()
    print(REFERENCES)


# --------------------------------------------------------------------------------------------
# timing
# --------------------------------------------------------------------------------------------
def _cpython_timings(loops: int) -> list[tuple[str, float]]:
    sps3 = [(12.3456, 1.2345)] * 3
    sync3 = M.encode_sync(17, 123456, sps3)
    state = M.encode_state(
        17,
        cycle=123456,
        t_ms=7_654_321,
        kappa=12.3456,
        phi=1.2345,
        servo_angles=[-0.52, 0.31, 0.21],
        status=16,
    )
    desc = M.encode_descriptor(
        {
            "uid": "24a1600c3b5e",
            "fw_version": "0.1.0",
            "protocol_version": 1,
            "model": "pcc",
            "length": 0.12,
            "tendon_angles": [0.0, 2.0944, 4.1888],
            "kappa_max": 20.0,
        }
    )
    reader = F.FrameReader()
    raw = bytearray(MAX_FRAME)
    out = bytearray(MAX_ENCODED)
    fr_sync = F.decode_frame(sync3)
    sraw = bytearray(fr_sync.raw())
    slots = [0, 0, 0, 0]
    fwd = bytearray(F.decode_frame(state).raw())

    def host_decode_state() -> None:
        for f in reader.feed(state):
            M.decode_message(f)

    def host_encode_sync_own() -> None:
        M.use_cbor2(False)
        M.encode_sync(17, 123456, sps3)
        M.use_cbor2(True)

    cases = [
        ("host encode_sync N=3 (cbor2)", lambda: M.encode_sync(17, 123456, sps3)),
        ("host encode_sync N=3 (own codec)", host_encode_sync_own),
        ("host feed + decode STATE", host_decode_state),
        ("host decode DESCRIPTOR", lambda: M.decode_message(F.decode_frame(desc))),
        (
            "dev state_frame (3 servos)",
            lambda: D.state_frame(
                raw,
                out,
                1,
                123456,
                7654321,
                123456,
                12345,
                [-5200, 3100, 2100],
                3,
                16,
                2,
            ),
        ),
        (
            "dev decode_sync N=3 pos 2",
            lambda: D.decode_sync(sraw, HEADER_LEN, len(sraw) - 3, 2, slots),
        ),
        ("dev scan one STATE frame", lambda: reader.scan(state, 0, len(state))),
        ("dev forward_into STATE", lambda: F.forward_into(fwd, len(fwd), 1, out)),
    ]
    res = []
    for name, fn in cases:
        t = min(timeit.repeat(fn, number=loops, repeat=3)) / loops
        res.append((name, t * 1e6))
    return res


MP_CODE = r"""
import time
from protocol import messages as M, frame as F, device as D
from protocol.constants import HEADER_LEN, MAX_FRAME, MAX_ENCODED
LOOPS = %d
if %s:  # pure-Python loops instead of the viper ones (protocol/_fast.py)
    from mp_runner import use_pure_loops  # tests/protocol: the one list of those switches
    use_pure_loops()
sps3 = [(12.3456, 1.2345)] * 3
sync3 = M.encode_sync(17, 123456, sps3)
state = M.encode_state(17, cycle=123456, t_ms=7654321, kappa=12.3456, phi=1.2345,
    servo_angles=[-0.52, 0.31, 0.21], status=16)
desc = M.encode_descriptor({"uid": "24a1600c3b5e", "fw_version": "0.1.0", "protocol_version": 2,
    "model": "pcc", "length": 0.12, "tendon_angles": [0.0, 2.0944, 4.1888], "kappa_max": 20.0})
reader = F.FrameReader()
raw = bytearray(MAX_FRAME)
out = bytearray(MAX_ENCODED)
sraw = bytearray(F.decode_frame(sync3).raw())
slots = [0, 0, 0, 0]
fwd = bytearray(F.decode_frame(state).raw())
sv = [-5200, 3100, 2100]
ns = len(sraw) - 3
nst = len(state)
nfwd = len(fwd)

def c0():
    M.encode_sync(17, 123456, sps3)
def c1():
    for f in reader.feed(state):
        M.decode_message(f)
def c2():
    M.decode_message(F.decode_frame(desc))
def c3():
    D.state_frame(raw, out, 1, 123456, 7654321, 123456, 12345, sv, 3, 16, 2)
def c4():
    D.decode_sync(sraw, HEADER_LEN, ns, 2, slots)
def c5():
    reader.scan(state, 0, nst)
def c6():
    F.forward_into(fwd, nfwd, 1, out)

for name, fn in (("host encode_sync N=3 (own codec)", c0), ("host feed + decode STATE", c1),
                 ("host decode DESCRIPTOR", c2), ("dev state_frame (3 servos)", c3),
                 ("dev decode_sync N=3 pos 2", c4), ("dev scan one STATE frame", c5),
                 ("dev forward_into STATE", c6)):
    best = None
    for _ in range(3):
        t0 = time.ticks_us()
        for _ in range(LOOPS):
            fn()
        dt = time.ticks_diff(time.ticks_us(), t0)
        best = dt if best is None or dt < best else best
    print("%%s|%%.2f" %% (name, best / LOOPS))
"""


def _mp_timings(loops: int, pure: bool = False) -> list[tuple[str, float]]:
    from tools.mpvm import REPO as ROOT
    from tools.mpvm import run_code

    paths = [ROOT, ROOT / "tests" / "protocol"]
    out = run_code(MP_CODE % (loops, pure), paths=paths, heap="2m", timeout=600)  # speed only
    res = []
    for line in out.strip().splitlines():
        name, _, us = line.partition("|")
        res.append((name, float(us)))
    return res


def print_timings(loops: int) -> None:
    cp = dict(_cpython_timings(loops))
    try:
        mp = dict(_mp_timings(max(loops // 5, 50)))
        mpp = dict(_mp_timings(max(loops // 5, 50), pure=True))
    except (OSError, RuntimeError) as e:
        print(f"MicroPython VM timing skipped: {e}")
        mp, mpp = {}, {}
    print("== encode/decode time per message [us] on this PC (an ESP32 will be slower; not")
    print("   measured here). 'MP viper' = the unix VM with the")
    print("   machine-code byte loops of protocol/_fast.py (default), 'MP pure' = without them")
    print(f"{'operation':<36}{'CPython':>9}{'MP viper':>10}{'MP pure':>9}{'pure/viper':>11}")
    for name in dict.fromkeys([*cp, *mp]):
        vals = [cp.get(name), mp.get(name), mpp.get(name)]
        cells = [f"{v:>9.2f}" if v is not None else f"{'-':>9}" for v in vals]
        ratio = f"{vals[2] / vals[1]:>11.1f}" if vals[1] and vals[2] else f"{'':>11}"
        print(f"{name:<36}{cells[0]}{cells[1]:>10}{cells[2]}{ratio}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer timing loops")
    ap.add_argument("--no-measure", action="store_true", help="model only, no emulated chain")
    args = ap.parse_args()
    print_wire_tables()
    if not args.no_measure:
        print_measured(1.0 if args.quick else 3.0)
    print_timings(300 if args.quick else 3000)


if __name__ == "__main__":
    main()
