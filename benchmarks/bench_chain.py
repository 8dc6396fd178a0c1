"""Emulated chain figures: discovery time, SYNC -> STATE round trip and sustained cycle rate for
1, 3 and 8 segments at 115200, 921600 and 2000000 baud, each as a ratio to the line-rate floor;
with and without the emulator's ESP32 timing model (docs/emulator.md "Timing model").

Run: .venv/bin/python benchmarks/bench_chain.py [--repeat N] [--duration S] [--rate HZ]
     [--timing off|on|both] [--segments 1,3,8] [--bauds 115200,921600,2000000]

Floors (docs/protocol.md "Floors", computed by host/floors.py, the one place): the line-rate
floor is the bytes the exchange puts on link 0 (SYNC + every STATE; the SYNC's size measured
here, the STATE's the fixed size the spec gives every STATE, ``floors.max_state_bytes``: bytes
received also hold cut or late frames, which would inflate the floor) x 10 / baud; the
cut-through floor adds the relay's 4 bytes per hop and direction (what the firmware's
cut-through allows with zero processing); the store-and-forward floor is n x (SYNC + STATE) x 10
/ baud, what forwarding whole frames costs. Nothing is dropped: a cycle in which any STATE is
missing or late is a miss and is counted (printed beside the median; a round trip that came
late but complete stays in the median, which is what the chain takes; the paced cycle median
counts each miss as at least its deadline, so it is printed as "≥" when most cycles missed).
Late means after the cycle's deadline:

* round trip (one cycle at a time, 10 ms apart): its period, 10 ms, or where even the
  store-and-forward floor of the largest frames does not fit in it (8 segments at 115200 baud),
  twice that floor (``rtt_deadline_s``); the host still waits up to 1 s, so a late cycle's time
  is seen, but it is a miss;
* paced: before the next tick (one period from its SYNC); a tick the host could not start on
  time is a miss too;
* pipelined: before the tick after next (two periods from its SYNC); a SYNC the host could not
  send is a miss of its cycle.

Each figure is printed as a ratio to its floor: round trip and paced cycle times to the
line-rate / cut-through / store-and-forward floors, back-to-back rates to the line-rate ceiling
(1 / line-rate floor), pipelined rates to the pipelined ceiling (``floors.pipelined_rate_hz``,
the busiest direction of link 0) and paced / pipelined complete rates to the rate asked.

Sustained: the host starts a SYNC on every tick of ``--rate`` Hz for ``--duration`` s and waits
at most until the next tick (the issue's goal: 8 segments @ 921600, 100 Hz for 60 s, 0 misses).
Back to back: the next SYNC as soon as the last cycle ended; its rate is the chain's ceiling.

The emulated chain runs in its own process (``ucr emulate``, driven through its control socket;
``--emulator thread`` runs it in this one, as the tests do), so this process is the host side
alone: "host CPU per cycle" is its CPU time over the paced run per cycle (the link's reader
thread, the SYNC encoding and the STATE decoding; printed, not in the docs' tables: on this
virtual machine a thread's wake-up alone costs the process 0.03-0.1 ms of CPU, a select(2)
timeout with nothing to read 0.09 ms, 2026-11-27, and a cycle has several of them).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.figures import Figures  # noqa: E402
from host import floors  # noqa: E402
from host.link import ChainLink, LinkError  # noqa: E402
from tools.emulator import EmulatedChain  # noqa: E402
from tools.emulator.pipe import CHUNK_MAX_BYTES  # noqa: E402
from tools.emulator.process import emulated_chain  # noqa: E402

SETPOINT = (0.5, 0.3)  # kappa 1/m, phi rad
RTT_PERIOD_S = 0.01  # round trips are this far apart: the period each must fit in
FACTORS: dict[str, set[int]] = {}  # table -> the CPU factors its chains measured


def rtt_deadline_s(n: int, baud: int) -> float:
    """A round trip's deadline: its period, or twice the store-and-forward floor of the largest
    frames where that floor alone does not fit in the period."""
    sf = floors.store_and_forward_floor_s(n, baud)
    return RTT_PERIOD_S if sf <= RTT_PERIOD_S else 2.0 * sf


def median_counting_misses(times: list[float], misses: int, bound: float) -> tuple[float, bool]:
    """The median cycle time where each missed cycle counts as at least ``bound`` (its deadline):
    (median, True) when the median is such a miss, so the value is only a lower bound. A median
    of the complete cycles alone would report the survivors of a chain that mostly misses."""
    values = sorted(times) + [float("inf")] * misses
    if not values:
        return float("nan"), False
    mid = values[len(values) // 2]
    return (bound, True) if mid == float("inf") else (mid, False)


@dataclass
class Cycles:
    """Outcome of a run of cycles: durations of the complete ones, misses, wire bytes seen."""

    times: list[float]
    misses: int
    cycles: int
    elapsed_s: float
    tx_bytes: int
    rx_bytes: int
    cpu_s: float = 0.0  # this process's CPU time over the run (the host side: link reader, loop)

    @property
    def cpu_per_cycle_s(self) -> float:
        return self.cpu_s / self.cycles if self.cycles else float("nan")

    @property
    def rate_hz(self) -> float:
        return (self.cycles - self.misses) / self.elapsed_s if self.elapsed_s else 0.0


def boot(link: ChainLink, n: int, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if len(link.discover(timeout=1.0)) == n:
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"chain of {n} did not boot within {timeout:.0f} s")


def settle(link: ChainLink, n: int, timeout: float = 60.0) -> None:
    """Wait until a cycle completes again (a chain that fell behind works off queued SYNCs)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if _cycle(link, n, 1.0)[1]:
            return
    raise SystemExit(f"chain of {n} answers no complete cycle within {timeout:.0f} s")


