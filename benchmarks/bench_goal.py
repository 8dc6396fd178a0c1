"""Long goals beside the control loop: what accepting a 10,000-waypoint goal costs the 100 Hz loop
in the daemon's process — its build time, the full (generation 2) garbage collections it causes
and the loop's overruns and jitter meanwhile — with the heap frozen at start, as the daemon runs
(host/realtime.freeze_heap, docs/daemon.md "Garbage collection"), and without.

    .venv/bin/python benchmarks/bench_goal.py [--goals 8] [--waypoints 10000] [--rt-priority N]
        [--figures FILE]

The goals are sent to the daemon's facade in its own process (no API: the API's part is
bench_api's phase goal10k), each cancelled once accepted, one every 1.5 s, on 3 emulated
segments. Prints figures (and saves them with ``--figures``, for tools/docfigures.py); asserts
nothing (the machine may be shared and noisy).
"""

# ruff: noqa: PLC0415 - heavy imports (daemon, emulator) only when the benchmark runs
from __future__ import annotations

import argparse
import gc
import math
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def wave(n: int) -> list[dict]:
    """``n`` waypoints 2 ms apart, a gentle wave on every segment (well inside the limits)."""
    names = ("segment_1", "segment_2", "segment_3")
    return [
        {"time_from_start": round(0.5 + 0.002 * i, 6), "segments": {
            s: {"kappa": round(0.3 + 0.2 * math.sin(i / 500 + k), 6), "phi": 0.5}
            for k, s in enumerate(names)}}
        for i in range(n)
    ]  # fmt: skip


def run(frozen: bool, goals: int, waypoints: int, rt: int) -> dict:
    """One daemon on a fresh emulated chain; ``goals`` goals; what they cost the loop."""
    import host.realtime as realtime
    from tools.rig import EmulatedRig

    gc.unfreeze()  # a previous run's freeze must not carry over
    gc.collect()
    real = realtime.freeze_heap
    if not frozen:
        realtime.freeze_heap = lambda: 0
    full_ms: list[float] = []
    t_start = [0.0]

    def watch(phase: str, info: dict) -> None:
        if phase == "start":
            t_start[0] = time.perf_counter()
        elif info["generation"] == 2:
            full_ms.append((time.perf_counter() - t_start[0]) * 1e3)

    try:
        with EmulatedRig("softrobot3.ucrdf", api=None, realtime_priority=rt) as rig:
            d = rig.daemon
            time.sleep(2.0)
            gc.callbacks.append(watch)
            builds, overruns, cycles, jitter = [], 0, 0, []
            try:
                for _ in range(goals):
                    points = wave(waypoints)  # as a client's request arrives: fresh objects
                    time.sleep(0.5)
                    d.loop.stats.reset()
                    t0 = time.monotonic()
                    goal = d.send_trajectory(points)
                    builds.append(time.monotonic() - t0)
                    time.sleep(0.1)
                    st = d.loop_stats()
                    overruns += st["overruns"]
                    cycles += st["cycles"]
                    jitter.append(st["jitter_us"]["max"] / 1e3)
                    d.cancel_trajectory(goal)
                    del points
                    time.sleep(1.0)
            finally:
                gc.callbacks.remove(watch)
    finally:
        realtime.freeze_heap = real
        gc.unfreeze()
    return {"builds": builds, "full_ms": full_ms, "overruns": overruns, "cycles": cycles,
            "jitter_ms": jitter}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--goals", type=int, default=8, help="goals per mode (default 8)")
    ap.add_argument("--waypoints", type=int, default=10_000, help="waypoints per goal")
    ap.add_argument("--rt-priority", type=int, default=10, metavar="N",
                    help="SCHED_FIFO priority of the loop and link reader (0: normal; default "
                    "10, as the service)")  # fmt: skip
    ap.add_argument("--figures", metavar="FILE", help="save the tables the docs quote (JSON)")
    args = ap.parse_args(argv)
    from benchmarks.figures import Figures

    figs = Figures.from_argv("bench_goal", argv)
    if figs is not None:
        figs.table(
            "goal",
            ["heap at start", "build, p50 (max)", "full GC collections: n, p50 / max",
             "loop overruns", "loop jitter max per goal, p50 / max"],
            note=f"{args.goals} goals of {args.waypoints} waypoints sent to the daemon's "
            "facade in its process, one every 1.5 s, each cancelled once accepted; 3 emulated "
            f"segments, 100 Hz, loop thread SCHED_FIFO {args.rt_priority}; the collections "
            "and loop figures from the goal's arrival to 0.1 s after it was accepted, plus the "
            "pauses between goals for the collections",
        )  # fmt: skip
    for frozen in (True, False):
        r = run(frozen, args.goals, args.waypoints, args.rt_priority)
        b, f, j = r["builds"], r["full_ms"], r["jitter_ms"]
        label = "frozen (as the daemon runs)" if frozen else "not frozen"
        gcs = f"{len(f)}, {statistics.median(f):.1f} / {max(f):.1f} ms" if f else "none"
        row = [label, f"{statistics.median(b):.2f} s ({max(b):.2f})", gcs,
               f"{r['overruns']} of {r['cycles']}",
               f"{statistics.median(j):.1f} / {max(j):.1f} ms"]  # fmt: skip
        print("  ".join(row), flush=True)
        if figs is not None:
            figs.row("goal", row)
    if figs is not None:
        figs.save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
