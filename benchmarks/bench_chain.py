"""Emulated chain figures: discovery time (1, 3, 8 segments) and SYNC -> STATE round trip on
throttled links (115200 and 921600 baud) as a ratio to two floors.

Run: .venv/bin/python benchmarks/bench_chain.py [--repeat N]
Line-rate floor: the time the bytes a round trip puts on link 0 (the SYNC plus every segment's
STATE) need at the line rate, bytes x 10 / baud. Store-and-forward floor: segments receive a
whole frame (and check its CRC) before passing it on, so the SYNC crosses n links one after the
other and so does the last segment's STATE: n x (t_sync + t_state). The first ratio is what the
protocol costs against a raw wire; the second is what the emulation and firmware add on top of
the chain's inherent latency.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from host.link import ChainLink  # noqa: E402
from tools.emulator import EmulatedChain  # noqa: E402


def boot(link: ChainLink, n: int, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if len(link.discover(timeout=0.5)) == n:
                return
        except OSError:
            pass
        time.sleep(0.1)
    raise SystemExit(f"chain of {n} did not boot")


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


def bench_roundtrip(n: int, baud: int, repeat: int) -> tuple[list[float], float, float]:
    with EmulatedChain(n) as chain, ChainLink(chain.host_port, baudrate=baud) as link:
        chain.set_all_links(baud=baud)
        boot(link, n)
        setpoints = [(0.5, 0.3)] * n
        link.sync(setpoints, timeout=1.0)
        times, floors, sf_floors = [], [], []
        for _ in range(repeat):
            s0 = link.stats
            t0 = time.perf_counter()
            states = link.sync(setpoints, timeout=1.0)
            dt = time.perf_counter() - t0
            s1 = link.stats
            if any(s is None for s in states):
                continue
            tx = s1["tx_bytes"] - s0["tx_bytes"]
            rx = s1["rx_bytes"] - s0["rx_bytes"]
            times.append(dt)
            floors.append((tx + rx) * 10 / baud)
            sf_floors.append(n * (tx + rx / n) * 10 / baud)
            time.sleep(0.01)
        return times, statistics.median(floors), statistics.median(sf_floors)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30)
    args = parser.parse_args()
    print("discovery (unthrottled links), median / p90 over", args.repeat, "runs")
    for n in (1, 3, 8):
        t = sorted(bench_discovery(n, args.repeat))
        print(
            f"  {n} segment(s): {statistics.median(t) * 1e3:7.2f} ms  p90 "
            f"{t[int(0.9 * (len(t) - 1))] * 1e3:7.2f} ms"
        )
    print("SYNC -> all STATEs round trip on throttled links, median over", args.repeat, "runs")
    for n in (1, 3, 8):
        for baud in (115200, 921600):
            t, floor, sf = bench_roundtrip(n, baud, args.repeat)
            med = statistics.median(t)
            print(
                f"  {n} segment(s) @ {baud:>6} bd: {med * 1e3:7.2f} ms | line-rate floor "
                f"{floor * 1e3:6.2f} ms, ratio {med / floor:4.2f} (goal <= 1.3) | "
                f"store-and-forward floor {sf * 1e3:6.2f} ms, ratio {med / sf:4.2f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
