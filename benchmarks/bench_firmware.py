"""Firmware figures on the MicroPython VM (unix port, ESP32-sized heap): microseconds per control
tick, per processed SYNC (decode + forward + STATE), per forwarded upstream frame, per full cycle,
heap bytes allocated per cycle (goal 0) and the heap left after boot.

Run: .venv/bin/python benchmarks/bench_firmware.py [--reps N] [--cycles N] [--samples N]
     [--no-boards]
The unix port on a PC is much faster than an ESP32: the board figures scale the VM's times by
each board's CPU factor (tools/emulator/timing.py, derivation in docs/emulator.md), and the
timing-model section runs the firmware with the model off and on (benchmarks/firmware_boards.py).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from benchmarks.figures import Figures  # noqa: E402
from protocol import messages as M  # noqa: E402
from tools import mpvm  # noqa: E402

VM_SETUP = """
import gc, json, sys, time, micropython
gc.collect()
import vmkit
gc.collect()
import config
gc.collect()
import segment  # before the configuration, as main.build does: the import's peak on a clean heap
gc.collect()
hal, seg = vmkit.make({{'watchdog_ms': 60000, 'servo_driver': '{driver}'}})
SYNC = bytes.fromhex('{sync}')
STATE = bytes.fromhex('{state}')
hal.up.feed(SYNC)
hal.down.feed(STATE)
N = {cycles}

def rewind(u, n):
    u.r = 0
    u.gate = n

def only_tick():
    for i in range(N):
        hal.t += 5
        seg.tick(hal.t)
        hal.up.discard()

SLEW = [0]