def _cycle(link: ChainLink, n: int, timeout: float) -> tuple[float, bool]:
    t0 = time.perf_counter()
    try:
        states = link.sync([SETPOINT] * n, timeout=timeout)
        ok = all(s is not None for s in states)
    except LinkError:
        ok = False
    return time.perf_counter() - t0, ok


def run_cycles(
    link: ChainLink,
    n: int,
    *,
    count: int = 0,
    duration_s: float = 0.0,
    rate_hz: float = 0.0,
    deadline_s: float = 0.0,
) -> Cycles:
    """``count`` cycles ``RTT_PERIOD_S`` apart (round trip), or cycles for ``duration_s`` at
    ``rate_hz`` (0 = back to back). A cycle is a miss if any STATE is missing or late: after
    ``deadline_s`` from its SYNC (round trip; 0 = none) or, paced, after the next tick; ticks
    the host starts late are misses too."""
    s0 = link.stats
    cpu0 = time.process_time()
    times: list[float] = []
    misses = cycles = 0
    period = 1.0 / rate_hz if rate_hz else 0.0
    t_start = time.perf_counter()
    next_tick = t_start
    while True:
        now = time.perf_counter()
        if count and cycles >= count:
            break
        if duration_s and now - t_start >= duration_s:
            break
        if period:
            if now - next_tick > period:  # the host fell behind: the ticks it skipped are misses
                skipped = int((now - next_tick) / period)
                misses += skipped
                cycles += skipped
                next_tick += skipped * period
            timeout = max(1e-3, next_tick + period - now)
        else:
            timeout = 1.0
        dt, complete = _cycle(link, n, timeout)
        cycles += 1
        if period:
            ok = complete and time.perf_counter() <= next_tick + period
        else:
            ok = complete and (not deadline_s or dt <= deadline_s)
        if complete and (ok or not period):
            times.append(dt)  # a late round trip is complete: its time is what the chain takes
        if not ok:
            misses += 1
        if period:
            next_tick += period
            delay = next_tick - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        elif count:
            time.sleep(RTT_PERIOD_S)
    elapsed = time.perf_counter() - t_start
    cpu = time.process_time() - cpu0
    s1 = link.stats
    return Cycles(
        times,
        misses,
        cycles,
        elapsed,
        s1["tx_bytes"] - s0["tx_bytes"],
        s1["rx_bytes"] - s0["rx_bytes"],
        cpu,
    )


def run_pipelined(link: ChainLink, n: int, *, duration_s: float, rate_hz: float) -> Cycles:
    """Paced cycles with pipelining (docs/protocol.md 8.4): on every tick the host sends the next
    SYNC first, then collects the previous cycle's STATEs, which must all be in before the next
    tick (so each cycle has two periods from its SYNC). An incomplete cycle or a late tick is a
    miss."""
    s0 = link.stats
    times: list[float] = []
    misses = cycles = 0
    period = 1.0 / rate_hz
    t_start = time.perf_counter()
    next_tick = t_start
    prev = None
    prev_t = 0.0
    while time.perf_counter() - t_start < duration_s:
        now = time.perf_counter()
        if now - next_tick > period:
            skipped = int((now - next_tick) / period)
            misses += skipped
            cycles += skipped
            next_tick += skipped * period
        try:
            cur = link.sync_send([SETPOINT] * n)
        except LinkError:
            cur = None  # this tick's cycle never started: a miss (it has nothing to collect)
            cycles += 1
            misses += 1
        t_cur = time.perf_counter()
        if prev is not None:
            left = max(1e-3, next_tick + period - time.perf_counter())
            states = link.sync_collect(prev, timeout=left)
            cycles += 1
            if all(s is not None for s in states) and time.perf_counter() <= next_tick + period:
                times.append(time.perf_counter() - prev_t)
            else:
                misses += 1
        prev, prev_t = cur, t_cur
        next_tick += period
        delay = next_tick - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    if prev is not None:
        link.sync_collect(prev, timeout=0.2)
    s1 = link.stats
    return Cycles(
        times,
        misses,
        cycles,
        time.perf_counter() - t_start,
        s1["tx_bytes"] - s0["tx_bytes"],
        s1["rx_bytes"] - s0["rx_bytes"],
    )


