"""Host daemon benchmark: cycle compute time, loop jitter, hot-plug latency, round trip.

Prints:
1. host cycle time (µs, compute only, no I/O wait) of the daemon's real control step
   (read → supervise → cJTC/cJSB/cRSP update → command interfaces) for 3 and 8 segments, on a
   replayed STATE set (no bus, so only the host's own work is timed), on a simulated 100 Hz clock
   with a short real idle after each step; cRSP's FK runs in the publisher thread (its cost per
   publish is printed). Goal: ≤ 100 µs for 3.
2. loop period/jitter/overruns of the daemon driving the emulated 3-segment chain (real firmware
   on the MicroPython VM) at 100 and 500 Hz.
3. hot-plug latency on the emulated chain: unplug the tip (and the middle) segment, plug it back;
   detection = first cycle that noticed, recovery = new HWI/controllers running ("controllable").
   Goals: detected ≤ 250 ms, controllable ≤ 500 ms.
4. command → state round trip (one SYNC down, every STATE back) over emulated links throttled to
   115200 and 921600 baud, as a ratio to the line-rate floor of a store-and-forward chain
   (``host.floors.line_rate_floor_s`` with the measured frame sizes). Goal ≤ 1.3×.

The emulator runs in this process (proxy threads) and the segments are MicroPython processes on
the same cores, so figures 2–4 include that load. Run: ``.venv/bin/python benchmarks/bench_host.py``
(``--quick`` for shorter runs).
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import numpy as np  # noqa: E402

import host.daemon as hd  # noqa: E402
from benchmarks.figures import Figures  # noqa: E402
from host.config import DaemonConfig  # noqa: E402
from host.daemon import Daemon  # noqa: E402
from host.link import ChainLink  # noqa: E402
from tools.emulator import EmulatedChain  # noqa: E402
from tools.segment_config import config_for  # noqa: E402
from ucrdf.compose import robot_from_descriptors  # noqa: E402
from ucrdf.parser import load  # noqa: E402

ROBOT = REPO / "robots" / "softrobot3.ucrdf"
IDLE_S = 0.002  # real idle time after each timed step (a 100 Hz loop idles ~9.9 ms)


def fmt(v: float) -> str:
    return f"{v:8.1f}"


# -- 1. cycle compute time ---------------------------------------------------------------------


class ReplayLink:
    """Answers discover/sync/heartbeat instantly with fixed descriptors and STATEs, so the
    daemon's step can be timed without any I/O. A benchmark fixture, not a firmware model."""

    def __init__(self, descriptors: list[dict]):
        self.descs = descriptors
        self.states = [
            {
                "position": i,
                "cycle": 0,
                "t_ms": 0,
                "kappa": 1.0,
                "phi": 0.3,
                "kx": math.cos(0.3),
                "ky": math.sin(0.3),
                "tendon_lengths": [0.3] * 3,
                "servo_angles": [0.0] * 3,
                "status": {"DOWNSTREAM"},
                "raw_status": 16,
            }
            for i in range(len(descriptors))
        ]
        self.states[-1]["status"] = set()
        self.stats = {}

    def discover(self, timeout: float = 0.5) -> list[dict]:
        return [dict(d) for d in self.descs]

    def sync(self, setpoints, timeout=0.1, *, expected=None, resume=False):
        return self.states

    def heartbeat(self, timeout=0.1, *, expected=None):
        return self.states

    def hold(self, position=None) -> None:
        pass

    def events(self) -> list[dict]:
        return []

    def close(self) -> None:
        pass


def descriptors_for(robot) -> list[dict]:
    out = []
    names = list(robot.bendables)
    for i, n in enumerate(names):
        b = robot.bendables[n]
        out.append(
            {
                "position": i,
                "uid": f"bench{i:04x}",
                "fw_version": "bench",
                "protocol_version": 1,
                "model": b.model.type,
                "length": b.length,
                "tendon_angles": list(b.actuation.angles),
                "tendon_radius": b.actuation.radius,
                "spool_radius": b.actuation.spool_radius,
                "kappa_max": b.model.limits.kappa_max,
                "kappa_rate_max": b.model.limits.kappa_rate_max,
                "mass": 0.3,
                "backbone_radius": 0.003,
                "name": n,
                "servo_driver": "emulated",
                "watchdog_ms": 200,
                "downstream_present": i < len(names) - 1,
            }
        )
    return out


