"""API benchmark: request round trip, publish->client latency, and what API load does to the
control loop's jitter. Runs the real daemon on an emulated 3-segment chain.

    .venv/bin/python benchmarks/bench_api.py [--seconds 4]

Prints figures (µs / ms) and ratios; asserts nothing (the machine may be shared and noisy).
The "flood" phase shows the per-connection pacing (``max_request_rate``, 500 requests/s).
"""

# ruff: noqa: PLC0415 - heavy imports (daemon, emulator) only when the benchmark runs
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def _jitter(daemon, seconds: float) -> dict:
    daemon.loop.stats.reset()
    time.sleep(seconds)
    return daemon.loop_stats()


def load_client(url: str, period: float, seconds: float) -> dict:
    """Two clients polling status (every ``period`` s, 0 = flat out) and two subscribers."""
    from host.api.client import connect

    stop = threading.Event()
    counts = {"req": 0, "msg": 0}

    def hammer() -> None:
        with connect(url) as h:
            while not stop.is_set():
                h.status()
                counts["req"] += 1
                if period:
                    time.sleep(period)

    def stream() -> None:
        with connect(url) as c, c.subscribe(["joint_states", "transforms"]) as sub:
            while not stop.is_set():
                if sub.get(timeout=0.2) is not None:
                    counts["msg"] += 1

    threads = [threading.Thread(target=f) for f in (hammer, hammer, stream, stream)]
    for t in threads:
        t.start()
    time.sleep(seconds)
    stop.set()
    for t in threads:
        t.join()
    return counts


def main(argv: list[str] | None = None) -> int:
    from host.api.client import connect
    from host.api.server import ApiServer
    from host.daemon import Daemon, DaemonError
    from tools.emulator import EmulatedChain
    from tools.segment_config import configs
    from ucrdf.parser import load

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=4.0, help="duration of each phase, s")
    ap.add_argument("--load-client", metavar="URL", help=argparse.SUPPRESS)
    ap.add_argument("--period", type=float, default=0.0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.load_client:
        print(json.dumps(load_client(args.load_client, args.period, args.seconds)))
        return 0

    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    with EmulatedChain(3, config_for=configs(robot)) as chain:
        deadline = time.monotonic() + 15
        while True:
            try:
                daemon = Daemon(robot, port=chain.host_port).start()
                break
            except DaemonError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        srv = ApiServer(daemon, "127.0.0.1", 0).start()
        try:
            time.sleep(0.5)
            quiet = _jitter(daemon, args.seconds)

            with connect(srv.url) as c:
                # 1. request round trips
                for op in ("ping", "status"):
                    rtts = []
                    for _ in range(300):  # 200 requests/s: below the server's pacing limit
                        t0 = time.perf_counter()
                        c.call(op)
                        rtts.append((time.perf_counter() - t0) * 1e6)
                        time.sleep(0.005)
                    print(
                        f"round trip {op:<7} p50 {statistics.median(rtts):7.0f} µs   "
                        f"p99 {_pct(rtts, 0.99):7.0f} µs"
                    )

                # 2. publish -> client latency (daemon monotonic clock, same machine)
                lat = []
                with c.subscribe(["joint_states"]) as sub:
                    t_end = time.monotonic() + args.seconds
                    while time.monotonic() < t_end:
                        m = sub.get(timeout=1)
                        if m is not None:
                            lat.append((time.monotonic() - m["t"]) * 1e3)
                print(
                    f"joint_states publish->client  n={len(lat)}  p50 "
                    f"{statistics.median(lat):.2f} ms  p99 {_pct(lat, 0.99):.2f} ms  "
                    f"(includes up to one poll interval, {srv.poll_interval * 1e3:.0f} ms)"
                )

            # 3. loop jitter under API load: a realistic client mix, then saturating request floods
            phases = {"quiet": quiet}
            for label, req_period in (("moderate", 0.01), ("flood", 0.0)):
                # Clients are other processes in real use: keep their GIL out of the daemon's.
                gen = subprocess.Popen(
                    [
                        sys.executable,
                        str(Path(__file__).resolve()),
                        "--load-client",
                        srv.url,
                        "--period",
                        str(req_period),
                        "--seconds",
                        str(args.seconds + 0.5),
                    ],
                    cwd=ROOT,
                    stdout=subprocess.PIPE,
                    text=True,
                )
                time.sleep(0.5)
                phases[label] = _jitter(daemon, args.seconds)
                out, _ = gen.communicate(timeout=60)
                counts = json.loads(out.strip().splitlines()[-1])
                print(
                    f"API load {label:<8}: {counts['req'] / args.seconds:6.0f} status req/s, "
                    f"{counts['msg'] / args.seconds:4.0f} stream msgs/s (separate process)"
                )
            for name, st in phases.items():
                j, comp = st["jitter_us"], st["compute_us"]
                print(
                    f"loop {st['rate_hz']:.0f} Hz {name:<9} jitter p99 {j['p99']:8.0f} µs  "
                    f"max {j['max']:8.0f} µs  compute p99 {comp['p99']:6.0f} µs  "
                    f"overruns {st['overruns']}"
                )
            for name in ("moderate", "flood"):
                ratio = phases[name]["jitter_us"]["p99"] / max(quiet["jitter_us"]["p99"], 1e-9)
                print(f"jitter p99 ratio {name}/quiet: {ratio:.2f}x")
            print(
                f"topology changes during the run: {daemon.status()['topology_changes']} "
                "(the emulated segments share 2 cores with the load generator)"
            )
        finally:
            srv.stop()
            daemon.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
