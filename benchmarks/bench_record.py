"""Recording and live Foxglove benchmark (interop/, docs/recording.md).

Prints:
1. MCAP size per second of robot time, zstd-compressed as `ucr record` writes it (chunks closed
   every second), for 3 and 8 segments with joint states at 100 Hz: with the default visual
   rate (/tf and /ucr/arcs at 20 Hz) and with everything at 100 Hz; plus the recorder's CPU time
   per second of data (build + encode + write). Synthetic joint states (a slow sine on every
   segment), so the figures do not depend on the machine's load.
2. Loop jitter p99 of the daemon driving the emulated 3-segment chain (real firmware on the
   MicroPython VM) at 100 Hz, with nothing attached vs with `ucr record --foxglove-port P` (the
   recorder serving Foxglove too: one API client) in its own process and a Foxglove WebSocket
   client subscribed to every channel.
   Phases alternate (off, on, off, on, ...) to spread the machine's drift. Goal: ratio <= 1.05.

Run: ``.venv/bin/python benchmarks/bench_record.py`` (``--quick`` for shorter phases).
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

from bench_host import robot_with  # noqa: E402

from interop.record import McapSink  # noqa: E402
from interop.sinks import Fanout  # noqa: E402
from interop.topics import RobotTopics  # noqa: E402
from ucrdf.writer import dumps  # noqa: E402

ROBOT = REPO / "robots" / "softrobot3.ucrdf"

# A Foxglove WebSocket client subscribing to every channel; counts bytes until killed.
FOXGLOVE_CLIENT = r"""
import json, sys
from websockets.sync.client import connect
n = 0
with connect(sys.argv[1], subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
    sub = 0
    while True:
        m = ws.recv()
        if isinstance(m, str):
            msg = json.loads(m)
            if msg.get("op") == "advertise":
                chans = msg["channels"]
                subs = [{"id": sub + i, "channelId": c["id"]} for i, c in enumerate(chans)]
                sub += len(subs)
                ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
        else:
            n += len(m)
"""


def mcap_rate(n: int, seconds: float, viz_hz: float) -> tuple[float, float, int]:
    """(bytes per second of robot time, recorder CPU ms per second, messages) for ``n``
    segments, joint states at 100 Hz."""
    robot, _ = robot_with(n)
    topics = RobotTopics(robot, dumps(robot), 10)
    names = list(robot.bendables)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "bench.mcap"
        sink = McapSink(path, flush_interval=math.inf)
        out = Fanout([sink])
        t0_ns = time.time_ns()
        cpu0 = time.process_time()
        for m in topics.static_messages(t0_ns):
            out.publish(m)
        steps = int(seconds * 100)
        viz_every = max(1, round(100 / viz_hz))
        for k in range(steps):
            t = k / 100.0
            t_ns = t0_ns + int(t * 1e9)
            kappa = [1.5 + 1.2 * math.sin(0.5 * t + i) for i in range(n)]
            phi = [math.remainder(0.3 * t + i, 2 * math.pi) for i in range(n)]
            js = {"kind": "joint_states", "t": t, "names": names, "kappa": kappa, "phi": phi,
                  "kx": [a * math.cos(b) for a, b in zip(kappa, phi, strict=True)],
                  "ky": [a * math.sin(b) for a, b in zip(kappa, phi, strict=True)],
                  "valid": [True] * n, "rigid": {}}  # fmt: skip
            out.publish(topics.joint_states(js, t_ns))
            if k % viz_every == 0:
                out.publish(topics.tf(js, t_ns))
                out.publish(topics.arcs(js, t_ns))
            if k % 100 == 0:
                status = {"state": "connected", "joint_states": {
                    nm: {"kappa": kappa[i], "phi": phi[i], "valid": True}
                    for i, nm in enumerate(names)}}  # fmt: skip
                out.publish(topics.segments(status, {"segments": []}, t_ns))
                stats = {"cycles": k, "overruns": 0, "period_us": {"mean": 10000.0, "p99": 10100.0},
                         "jitter_us": {"mean": 20.0, "p99": 90.0, "max": 300.0}}  # fmt: skip
                out.publish(topics.loop_stats(stats, t_ns))
                sink.flush()  # as the recorder does every second
        cpu = time.process_time() - cpu0
        sink.close()
        size = path.stat().st_size
    return size / seconds, cpu / seconds * 1000.0, sink.messages


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def jitter_phases(phase_s: float, rounds: int) -> None:
    from tools.rig import EmulatedRig

    rig = EmulatedRig(ROBOT, boot_timeout_s=20)
    robot, daemon, srv = rig.robot, rig.daemon, rig.srv
    procs: list[subprocess.Popen] = []
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    try:
        # keep the robot moving: a slow wave on every segment, resent when it ends
        pts = [{"time_from_start": 2.0 * (k + 1), "segments": {
            n: {"kappa": 1.0 + 0.8 * math.sin(k + i), "phi": 0.5 * k} for i, n in
            enumerate(robot.bendables)}} for k in range(200)]  # fmt: skip

        def keep_moving() -> None:  # a stall under load aborts a goal: start the wave again
            if not daemon.status()["running_goals"]:
                try:
                    daemon.send_trajectory(pts)
                except Exception as exc:  # noqa: BLE001 - rebuilding: the next phase retries
                    print(f"   (wave not restarted: {exc})")

        keep_moving()
        time.sleep(3.0)
        results: dict[str, list[dict]] = {"off": [], "on": []}
        tmp = tempfile.mkdtemp()
        for r in range(rounds):
            for mode in ("off", "on"):
                keep_moving()
                if mode == "on":
                    port = free_port()
                    ucr = [sys.executable, "-m", "tools.cli"]
                    common = ["--url", srv.url, "--robot", str(ROBOT)]
                    # one API client serves both: the recorder with its Foxglove server on
                    procs = [
                        subprocess.Popen([*ucr, "record", "-o", f"{tmp}/bench{r}.mcap",
                                          "--foxglove-port", str(port), *common],
                                         cwd=REPO, env=env, stderr=subprocess.DEVNULL),
                    ]  # fmt: skip
                    time.sleep(2.0)
                    procs.append(subprocess.Popen(
                        [sys.executable, "-c", FOXGLOVE_CLIENT, f"ws://127.0.0.1:{port}"],
                        cwd=REPO, env=env, stderr=subprocess.DEVNULL))  # fmt: skip
                time.sleep(phase_s)
                st = daemon.loop_stats()
                results[mode].append(st)
                for p in procs:
                    p.send_signal(signal.SIGINT)
                for p in procs:
                    try:
                        p.wait(timeout=15)
                    except subprocess.TimeoutExpired:
                        p.kill()
                if procs:
                    size = Path(f"{tmp}/bench{r}.mcap").stat().st_size
                    print(f"   round {r + 1}: recorded {size / 1024:.0f} KiB in ~{phase_s:.0f} s "
                          f"({size / phase_s / 1024:.1f} KiB/s live, 3 segments)")  # fmt: skip
                procs = []
                time.sleep(1.0)
        print(f"{'':6s}{'jitter p99 µs per round':>28s}{'period p99 µs per round':>28s}"
              f"{'overruns':>10s}")  # fmt: skip
        p99 = {}
        for mode in ("off", "on"):
            vals = [s["jitter_us"]["p99"] for s in results[mode]]
            per = [s["period_us"]["p99"] for s in results[mode]]
            p99[mode] = sorted(vals)[len(vals) // 2]
            print(f"{mode:6s}{' / '.join(f'{v:.0f}' for v in vals):>28s}"
                  f"{' / '.join(f'{v:.0f}' for v in per):>28s}"
                  f"{results[mode][-1]['overruns']:>10d}")  # fmt: skip
        ratio = p99["on"] / p99["off"] if p99["off"] else float("inf")
        verdict = "ok" if ratio <= 1.05 else "ABOVE GOAL"
        print(f"jitter p99 median on/off: {p99['on']:.0f} / {p99['off']:.0f} µs = "
              f"{ratio:.3f}  (goal <= 1.05: {verdict})")  # fmt: skip
    finally:
        for p in procs:
            p.kill()
        rig.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter phases")
    ap.add_argument("--skip-jitter", action="store_true", help="only the file-size figures")
    args = ap.parse_args()
    seconds = 10.0 if args.quick else 30.0
    print(f"1. MCAP size, zstd, chunk per second ({seconds:.0f} s of synthetic robot time)")
    print(f"{'segments':>9s}{'viz Hz':>8s}{'KiB/s':>9s}{'MiB/hour':>10s}{'CPU ms/s':>10s}"
          f"{'msgs/s':>8s}")  # fmt: skip
    for n in (3, 8):
        for viz in (20.0, 100.0):
            rate, cpu, msgs = mcap_rate(n, seconds, viz)
            print(f"{n:9d}{viz:8.0f}{rate / 1024:9.1f}{rate * 3600 / 2**20:10.1f}{cpu:10.1f}"
                  f"{msgs / seconds:8.0f}")  # fmt: skip
    if not args.skip_jitter:
        phase = 12.0 if args.quick else 20.0
        rounds = 2 if args.quick else 3
        print(
            f"\n2. daemon loop jitter at 100 Hz, 3 emulated segments, {rounds} x ({phase:.0f} s "
            f"off, {phase:.0f} s on: ucr record --foxglove-port + a subscribed client)"
        )
        jitter_phases(phase, rounds)


if __name__ == "__main__":
    main()