def bench_discovery(n: int, repeat: int) -> list[float]:
    with EmulatedChain(n) as chain, ChainLink(chain.host_port) as link:
        boot(link, n)
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            descs = link.discover(timeout=1.0)
            times.append(time.perf_counter() - t0)
            assert len(descs) == n
            time.sleep(0.01)
        return times


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[int(q * (len(s) - 1))] if s else float("nan")


RTT_HEADERS = [
    "segments", "baud (bit/s)", "SYNC → every STATE, median (p90)", "line-rate floor",
    "× line-rate", "× cut-through", "× store-and-forward", "missed", "100 Hz sustained, missed",
]  # fmt: skip


def bench_chain(
    n: int, timing: bool, bauds: list[int], args: argparse.Namespace, figs: Figures | None = None
) -> None:
    table = "rtt_model" if timing else "rtt"
    with (
        emulated_chain(n, timing=timing, where=args.emulator) as chain,
        ChainLink(chain.host_port) as link,
    ):
        factor = chain.cpu_factor_of(0)
        boot(link, n)
        for baud in bauds:
            chain.set_all_links(baud=baud)
            settle(link, n)  # warm up at this baud
            rtt = run_cycles(link, n, count=args.repeat, deadline_s=rtt_deadline_s(n, baud))
            sync_b = rtt.tx_bytes / max(1, rtt.cycles)
            state_b = floors.max_state_bytes()  # every STATE has it (host/floors.py)
            seen_b = rtt.rx_bytes / max(1, rtt.cycles) / n  # incl. cut and late frames
            lr = floors.line_rate_floor_s(n, baud, sync_b, state_b)
            sf = floors.store_and_forward_floor_s(n, baud, sync_b, state_b)
            ct = floors.cut_through_floor_s(n, baud, sync_b, state_b)
            med = statistics.median(rtt.times) if rtt.times else float("nan")
            model = f" [ESP32 model x{factor:.0f}]" if timing else ""
            label = f"  {n} seg @ {baud:>7} bd{model}"
            print(
                f"{label}: RTT median {med * 1e3:7.2f} ms p90 {_pct(rtt.times, 0.9) * 1e3:7.2f}"
                f" ms, misses {rtt.misses}/{rtt.cycles} | line-rate floor {lr * 1e3:6.2f} ms"
                f" -> {med / lr:4.2f}x (goal <= 1.3) | cut-through floor {ct * 1e3:6.2f} ms ->"
                f" {med / ct:4.2f}x | store-and-forward floor {sf * 1e3:6.2f}"
                f" ms -> {med / sf:4.2f}x | deadline {rtt_deadline_s(n, baud) * 1e3:.0f} ms"
                f" | {sync_b:.0f} B SYNC, {state_b:.0f} B/STATE ({seen_b:.0f} B received)",
                flush=True,
            )
            b2b = run_cycles(link, n, duration_s=min(args.duration, 3.0))
            settle(link, n)
            paced = run_cycles(link, n, duration_s=args.duration, rate_hz=args.rate)
            settle(link, n)  # a chain that fell behind first works off its backlog
            piped = run_pipelined(link, n, duration_s=args.duration, rate_hz=args.rate)
            settle(link, n)
            ceiling = 1.0 / lr
            pipe_ceiling = floors.pipelined_rate_hz(n, baud, sync_b, state_b)
            period = 1.0 / args.rate
            pmed, bound = median_counting_misses(paced.times, paced.misses, period)
            at = "≥ " if bound else ""
            print(
                f"{'':>{len(label)}}  {args.rate:.0f} Hz for {paced.elapsed_s:.0f} s: "
                f"{paced.rate_hz:6.1f} Hz complete = {paced.rate_hz / args.rate:4.2f}x asked,"
                f" misses {paced.misses}/{paced.cycles}, cycle median (misses counted)"
                f" {at}{pmed * 1e3:6.2f} ms -> {at}{pmed / lr:4.2f}x line-rate,"
                f" {at}{pmed / ct:4.2f}x cut-through floor"
                f" | back to back: {b2b.rate_hz:6.1f} Hz, misses {b2b.misses}/{b2b.cycles}"
                f" = {b2b.rate_hz / ceiling:4.2f}x the line-rate ceiling {ceiling:6.0f} Hz"
                f" | host CPU {paced.cpu_per_cycle_s * 1e3:.2f} ms per {args.rate:.0f} Hz cycle",
                flush=True,
            )
            print(
                f"{'':>{len(label)}}  {args.rate:.0f} Hz pipelined (next SYNC first): "
                f"{piped.rate_hz:6.1f} Hz complete = {piped.rate_hz / args.rate:4.2f}x asked"
                f" = {piped.rate_hz / pipe_ceiling:4.2f}x the pipelined ceiling"
                f" {pipe_ceiling:6.0f} Hz, misses {piped.misses}/{piped.cycles}",
                flush=True,
            )
            if figs is not None:
                FACTORS.setdefault(table, set()).add(round(factor))
                seen = sorted(FACTORS[table])
                span = f"{seen[0]}" if len(seen) == 1 else f"{seen[0]}–{seen[-1]}"
                note = (
                    f"emulator's ESP32 timing model on (compute × {span}, measured at each"
                    " chain's start)"
                    if timing
                    else "emulator timing model off (PC speed)"
                )
                place = (
                    "the emulator in its own process (ucr emulate)"
                    if args.emulator == "process"
                    else "the emulator in the benchmark's process"
                )
                note = (
                    f"{note}; links throttled to the baud rate, released in pieces of"
                    f" at most {CHUNK_MAX_BYTES} bytes; {place}"
                )
                if table not in figs.tables:
                    figs.table(table, RTT_HEADERS, note=note)
                figs.tables[table]["note"] = note
                figs.row(table, [
                    n, baud, f"{med * 1e3:.2f} ms ({_pct(rtt.times, 0.9) * 1e3:.2f})",
                    f"{lr * 1e3:.2f} ms", f"{med / lr:.2f}", f"{med / ct:.2f}", f"{med / sf:.2f}",
                    f"{rtt.misses}/{rtt.cycles}", f"{paced.misses}/{paced.cycles}",
                ])  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30, help="round trips per figure")
    parser.add_argument("--duration", type=float, default=5.0, help="s per sustained run")
    parser.add_argument("--rate", type=float, default=100.0, help="sustained cycle rate, Hz")
    parser.add_argument("--timing", choices=("off", "on", "both"), default="both")
    parser.add_argument("--segments", default="1,3,8")
    parser.add_argument("--bauds", default="115200,921600,2000000")
    parser.add_argument("--no-discovery", action="store_true")
    parser.add_argument(
        "--emulator",
        choices=("process", "thread"),
        default="process",
        help="run the emulated chain in its own process (ucr emulate, default) or in a thread of "
        "this one, where it shares the interpreter lock with the host's link reader",
    )
    parser.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = parser.parse_args()
    figs = Figures.from_argv("bench_chain")
    ns = [int(x) for x in args.segments.split(",")]
    bauds = [int(x) for x in args.bauds.split(",")]
    if not args.no_discovery:
        print("discovery (unthrottled links), median / p90 over", args.repeat, "runs")
        if figs is not None:
            figs.table("discovery", ["segments", "DISCOVER → every descriptor, median (p90)"],
                       note=f"unthrottled emulated links, {args.repeat} runs")  # fmt: skip
        for n in ns:
            t = bench_discovery(n, args.repeat)
            print(
                f"  {n} segment(s): {statistics.median(t) * 1e3:7.2f} ms"
                f"  p90 {_pct(t, 0.9) * 1e3:7.2f} ms"
            )
            if figs is not None:
                figs.row("discovery", [n, (f"{statistics.median(t) * 1e3:.1f} ms "
                                          f"({_pct(t, 0.9) * 1e3:.1f})")])  # fmt: skip
    models = {"off": [False], "on": [True], "both": [False, True]}[args.timing]
    for timing in models:
        print(
            "SYNC -> all STATEs on throttled links, "
            + ("ESP32 timing model ON" if timing else "timing model off (PC speed)"),
            flush=True,
        )
        for n in ns:
            bench_chain(n, timing, bauds, args, figs)
    if figs is not None:
        figs.save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