def robot_with(n: int):
    base = descriptors_for(load(ROBOT))[0]
    descs = [
        {
            **base,
            "position": i,
            "uid": f"bench{i:04x}",
            "name": f"segment_{i + 1}",
            "downstream_present": i < n - 1,
        }
        for i in range(n)
    ]
    return robot_from_descriptors(descs, f"bench{n}"), descs


class SimClock:
    """Stands in for the ``time`` module inside host.daemon: monotonic() advances one period per
    tick(); perf_counter() stays real, so compute time is measured for real."""

    def __init__(self, t0: float, period: float):
        self.t, self.period = t0, period
        self.perf_counter = time.perf_counter
        self.sleep = time.sleep

    def tick(self) -> None:
        self.t += self.period

    def monotonic(self) -> float:
        return self.t


def cycle_time(n: int, controllers: list[str], cycles: int) -> dict[str, float]:
    robot, descs = robot_with(n)
    cfg = DaemonConfig(port="replay://", active=controllers)
    d = Daemon(robot, cfg, link_factory=lambda url, baud: ReplayLink(descs))
    d.start()
    d.loop.stop()  # time the step by hand, in this thread
    names = d.hwi.names
    if "jtc" in controllers:
        pts = [
            {
                "time_from_start": 1000.0 + k,
                "segments": {nm: {"kappa": 1.0 + 0.1 * k, "phi": 0.2 * k} for nm in names},
            }
            for k in range(5)
        ]
        d.send_trajectory(pts)
    # Simulated clock: each step is one 100 Hz period later, so the broadcasters publish at
    # their configured rates (cJSB 50 Hz, cRSP 20 Hz) exactly as in a running daemon.
    clock = SimClock(time.monotonic(), 0.01)
    real_time, hd.time = hd.time, clock
    samples = []
    try:
        for _ in range(cycles):
            clock.tick()
            c = d._step()
            if c is not None:
                samples.append(c * 1e6)
            time.sleep(IDLE_S)  # the idle rest of a period, when the publisher thread works
    finally:
        hd.time = real_time
    time.sleep(0.2)  # let the publisher thread finish
    pub = d.loop_stats()["publisher"]
    d.stop(hold=False)
    a = np.array(samples)
    return {
        "mean": a.mean(),
        "p50": float(np.percentile(a, 50)),
        "p99": float(np.percentile(a, 99)),
        "max": a.max(),
        "publish_us": pub["mean_us"],
        "publishes": pub["done"],
        "publish_dropped": pub["dropped"],
    }


# -- 2–4: emulated chain -----------------------------------------------------------------------


def emulated_chain(robot):
    names = list(robot.bendables)
    return EmulatedChain(
        len(names), config_for=lambda k: {**config_for(robot, names[k]), "servo_driver": "emulated"}
    )


def wait_segments(link_url: str, n: int, timeout: float = 15.0) -> None:
    end = time.monotonic() + timeout
    with ChainLink(link_url) as link:
        while time.monotonic() < end:
            try:
                if len(link.discover(timeout=0.3)) == n:
                    return
            except OSError:
                pass
            time.sleep(0.1)
    raise RuntimeError("emulated segments did not answer")


def loop_jitter(chain, robot, rate: float, seconds: float) -> dict:
    d = Daemon(robot, DaemonConfig(port=chain.host_port, rate_hz=rate))
    d.start()
    try:
        names = d.hwi.names
        d.send_trajectory(
            [
                {
                    "time_from_start": seconds,
                    "segments": {n: {"kappa": 1.5, "phi": 1.0} for n in names},
                }
            ]
        )
        d.loop.stats.reset()
        time.sleep(seconds)
        s = d.loop_stats()
    finally:
        d.stop()
    return s


