"""FK throughput: batched PCC segment transforms per second and whole-robot FK calls per second.

Run: .venv/bin/python benchmarks/bench_fk.py   (prints figures; goal from issue 2)
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ucrdf.fk import RobotKinematics  # noqa: E402
from ucrdf.models.pcc import pcc_tip_jacobians, pcc_transforms  # noqa: E402
from ucrdf.models.ppc import ppc_transforms  # noqa: E402
from ucrdf.parser import load  # noqa: E402

GOAL_BATCHED = 1e6  # segment transforms per second


def rate(func, count: int, min_time: float = 1.0) -> float:
    """Items per second: best of repeated timed runs (shared, noisy machine)."""
    func()  # warm up
    best = math.inf
    start = time.perf_counter()
    while time.perf_counter() - start < min_time:
        t0 = time.perf_counter()
        func()
        best = min(best, time.perf_counter() - t0)
    return count / best


def main() -> None:
    rng = np.random.default_rng(0)
    kmax = math.radians(60) / 0.316
    print("FK benchmark (goal from issue 2: >= 1e6 batched segment transforms/s)")
    for n in (1_000, 100_000):
        r = kmax * np.sqrt(rng.random(n))
        a = rng.uniform(-math.pi, math.pi, n)
        kx, ky = r * np.cos(a), r * np.sin(a)
        measured = rate(lambda kx=kx, ky=ky: pcc_transforms(kx, ky, 0.316), n)
        print(f"  PCC batched transforms, N={n:>7}: {measured:12.3e} /s  goal {GOAL_BATCHED:.0e}"
              f"  ratio {measured / GOAL_BATCHED:6.2f}")  # fmt: skip
    n = 100_000
    r = kmax * np.sqrt(rng.random(n))
    a = rng.uniform(-math.pi, math.pi, n)
    kx, ky = r * np.cos(a), r * np.sin(a)
    measured = rate(lambda: pcc_tip_jacobians(kx, ky, 0.316), n)
    print(f"  PCC batched tip Jacobians, N={n}: {measured:12.3e} /s")
    n = 10_000
    sx, sy = rng.uniform(-3, 3, n), rng.uniform(-3, 3, n)
    measured = rate(lambda: ppc_transforms(kx[:n], ky[:n], sx, sy, 0.316, 16), n)
    print(f"  PPC batched transforms (16 Magnus steps), N={n}: {measured:12.3e} /s")

    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    kin = RobotKinematics(robot)
    config = {name: {"kappa": 2.0, "phi": 0.3 * i} for i, name in enumerate(robot.bendables)}
    measured = rate(lambda: kin.fk(config), 1)
    print(f"  robot FK (softrobot3, checked config -> all link frames): {measured:10.0f} calls/s"
          f"  ({1e6 / measured:.1f} us/call; host needs >= 100 calls/s, ratio "
          f"{measured / 100:.0f})")  # fmt: skip
    coords, joints = kin.coordinates(config)
    measured = rate(lambda: kin.fk_coordinates(coords, joints), 1)
    print(f"  robot FK fast path (fk_coordinates, no checks): {measured:10.0f} calls/s"
          f"  ({1e6 / measured:.1f} us/call)")  # fmt: skip


if __name__ == "__main__":
    main()