def slewing_tick():
    for i in range(N):
        k = SLEW[0]
        SLEW[0] = k + 1
        if k % 50 == 0:   # a far target every 50 ticks: the slew limit is always active
            seg.mc.set_target(30000, 31416 if (k // 50) & 1 else 0)
        hal.t += 5
        seg.tick(hal.t)
        hal.up.discard()

def only_sync():
    for i in range(N):
        rewind(hal.up, len(SYNC))
        seg.poll()
        hal.up.discard()
        hal.down.discard()

def only_forward():
    for i in range(N):
        rewind(hal.down, len(STATE))
        seg.poll()
        hal.up.discard()

def full():
    for i in range(N):
        rewind(hal.up, len(SYNC))
        rewind(hal.down, len(STATE))
        hal.t += 5
        seg.poll()
        seg.tick(hal.t)
        hal.up.discard()
        hal.down.discard()

BATCH = 40
REPS = {reps}
# the measurement runs in ROUNDS rounds of REPS // ROUNDS batches per figure, the best batch of
# all rounds counts: a slow stretch of this shared host (seconds long) then costs one round of
# every figure instead of all batches of one figure
ROUNDS = 5
REPS_R = max(1, REPS // ROUNDS)

def timed(f):
    # the best of REPS batches of BATCH cycles: a shared host interrupts long runs, and the
    # best short batch is what the code itself costs
    global N
    n0 = N
    N = BATCH
    best = None
    for _ in range(REPS_R):
        seg.last_feed = hal.t  # as a SYNC would: tick-only batches must not trip the watchdog
        t0 = time.ticks_us()
        f()
        dt = time.ticks_diff(time.ticks_us(), t0) / BATCH
        best = dt if best is None or dt < best else best
    N = n0
    return best

from array import array
from protocol import _fast, crc as _crc
from protocol.frame import FrameReader
from protocol.relay import Relay
_T = _crc._TABLE
_rd = FrameReader()
_rl = (Relay(False), Relay(True))  # (their states are back at the start after every frame)
_raw2 = bytearray(256)
_out = bytearray(300)
_sp = [0, 0, 0, 0]
_sv = array('i', [1000, -2000, 3000])

def machine_code():
    # the viper calls one full cycle makes on these frames: for the SYNC and the neighbour's
    # STATE the frame reader's scan and the relay's step (CRC for the next hop included), the
    # SYNC entry, and the own STATE frame built
    raw = _rd.raw
    st = _rd.st
    for i in range(N):
        for w, up in ((SYNC, 0), (STATE, 1)):
            r = _fast.scan(w, 0, len(w), raw, st, _T)
            _fast.relay_feed(w, 0, len(w), _out, _rl[up].st, r & 1, raw, st[7], _T)
            if not up:
                _fast.sync_entry(raw, 5, st[8], 1, _sp)
        _fast.state_wire(_raw2, _out, 1, 42, 100, 5000, 1000, 16, _sv, 3, _T)

import protocol.device as pd
from protocol.constants import HEADER_LEN
bus = seg.bus
mc = seg.mc
rd = seg.rd_up

def part(f):
    # one piece of the cycle alone, in us per call (the best of REPS_R batches of BATCH calls)
    best = None
    for _ in range(REPS_R):
        t0 = time.ticks_us()
        for i in range(BATCH):
            f()
        dt = time.ticks_diff(time.ticks_us(), t0) / BATCH
        best = dt if best is None or dt < best else best
    return best

def _scan():
    rd.scan(SYNC, 0, len(SYNC))

def _state():
    seg._send_state(42, 1)
    hal.up.discard()

PARTS = (
    ('servo driver poll ({driver} servos)', lambda: bus.poll(hal.t)),
    ('servo fault checks', lambda: seg._faults(hal.t)),
    ('MC measure (positions -> kappa, phi)', lambda: mc.measure(bus.pos)),
    ('MC update (slew, servo targets)', lambda: mc.update()),
    ('SC step and driver command', lambda: bus.command(seg.sc.step(mc.servo_target), hal.t)),
    ('chain housekeeping (service)', lambda: seg.service(hal.t)),
    ('frame reader: SYNC bytes -> frame', _scan),
    ('SYNC payload decode',
     lambda: pd.decode_sync(rd.raw, HEADER_LEN, rd.payload_end, 1, seg.sync_out)),
    ('setpoint (kappa clamp, rate check)',
     lambda: mc.set_target(seg.sync_out[1], seg.sync_out[2], 5)),
    ('STATE encoded and sent', _state),
    ('relay point, nothing arrived', seg.relay_point),
    ('empty call (the VM floor)', lambda: None),
)

def _relay_path():
    rewind(hal.up, len(SYNC))
    seg.poll()
    hal.down.discard()

_rx = bytearray(256)

def _uart_calls():
    # the loopback UART's calls the relay path makes (a board's UART methods are C, costing
    # about one empty call each): read the SYNC, find the down port empty, write it on
    rewind(hal.up, len(SYNC))
    hal.up.readinto(_rx)
    hal.down.readinto(_rx)
    hal.down.write(_rx, len(SYNC))
    hal.down.discard()

def relay_path():
    # a SYNC's bytes read, scanned and relayed downstream, its handling left out: what a relay
    # point costs when a frame arrived, with the loopback UART's bytecode replaced by the cost
    # of three C calls
    real = seg._on_up
    seg._on_up = lambda r: None
    try:
        harness = part(lambda: rewind(hal.up, len(SYNC)) or hal.down.discard())
        path = part(_relay_path) - harness
        uart = part(_uart_calls) - harness
        return path - uart + 3 * part(lambda: None)
    finally:
        seg._on_up = real

def _wake_work():
    s = 0
    for i in range(20):
        s += i
    return s

def wake():
    # the same small piece of bytecode hot and right after a 5 ms sleep (the timing model
    # sleeps between compute intervals): medians of 50, in us
    gc.collect()
    hot, cold = [], []
    for i in range(50):
        t0 = time.ticks_us()
        _wake_work()
        hot.append(time.ticks_diff(time.ticks_us(), t0))
    for i in range(50):
        time.sleep_us(5000)
        t0 = time.ticks_us()
        _wake_work()
        cold.append(time.ticks_diff(time.ticks_us(), t0))
    hot.sort()
    cold.sort()
    return [hot[25], cold[25]]

"""

VM_MEASURE = """
k0 = kernel_loops_per_s()
R = {{}}
a0 = a1 = 0  # globals created before the measurement: a new global would grow the module dict
full()   # warm up, and start moving
gc.collect()
MAIN = (('tick_us', only_tick), ('slew_tick_us', slewing_tick), ('sync_us', only_sync),
        ('forward_us', only_forward), ('cycle_us', full), ('viper_us', machine_code))
RELAY = 'relay path: a SYNC read, scanned, relayed (not handled; UART calls as C)'
PB = None
rnd = 0
for rnd in range(ROUNDS):  # the whole measurement in rounds, the best per figure
    for key, f in MAIN:
        v = timed(f)
        if key not in R or v < R[key]:
            R[key] = v
    ps = [part(f) for name, f in PARTS]
    ps.insert(-1, relay_path())
    PB = ps if PB is None else [min(a, b) for a, b in zip(PB, ps)]
R['kernel'] = max(k0, kernel_loops_per_s())  # the host's speed, before and after, same process
names = [name for name, f in PARTS]
names.insert(-1, RELAY)
R['parts'] = [[n, v] for n, v in zip(names, PB)]
R['wake'] = wake()
gc.collect()
gc.disable()
a0 = gc.mem_alloc()
full()
a1 = gc.mem_alloc()
gc.enable()
R['heap_bytes_per_cycle'] = (a1 - a0) / N
R['heap_lock_ok'] = False   # key created before the lock: inserting it would allocate
micropython.heap_lock()
try:
    full()
    R['heap_lock_ok'] = True
except MemoryError:
    R['heap_lock_ok'] = False
micropython.heap_unlock()
gc.collect()
R['heap_free'] = gc.mem_free()
R['heap_used'] = gc.mem_alloc()
# streamed: the text in one piece needs a free block that a fragmented heap may lack
sys.stdout.write('@@')
json.dump(R, sys.stdout)
print()
"""

# The test ports' calls, in a VM run of their own (their code must not change the heap
# figures of the main run): counted per full cycle and timed as the test port's bytecode.
VM_PORTS = """
def harness():
    # what full() does besides the firmware: rewinding and emptying the test ports
    for i in range(N):
        rewind(hal.up, len(SYNC))
        rewind(hal.down, len(STATE))
        hal.t += 5
        hal.up.discard()
        hal.down.discard()

_calls = {{'rd_data': 0, 'rd_empty': 0, 'write': 0, 'any': 0, 'pwm': 0}}

def _counting(u):
    real_rd, real_wr, real_any = u.readinto, u.write, u.any
    def rd(buf):
        n = real_rd(buf)
        _calls['rd_data' if n else 'rd_empty'] += 1
        return n
    def wr(buf, n=-1):
        _calls['write'] += 1
        return real_wr(buf, n)
    def an():
        _calls['any'] += 1
        return real_any()
    u.readinto = rd
    u.write = wr
    u.any = an

def _counting_pwm(p):
    real = p.duty_ns
    def duty(ns):
        _calls['pwm'] += 1
        return real(ns)
    p.duty_ns = duty

PWMS = getattr(seg.bus, 'pwm', None) or []

def port_calls():
    # the test ports' calls one full cycle makes, counted (instance attributes shadow the
    # methods for the count, then go), and what each costs as the test port's bytecode; the
    # PWM outputs' duty_ns (machine.PWM on a board: C) likewise
    for u in (hal.up, hal.down):
        _counting(u)
    for p in PWMS:
        _counting_pwm(p)
    full()
    for u in (hal.up, hal.down):
        del u.readinto
        del u.write
        del u.any
    for p in PWMS:
        del p.duty_ns
    return dict((k, v / N) for k, v in _calls.items())

def port_costs():
    base = part(lambda: rewind(hal.up, len(SYNC)) or hal.down.discard())
    return {{
        'any': part(lambda: hal.down.any()),
        'rd_empty': part(lambda: hal.down.readinto(_rx)),
        'rd_data': part(lambda: rewind(hal.up, len(SYNC)) or hal.up.readinto(_rx)
                        or hal.down.discard()) - base,
        'write': part(lambda: hal.down.write(_rx, len(SYNC)) or hal.down.discard())
                 - part(lambda: hal.down.discard()),
        'pwm': part(lambda: PWMS[0].duty_ns(1500000)) if PWMS else 0.0,
        'harness': timed(harness),
        'empty': part(lambda: None),
    }}

full()  # warm up, and start moving
R = {{}}
R['port_calls'] = port_calls()
C = port_costs()
for rnd in range(ROUNDS - 1):  # rounds, the best per figure (ROUNDS in VM_SETUP)
    D = port_costs()
    for k in C:
        if D[k] < C[k]:
            C[k] = D[k]
R['harness_us'] = C.pop('harness')
R['empty_call_us'] = C.pop('empty')
R['port_cost'] = C
gc.collect()  # the heap is the board's budget: room for the JSON text
# streamed: the text in one piece needs a free block that a fragmented heap may lack
sys.stdout.write('@@')
json.dump(R, sys.stdout)
print()
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--cycles", type=int, default=500, help="cycles of the heap measurements (default 500)"
    )
    ap.add_argument(
        "--driver",
        choices=("pwm", "emulated"),
        default="pwm",
        help="the segment's servo driver: pwm (an ESP32 segment's default; its outputs' "
        "duty_ns counted as C calls) or emulated (the emulator's servo model, which a board "
        "does not run)",
    )
    ap.add_argument(
        "--reps",
        type=int,
        default=300,
        help="timed batches of 40 cycles per figure, the best counts (default 300)",
    )
    ap.add_argument("--samples", type=int, default=200, help="samples per timing-model figure")
    ap.add_argument("--no-boards", action="store_true", help="skip the board/timing-model part")
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = ap.parse_args()
    figs = Figures.from_argv("bench_firmware")
    if args.cycles < 1 or args.reps < 1:
        ap.error("--cycles and --reps must be >= 1")
    sync = M.encode_sync(1, 42, [(2.0, 0.5), (1.0, -0.5), (0.5, 2.0)])
    state = M.encode_state(
        3,
        cycle=42,
        t_ms=100,
        kappa=0.5,
        phi=0.1,
        servo_angles=[0.1, -0.2, 0.3],
        status=16,
    )
    import tempfile

    from tools.emulator.chain import populate_segment_dir
    from tools.emulator.timing import KERNEL_FUNC

    # the firmware as a board runs it: precompiled (.mpy, tools/mpy.py), as `ucr flash` deploys
    flash = Path(tempfile.mkdtemp(prefix="bench-firmware-"))
    populate_segment_dir(flash)
    paths = [flash, mpvm.REPO / "tests" / "device"]
    r: dict = {}
    for body in (VM_MEASURE, VM_PORTS):
        code = KERNEL_FUNC + (VM_SETUP + body).format(
            sync=sync.hex(),
            state=state.hex(),
            cycles=args.cycles,
            reps=args.reps,
            driver=args.driver,
        )
        try:
            out = mpvm.run_code(code, paths=paths, timeout=300)
        except (RuntimeError, FileNotFoundError) as e:
            print(f"bench_firmware: the VM run failed: {e}", file=sys.stderr)
            return 1
        finally:
            if body is VM_PORTS:
                shutil.rmtree(flash, ignore_errors=True)
        line = next(x for x in out.splitlines() if x.startswith("@@"))
        r.update(json.loads(line[2:]))
    r["driver"] = args.driver
    # On a board the UART methods are C: the test ports' bytecode and the harness that rewinds
    # them are not the firmware's. The board figures use the cycle without them, each port
    # call costing one empty call instead (as the relay-path part does).
    calls = sum(r["port_calls"].values())
    r["port_us"] = sum(r["port_calls"][k] * max(0.0, r["port_cost"][k]) for k in r["port_calls"])
    r["firmware_us"] = max(
        0.0, r["cycle_us"] - r["harness_us"] - r["port_us"] + calls * r["empty_call_us"]
    )
    tick_budget = 5000.0
    print(
        f"MicroPython VM (unix port), heap {mpvm.ESP32_HEAP}, best of {args.reps} batches "
        f"of 40 cycles in 5 rounds"
    )
    print(f"  control tick (servos, MC, SC, safety)    {r['tick_us']:8.1f} us")
    print(f"  control tick while slew-limiting         {r['slew_tick_us']:8.1f} us")
    print(f"  SYNC processed (decode, forward, STATE)  {r['sync_us']:8.1f} us")
    print(f"  upstream frame forwarded (hop+1, CRC)    {r['forward_us']:8.1f} us")
    print(f"  full cycle (SYNC + forward + tick)       {r['cycle_us']:8.1f} us")
    print(f"  full cycle / 5 ms tick budget            {r['cycle_us'] / tick_budget:8.3%}")
    print(f"  of the cycle, viper machine code         {r['viper_us']:8.1f} us (the rest bytecode)")
    print(
        f"  of it, test harness / test ports' code   {r['harness_us']:8.1f} / "
        f"{r['port_us']:.1f} us ({calls:.0f} port calls per cycle)"
    )
    print(f"  full cycle, port calls as C (firmware)   {r['firmware_us']:8.1f} us")
    print(
        f"  bytes per cycle on its upstream link     {len(sync) + 2 * len(state):8d} "
        f"(SYNC {len(sync)} down; own and the neighbour's STATE, {len(state)} each, up)"
    )
    print(f"  heap bytes allocated per cycle           {r['heap_bytes_per_cycle']:8.1f} (goal 0)")
    print(f"  full cycle under heap_lock               {'ok' if r['heap_lock_ok'] else 'FAILED'}")
    print(f"  heap used after boot + run               {r['heap_used']:8d} bytes")
    print(f"  heap free                                {r['heap_free']:8d} bytes")
    print("  where it goes (each piece timed alone, one call each; they overlap the above):")
    for name, us in r["parts"]:
        print(f"    {name:40s} {us:6.1f} us")
    ok = r["heap_lock_ok"] and r["heap_bytes_per_cycle"] == 0
    if figs is not None:
        note = (
            f"unix port, heap {mpvm.ESP32_HEAP}, the firmware precompiled (.mpy) as `ucr flash` "
            f"deploys it; best of {args.reps} batches of 40 cycles in 5 rounds; a cycle: SYNC "
            "in and relayed, STATE out, a neighbour's STATE relayed, tick"
        )
        figs.table("vm", ["on the MicroPython unix VM", "per cycle"], note=note)
        for label, value in (
            ("control tick (servos, mechanism and servo controllers)", f"{r['tick_us']:.1f} µs"),
            ("control tick while slew-limiting", f"{r['slew_tick_us']:.1f} µs"),
            ("SYNC processed (decode, forward, STATE)", f"{r['sync_us']:.1f} µs"),
            ("upstream frame relayed (hop + 1, CRC)", f"{r['forward_us']:.1f} µs"),
            ("full cycle", f"{r['cycle_us']:.1f} µs"),
            ("of it, viper machine code (the rest is bytecode)", f"{r['viper_us']:.1f} µs"),
            ("of it, the test harness and the test ports' bytecode (on a board: C calls)",
             f"{r['harness_us']:.1f} + {r['port_us']:.1f} µs ({calls:.0f} port calls)"),
            ("full cycle of the firmware, port calls as C (what the board figures use)",
             f"{r['firmware_us']:.1f} µs"),
            ("heap bytes allocated per cycle (goal 0)", f"{r['heap_bytes_per_cycle']:.0f}"),
            ("full cycle under heap_lock", "ok" if r["heap_lock_ok"] else "FAILED"),
            ("heap used / free after boot and the run (64-bit VM objects)",
             f"{r['heap_used'] / 1024:.1f} KB / {r['heap_free'] / 1024:.1f} KB"),
        ):  # fmt: skip
            figs.row("vm", [label, value])
        figs.table("parts", ["piece of the cycle (timed alone)", "on the VM", "esp32 model"],
                   note="the same run; each piece called on its own, so one call's overhead "
                   "is in each figure; the esp32 column × the board's CPU factor")  # fmt: skip
    if not args.no_boards:
        _boards(r, args.samples, figs)
    if figs is not None:
        figs.save()
    return 0 if ok else 2


def _forwarding_bound(r: dict, pystones: float, figs: Figures | None) -> None:
    """Per-hop forwarding from the hot VM figures × the esp32 factor: a frame waits for the
    running phase of the tick to reach its next relay point, then takes the relay path. The
    process measurement below stretches wall time, which this host inflates after every sleep
    (the 'wake' figures), so it is an upper bound; this is the estimate from the same figures
    as the cycle's share of the tick."""
    from tools.emulator.timing import cpu_factor

    parts = dict(r["parts"])
    f = cpu_factor("esp32", pystones)
    phases = {  # Segment.tick's phases between its relay points
        "servo read + fault checks": parts[f"servo driver poll ({r['driver']} servos)"]
        + parts["servo fault checks"],
        "MC measure": parts["MC measure (positions -> kappa, phi)"],
        "MC update": parts["MC update (slew, servo targets)"],
        "SC step + command": parts["SC step and driver command"],
        "housekeeping until the next poll": parts["chain housekeeping (service)"],
    }
    name, longest = max(phases.items(), key=lambda kv: kv[1])
    relay = parts["relay path: a SYNC read, scanned, relayed (not handled; UART calls as C)"]
    handling = max(0.0, r["sync_us"] - relay)
    hot, cold = r["wake"]
    rows = [
        ("relay path (bytes in, relayed out)", relay),
        (f"longest tick phase between relay points ({name})", longest),
        ("per-hop bound while the segment ticks (the two above)", relay + longest),
        ("a SYNC being handled (no relay point inside)", handling),
    ]
    print(f"Per-hop forwarding from the hot figures, esp32 (CPU factor {f:.0f})")
    for label, us in rows:
        print(f"  {label:55s} {us:6.1f} us VM = {us * f / 1000:6.2f} ms")
    print(f"  this host after a 5 ms sleep: {cold} us for what takes {hot} us hot")
    if figs is not None:
        figs.table("forwarding_bound", ["piece", "on the VM", "esp32 model"], note=(
            f"the hot figures above × the esp32 CPU factor ({f:.0f}); for comparison this host "
            f"ran a piece of bytecode that takes {hot} µs hot in {cold} µs right after a 5 ms "
            "sleep (median of 50), an inflation the process measurement below multiplies by "
            "the factor too"))  # fmt: skip
        for label, us in rows:
            figs.row("forwarding_bound", [label, f"{us:.1f} µs", f"{us * f / 1000:.2f} ms"])


def _boards(r: dict, samples: int, figs: Figures | None = None) -> None:
    import firmware_boards as fb

    from tools.emulator.timing import KERNEL_PER_PYSTONE, cpu_factor

    # the host's speed measured in the same VM process as the cycle (a shared machine can run
    # a whole process at half speed: a factor from another process would not cancel it)
    pystones = r["kernel"] / KERNEL_PER_PYSTONE

    print(f"Boards (this VM: about {pystones:.0f} pystones/s, measured beside the cycle)")
    cycle = r["firmware_us"]  # the test ports' bytecode as C calls (main())
    byte_us = max(0.0, cycle - r["viper_us"])
    if figs is not None:
        figs.table(
            "boards",
            ["board (CPU factor)", "full cycle", "share of the 5 ms tick (goal ≤ 20 %)",
             "bytecode alone"],
            note=f"the emulator's timing model (tools/emulator/timing.py): the firmware's VM "
            "time (the full cycle with the test ports' calls as C calls) × the board's CPU "
            f"factor, this VM at about {pystones:.0f} pystones/s (its calibration kernel, run "
            "in the same process as the cycle)",
        )  # fmt: skip
        figs.table("heap", ["board", "heap after boot"], note=(
            "main.build() with the board's heap budget on the unix VM (64-bit objects; an "
            "ESP32's 32-bit objects need less)"))  # fmt: skip
        figs.table("wait", ["esp32 tick model, CPU factor 1", "wait overshoot p50 / p99"],
                   note=f"{samples} waits past their deadline")  # fmt: skip
        figs.table("forwarding", ["esp32", "per-hop SYNC forwarding p50 / p99", "lost"],
                   note=f"{samples // 2} SYNCs; goal ≤ 1 ms")  # fmt: skip
    if figs is not None:
        f = cpu_factor("esp32", pystones)
        for name, us in r["parts"]:
            figs.row("parts", [name, f"{us:.1f} µs", f"{us * f / 1000:.2f} ms"])
    for name in ("esp32", "esp32s3", "esp32c3"):
        f = cpu_factor(name, pystones)
        share = cycle * f / 5000.0
        print(
            f"  {name:8s} CPU factor {f:6.1f}: full cycle {cycle * f / 1000:7.2f} ms = "
            f"{share:7.1%} of the 5 ms tick (goal <= 20 %); bytecode alone "
            f"{byte_us * f / 1000:6.2f} ms = {byte_us * f / 5000.0:6.1%}"
        )
        if figs is not None:
            figs.row("boards", [
                f"{name} ({f:.0f})", f"{cycle * f / 1000:.1f} ms", f"{share:.0%}",
                f"{byte_us * f / 1000:.1f} ms",
            ])  # fmt: skip
    print("Heap after boot, main.build() with the board's heap budget (64-bit VM objects)")
    for name, text in fb.heap_after_boot():
        print(f"  {name:16s} {text}")
        if figs is not None:
            figs.row("heap", [name, text])
    print(f"Wait overshoot past its deadline, esp32 tick model, CPU factor 1 ({samples} waits)")
    for label, p50, p99 in fb.wait_overshoot(samples):
        print(f"  {label:20s} p50 {p50 / 1000:6.2f} ms  p99 {p99 / 1000:6.2f} ms (goal p99 <= 0.5)")
        if figs is not None:
            figs.row("wait", [label, f"{p50 / 1000:.2f} / {p99 / 1000:.2f} ms"])
    _forwarding_bound(r, pystones, figs)
    factor, rows = fb.forwarding(samples // 2)
    print(f"Per-hop SYNC forwarding latency, esp32 (CPU factor {factor:.0f}), {samples // 2} SYNCs")
    for label, p50, p99, lost in rows:
        print(f"  {label:20s} p50 {p50:6.2f} ms  p99 {p99:6.2f} ms  lost {lost} (goal <= 1 ms)")
        if figs is not None:
            figs.row("forwarding", [f"{label} (CPU factor {factor:.0f})",
                                    f"{p50:.2f} / {p99:.2f} ms", str(lost)])  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