def hotplug(chain, robot, k: int, reps: int) -> list[dict]:
    """Unplug link k then plug it back, ``reps`` times; latencies in ms."""
    d = Daemon(robot, DaemonConfig(port=chain.host_port))
    d.start()
    out = []
    try:
        for _ in range(reps):
            for action, want in (("unplug", k), ("plug", len(robot.bendables))):
                time.sleep(0.5)
                n_log = len(d.hotplug_log)
                t0 = time.monotonic()
                getattr(chain, action)(k)
                end = t0 + 5.0
                while time.monotonic() < end and (
                    len(d.hotplug_log) == n_log or len(d.hwi.names if d.hwi else []) != want
                ):
                    time.sleep(0.002)
                entry = d.hotplug_log[-1]
                out.append(
                    {
                        "action": action,
                        "detect_ms": (entry["t"] - t0) * 1e3,
                        "ready_ms": (entry["t"] + entry["rebuild_s"] - t0) * 1e3,
                        "segments": len(entry["segments"]),
                    }
                )
    finally:
        d.stop()
    return out


def round_trip(chain, n: int, baud: int | None, cycles: int) -> dict:
    from host import floors  # noqa: PLC0415 - the one definition of every floor

    chain.set_all_links(baud=baud)
    try:
        with ChainLink(chain.host_port, baudrate=baud or 921600) as link:
            link.discover(timeout=0.5)
            sps = [(1.0, 0.5)] * n
            link.sync(sps, timeout=0.5, resume=True)
            s0 = link.stats
            times = []
            for _ in range(cycles):
                t = time.perf_counter()
                states = link.sync(sps, timeout=0.5)
                times.append(time.perf_counter() - t)
                assert all(s is not None for s in states)
                time.sleep(0.002)
            s1 = link.stats
    finally:
        chain.set_all_links(baud=None)
    b_sync = (s1["tx_bytes"] - s0["tx_bytes"]) / cycles
    b_state = (s1["rx_bytes"] - s0["rx_bytes"]) / cycles / n
    floor = floors.line_rate_floor_s(n, baud, b_sync, b_state) if baud else float("nan")
    ct = floors.cut_through_floor_s(n, baud, b_sync, b_state) if baud else float("nan")
    med = statistics.median(times)
    return {
        "baud": baud,
        "median_ms": med * 1e3,
        "p99_ms": float(np.percentile(times, 99)) * 1e3,
        "floor_ms": floor * 1e3,
        "ratio": med / floor if baud else float("nan"),
        "ct_ratio": med / ct if baud else float("nan"),
        "sync_bytes": b_sync,
        "state_bytes": b_state,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--figures", metavar="FILE", help="save the table the docs quote (JSON)")
    args = ap.parse_args()
    cycles = 1000 if args.quick else 3000
    figs = Figures.from_argv("bench_host")
    rows: list[list[str]] = []  # what | result | goal (docs/daemon.md "Measured")

    print(
        "1. host cycle time, compute only (µs)   mean      p50      p99      max   "
        "cRSP FK (publisher thread)"
    )
    for n in (3, 8):
        for ctrls in (["jtc", "jsb", "rsp"], ["jtc"]):
            r = cycle_time(n, ctrls, cycles)
            label = f"{n} segments, {'+'.join(ctrls):12s}"
            extra = ""
            if "rsp" in ctrls:
                extra = (
                    f"   {r['publish_us']:5.0f} µs per publish ({r['publishes']} done, "
                    f"{r['publish_dropped']} dropped)"
                )
            print(
                f"   {label:36s}{fmt(r['mean'])} {fmt(r['p50'])} {fmt(r['p99'])} "
                f"{fmt(r['max'])}{extra}"
            )
            if "rsp" in ctrls:
                rows.append([
                    f"host cycle, compute only, {n} segments, cJTC + cJSB + cRSP",
                    f"mean {r['mean']:.0f} µs, p99 {r['p99']:.0f} µs",
                    "≤ 100 µs" if n == 3 else "",
                ])  # fmt: skip
                rows.append([
                    f"cRSP forward kinematics + backbones per publish, {n} segments",
                    f"{r['publish_us'] / 1e3:.1f} ms (publisher thread, off the loop)", "",
                ])  # fmt: skip
    print("   (goal: <= 100 µs for 3 segments)")
    robot = load(ROBOT)
    chain = emulated_chain(robot)
    try:
        wait_segments(chain.host_port, 3)
        secs = 2.0 if args.quick else 5.0
        print(
            "2. loop on the emulated 3-segment chain   period mean  jitter p99  jitter max  "
            "compute p99  overruns/cycles"
        )
        for rate in (100.0, 500.0):
            s = loop_jitter(chain, robot, rate, secs)
            print(
                f"   {rate:5.0f} Hz {' ' * 27}{s['period_us']['mean']:9.0f} µs "
                f"{s['jitter_us']['p99']:8.0f} µs {s['jitter_us']['max']:8.0f} µs "
                f"{s['compute_us']['p99']:9.0f} µs   {s['overruns']}/{s['cycles']}"
            )
            rows.append([
                f"loop at {rate:.0f} Hz on the emulated 3-segment chain",
                (f"period mean {s['period_us']['mean'] / 1e3:.3f} ms, jitter p99 "
                f"{s['jitter_us']['p99']:.0f} µs, max {s['jitter_us']['max'] / 1e3:.1f} ms, "
                f"{s['overruns']} overruns in {s['cycles']} cycles"), "",
            ])  # fmt: skip
        print("3. hot-plug on the emulated chain (ms)    detected   controllable   segments")
        reps = 1 if args.quick else 3
        for k, label in ((2, "tip (segment 3)"), (1, "middle (segment 2)")):
            res = hotplug(chain, robot, k, reps)
            for action in ("unplug", "plug"):
                runs = [r for r in res if r["action"] == action]
                det = max(r["detect_ms"] for r in runs)
                rdy = max(r["ready_ms"] for r in runs)
                print(
                    f"   {action:6s} {label:32s}{det:8.0f}   {rdy:10.0f}        "
                    f"{runs[-1]['segments']}   (worst of {len(runs)}; goals 250 / 500)"
                )
                rows.append([
                    f"{action} {label}: detected, controllable again",
                    f"{det:.0f} ms, {rdy:.0f} ms (worst of {len(runs)})", "250 ms, 500 ms",
                ])  # fmt: skip
        print(
            "4. command -> state round trip, 3 segments   median    p99   line-rate floor  "
            'ratio   bytes SYNC/STATE   (floors: docs/protocol.md "Floors", host/floors.py)'
        )
        r = round_trip(chain, 3, None, 100 if args.quick else 300)
        print(
            f"   unthrottled (processing only) {' ' * 10}{r['median_ms']:6.2f} ms "
            f"{r['p99_ms']:6.2f} ms   (segments + emulator + host, no line time)"
        )
        rows.append([
            "command → state round trip, 3 segments, unthrottled links (processing only)",
            f"median {r['median_ms']:.2f} ms, p99 {r['p99_ms']:.2f} ms", "",
        ])  # fmt: skip
        for baud in (115200, 921600):
            r = round_trip(chain, 3, baud, 100 if args.quick else 300)
            print(
                f"   {baud:7d} baud {' ' * 26}{r['median_ms']:6.2f} ms {r['p99_ms']:6.2f} ms "
                f"{r['floor_ms']:8.2f} ms   {r['ratio']:5.2f}x   {r['sync_bytes']:.0f}/"
                f"{r['state_bytes']:.0f}   (goal <= 1.3x of the line rate)"
            )
            rows.append([
                f"command → state round trip, 3 segments, {baud} baud",
                (f"median {r['median_ms']:.2f} ms = {r['ratio']:.2f} × the line-rate floor "
                f"({r['floor_ms']:.2f} ms), {r['ct_ratio']:.2f} × the cut-through floor"),
                "≤ 1.3 × the line-rate floor",
            ])  # fmt: skip
    finally:
        chain.close()
    if figs is not None:
        figs.table("host", ["what", "result", "goal"], note=(
            "the emulator and three MicroPython segment processes on the same machine, "
            "emulator timing model off"))  # fmt: skip
        for row in rows:
            figs.row("host", row)
        figs.save()
    return 0


if __name__ == "__main__":
    sys.exit(main())
