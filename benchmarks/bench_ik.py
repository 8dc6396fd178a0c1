"""IK success rate and time for 3-segment position targets sampled from the reachable workspace.

Targets are FK of configurations drawn uniformly from each segment's curvature disc
(|k| <= kappa_max), so every target is reachable. Each solve starts from the straight robot (the
ros2_control initial values), as a user's first request would.

A second part solves pose targets (position and orientation of the tip, tol 1e-4 m and 1e-3 rad)
and counts the solves that need more than ITERATION_GOAL iterations (the bound
tests/ucrdf_kin/test_ik.py asserts for orientation round trips).

Run: .venv/bin/python benchmarks/bench_ik.py [COUNT] [--figures FILE]   (goal from issue 2)
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.figures import Figures  # noqa: E402
from ucrdf.fk import RobotKinematics  # noqa: E402
from ucrdf.ik import IKSolver  # noqa: E402
from ucrdf.parser import load  # noqa: E402

GOAL_SUCCESS = 0.99
GOAL_MEDIAN_S = 2e-3
ITERATION_GOAL = 60  # pose targets: Gauss-Newton-like convergence, not a slow crawl


def _random_config(kin: RobotKinematics, rng: np.random.Generator) -> dict:
    config = {}
    for name, model in kin.models.items():
        kmax = model.spec.limits.kappa_max
        config[name] = {"kappa": kmax * math.sqrt(rng.random()),
                        "phi": rng.uniform(-math.pi, math.pi)}  # fmt: skip
    return config


IK_HEADERS = ["targets (3-segment robot, start straight)", "success", "median time", "p95 time",
              "iterations, median (max)"]  # fmt: skip


def pose_targets(count: int, figs: Figures | None = None) -> None:
    """Position + orientation targets: success, time, iterations (and how many exceed the goal)."""
    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    kin = RobotKinematics(robot)
    solver = IKSolver(kin)
    rng = np.random.default_rng(2)
    times, iterations, ok = [], [], 0
    for _ in range(count):
        goal = kin.fk(_random_config(kin, rng))[solver.tip]
        t0 = time.perf_counter()
        result = solver.solve(goal[:3, 3], target_rot=goal[:3, :3])
        times.append(time.perf_counter() - t0)
        iterations.append(result.iterations)
        ok += bool(result.success)
    slow = sum(1 for n in iterations if n > ITERATION_GOAL)
    print(f"IK pose targets: {count} reachable poses, tol 1e-4 m / 1e-3 rad")
    print(f"  success rate  {ok / count * 100:7.2f} %")
    p95 = float(np.percentile(times, 95))
    print(f"  median time   {float(np.median(times)) * 1e3:7.3f} ms   p95 {p95 * 1e3:.3f} ms"
          f"   max {max(times) * 1e3:.2f} ms")  # fmt: skip
    print(f"  iterations    median {np.median(iterations):.0f}, p95 "
          f"{np.percentile(iterations, 95):.0f}, max {max(iterations)}; over {ITERATION_GOAL}: "
          f"{slow} ({slow / count * 100:.1f} %)")  # fmt: skip
    if figs is not None:
        figs.row("ik", [
            f"{count} reachable poses (position + orientation), tol 1e-4 m / 1e-3 rad",
            f"{ok / count * 100:.1f} %", f"{float(np.median(times)) * 1e3:.2f} ms",
            f"{p95 * 1e3:.2f} ms", f"{np.median(iterations):.0f} ({max(iterations)})",
        ])  # fmt: skip


def main(count: int = 1000, figs: Figures | None = None) -> None:
    robot = load(ROOT / "robots" / "softrobot3.ucrdf")
    kin = RobotKinematics(robot)
    solver = IKSolver(kin)
    rng = np.random.default_rng(1)
    times, iterations, restarts = [], [], []
    ok = 0
    worst = 0.0
    for _ in range(count):
        config = {}
        for name, model in kin.models.items():
            kmax = model.spec.limits.kappa_max
            config[name] = {"kappa": kmax * math.sqrt(rng.random()),
                            "phi": rng.uniform(-math.pi, math.pi)}  # fmt: skip
        target = kin.fk(config)[solver.tip][:3, 3]
        t0 = time.perf_counter()
        result = solver.solve(target)
        times.append(time.perf_counter() - t0)
        iterations.append(result.iterations)
        restarts.append(result.restarts)
        if result.success:
            ok += 1
            check = np.linalg.norm(kin.fk(result.config)[solver.tip][:3, 3] - target)
            worst = max(worst, check)
    success = ok / count
    median = float(np.median(times))
    p95 = float(np.percentile(times, 95))
    print(f"IK benchmark: {count} reachable position targets, 3-segment robot "
          f"({robot.name}), tol 1e-4 m")  # fmt: skip
    print(f"  success rate  {success * 100:7.2f} %   goal >= {GOAL_SUCCESS * 100:.0f} %"
          f"   ratio {success / GOAL_SUCCESS:.3f}")  # fmt: skip
    print(f"  median time   {median * 1e3:7.3f} ms  goal <= {GOAL_MEDIAN_S * 1e3:.0f} ms"
          f"   ratio (goal/measured) {GOAL_MEDIAN_S / median:.1f}")  # fmt: skip
    print(f"  p95 time      {p95 * 1e3:7.3f} ms   max {max(times) * 1e3:.2f} ms")
    print(f"  iterations    median {np.median(iterations):.0f}, max {max(iterations)}; "
          f"solves needing a restart: {sum(1 for r in restarts if r)}")  # fmt: skip
    print(f"  worst position error of a reported success (re-checked by FK): {worst:.2e} m")
    if figs is not None:
        figs.table("ik", IK_HEADERS, note="targets from uniformly sampled configurations")
        figs.row("ik", [
            f"{count} reachable positions, tol 1e-4 m", f"{success * 100:.1f} %",
            f"{median * 1e3:.2f} ms", f"{p95 * 1e3:.2f} ms",
            f"{np.median(iterations):.0f} ({max(iterations)})",
        ])  # fmt: skip


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("count", nargs="?", type=int, default=1000, help="targets per part (1000)")
    ap.add_argument("--figures", metavar="FILE", help="save the table the docs quote (JSON)")
    args = ap.parse_args()
    figures = Figures.from_argv("bench_ik")
    main(args.count, figures)
    pose_targets(args.count, figures)
    if figures is not None:
        figures.save()
