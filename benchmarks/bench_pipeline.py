"""The daemon with and without pipelining (docs/daemon.md "Pipelining"): the share of cycles
whose STATEs all arrive, the loop's usable rate and overruns, for 3 and 8 emulated segments
with the links throttled to the baud rate.

Run: .venv/bin/python benchmarks/bench_pipeline.py [--segments 3,8] [--baud 921600]
     [--rate 100] [--duration 10] [--timing off|on] [--pipeline off,on] [--rt-priority N]
     [--figures FILE]

``--rt-priority N`` runs the daemon's loop and link reader at SCHED_FIFO N, as the installed
service does (docs/daemon.md "Real-time scheduling"; needs root or RLIMIT_RTPRIO, else the daemon
warns and runs them normally, and the note says what they got).

Each run starts a fresh daemon (``pipeline`` off, then on) on one emulated chain (the real
firmware) whose robot is composed from the segments' descriptors, holds every segment still,
and counts over ``--duration`` s: exchanges, exchanges with any STATE missing (the link's
``timeouts``), loop overruns, and the usable rate the link health settled on (it lowers the
rate when a position misses most cycles, docs/daemon.md "Degrade, don't stall"). A complete
exchange is one whose every STATE came within the reply window: 0.8 x the period after its
SYNC without pipelining, 1.8 x the period with it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.figures import Figures  # noqa: E402
from host.config import DaemonConfig  # noqa: E402
from host.link import ChainLink  # noqa: E402
from tools.emulator import EmulatedChain, EmulatorProcess  # noqa: E402
from tools.emulator.process import emulated_chain  # noqa: E402
from tools.rig import start_daemon_on  # noqa: E402
from ucrdf.compose import robot_from_descriptors  # noqa: E402

HEADERS = [
    "segments",
    "baud (bit/s)",
    "pipeline",
    "complete exchanges",
    "usable rate (Hz)",
    "overruns",
]


def _robot(chain: EmulatedChain | EmulatorProcess, n: int):
    link = ChainLink(chain.host_port)
    try:
        end = time.monotonic() + 120.0
        while time.monotonic() < end:
            try:
                descs = link.discover(timeout=1.0)
                if len(descs) == n:
                    return robot_from_descriptors(descs, "bench")
            except OSError:
                pass
            time.sleep(0.1)
    finally:
        link.close()
    raise SystemExit(f"chain of {n} did not boot")


def _run(chain, robot, rate: float, pipeline: bool, duration: float, rt: int = 0) -> dict:
    d = start_daemon_on(
        chain,
        robot,
        30.0,
        config=DaemonConfig(pipeline=pipeline),
        rate_hz=rate,
        realtime_priority=rt,
    )
    try:
        time.sleep(1.0)  # settle
        o0 = d.loop_stats()["overruns"]
        exchanges = incomplete = 0
        last: dict[str, tuple[int, int]] = {}  # counters of the HWI / link objects seen last
        end = time.monotonic() + duration
        while time.monotonic() < end:
            hwi, link = d.topo.hwi, d.topo.link
            if hwi is not None and link is not None:
                e, t = hwi.exchanges, link.stats["timeouts"]
                pe, pt = last.get("hwi", (id(hwi), e)), last.get("link", (id(link), t))
                exchanges += e - pe[1] if pe[0] == id(hwi) else 0
                incomplete += t - pt[1] if pt[0] == id(link) else 0
                last = {"hwi": (id(hwi), e), "link": (id(link), t)}
            time.sleep(0.05)
        stats = d.loop_stats()
        overruns = stats["overruns"] - o0
        health = d.status()["link_health"]
    finally:
        d.stop()
    return {
        "exchanges": exchanges,
        "complete": exchanges - incomplete,
        "usable_rate_hz": health.get("usable_rate_hz", rate),
        "overruns": overruns,
        "scheduling": stats.get("scheduling", {}),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--segments", default="3,8")
    ap.add_argument("--baud", type=int, default=921600)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--duration", type=float, default=10.0)
    ap.add_argument("--timing", choices=("off", "on"), default="off")
    ap.add_argument("--pipeline", default="off,on", help="which runs: off, on or off,on")
    ap.add_argument("--rt-priority", type=int, default=0, help="daemon SCHED_FIFO priority")
    ap.add_argument(
        "--emulator",
        choices=("process", "thread"),
        default="process",
        help="the emulated chain in its own process (ucr emulate, default) or in a thread of "
        "the daemon's, where it shares the interpreter lock with the daemon's threads",
    )
    ap.add_argument("--figures", help="save the table for tools/docfigures.py")
    args = ap.parse_args()
    figs = Figures.from_argv("bench_pipeline")
    timing = args.timing == "on"
    modes = [{"off": False, "on": True}[m.strip()] for m in args.pipeline.split(",")]
    where = "its own process (ucr emulate)" if args.emulator == "process" else "the daemon's"
    note = (
        f"{args.rate:.0f} Hz for {args.duration:.0f} s per run; emulator timing model "
        f"{args.timing}; links throttled to the baud rate; the emulator in {where}"
    )
    if args.rt_priority:
        note += f"; daemon --rt-priority {args.rt_priority}"
    if figs:
        figs.table("daemon", HEADERS, note=note)
    print(f"daemon pipelining, {note}")
    for n in [int(x) for x in args.segments.split(",")]:
        with emulated_chain(n, timing=timing, where=args.emulator) as chain:
            robot = _robot(chain, n)
            chain.set_all_links(baud=args.baud)
            for pipeline in modes:
                r = _run(chain, robot, args.rate, pipeline, args.duration, args.rt_priority)
                if args.rt_priority:
                    print(f"  daemon threads: {r['scheduling']}")
                share = r["complete"] / r["exchanges"] if r["exchanges"] else 0.0
                row = [
                    n,
                    args.baud,
                    "on" if pipeline else "off",
                    f"{r['complete']}/{r['exchanges']} ({share:.0%})",
                    f"{r['usable_rate_hz']:.0f}",
                    r["overruns"],
                ]
                print("  ".join(str(c) for c in row))
                if figs:
                    figs.row("daemon", row)
    if figs:
        figs.save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
